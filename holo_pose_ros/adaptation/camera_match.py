"""Rendered views made to look as if the user's camera had taken them: a statistical model of what that camera does
to an image, measured from the user's own crops alone. Per colour channel and radial spatial frequency, the mean
power of the user's crops against that of rendered crops gives the camera's transfer: where the user's images hold
less power (blur, a lower-resolution sensor, compression), rendered views are attenuated by the square root of
the ratio of the two scenes' power (each set's white noise, measured in the image, taken off first); noise of
random phase then makes up the power the filtered views still lack (the user's sensor noise, mostly). Each
image's mean stays as it is (colour statistics are the BatchNorm step's). No label and no description of any look:
only the two sets of images."""

from __future__ import annotations

import torch

MAX_GAIN = 1.5       # largest amplitude gain: more of the user's power at a frequency is taken for noise
MIN_GAIN = 0.02      # smallest amplitude gain (a frequency the user's camera all but removes)
CHUNK = 64           # images per FFT batch (memory)


def _radius_index(size: int) -> torch.Tensor:
    """(S, S // 2 + 1) radial frequency bin of each rfft2 coefficient of an S x S image, in cycles per image
    (rounded; the corners beyond S / 2 share the last bin)."""
    fy = torch.fft.fftfreq(size) * size
    fx = torch.fft.rfftfreq(size) * size
    r = torch.sqrt(fy[:, None] ** 2 + fx[None, :] ** 2).round().long()
    return r.clamp_max(size // 2)


def radial_power(images: torch.Tensor) -> torch.Tensor:
    """(3, S // 2 + 1) mean power |F|^2 of (N, 3, S, S) images (values in [0, 1]) per channel and radial frequency
    bin, each image's mean removed first."""
    size = images.shape[-1]
    index = _radius_index(size).flatten()
    counts = torch.bincount(index, minlength=size // 2 + 1).double()
    total = torch.zeros(images.shape[1], size // 2 + 1, dtype=torch.float64)
    for i in range(0, len(images), CHUNK):
        x = images[i:i + CHUNK].float()
        power = torch.fft.rfft2(x - x.mean((2, 3), keepdim=True)).abs().square().sum(0)   # (3, S, S//2+1)
        total += torch.stack([torch.bincount(index, weights=p.flatten().double(), minlength=size // 2 + 1)
                              for p in power])
    return total / counts / max(len(images), 1)


def noise_sigma(images: torch.Tensor) -> torch.Tensor:
    """(3,) standard deviation of white noise in (N, 3, S, S) images, per channel: the median absolute response
    of the Laplacian-difference kernel [[1, -2, 1], [-2, 4, -2], [1, -2, 1]] (norm 6), which cancels smooth
    content, scaled to a Gaussian's sigma (1.4826); the median ignores the few pixels on edges."""
    kernel = torch.tensor([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]]).expand(3, 1, 3, 3)
    responses = [torch.nn.functional.conv2d(images[i:i + CHUNK].float(), kernel, groups=3).abs()
                 .transpose(0, 1).reshape(3, -1) for i in range(0, len(images), CHUNK)]
    every = torch.cat(responses, dim=1)
    sample = every[:, torch.randperm(every.shape[1], generator=torch.Generator().manual_seed(0))[:1_000_000]]
    return 1.4826 * sample.median(dim=1).values.double() / 6.0


class CameraMatch:
    """Callable (B, 3, S, S) rendered images in [0, 1] -> the same, filtered and with noise added so that their mean
    power spectrum is the user's (the module docstring)."""

    def __init__(self, user: torch.Tensor, rendered: torch.Tensor):
        if user.shape[1:] != rendered.shape[1:] or user.shape[-1] != user.shape[-2]:
            raise ValueError(f"camera match needs square crops of one size, got {tuple(user.shape[1:])} and "
                             f"{tuple(rendered.shape[1:])}")
        self.size = user.shape[-1]
        self.user_power, self.rendered_power = radial_power(user), radial_power(rendered)
        # white sensor noise has a flat spectrum, S^2 sigma^2 per coefficient; what lies above it is the scene
        self.user_noise, self.rendered_noise = noise_sigma(user), noise_sigma(rendered)          # (3,)
        signal_user = (self.user_power - (self.user_noise ** 2 * self.size ** 2)[:, None]).clamp_min(0.0)
        signal_rendered = (self.rendered_power - (self.rendered_noise ** 2 * self.size ** 2)[:, None]).clamp_min(1e-12)
        self.gain = (signal_user / signal_rendered).sqrt().clamp(MIN_GAIN, MAX_GAIN)              # (3, R)
        self.noise_power = (self.user_power - self.gain.square() * self.rendered_power).clamp_min(0.0)
        self._index = _radius_index(self.size)

    def __call__(self, images: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        x = images.float()
        mean = x.mean((2, 3), keepdim=True)
        gain = self.gain.float()[:, self._index]                                          # (3, S, S//2+1)
        spectrum = torch.fft.rfft2(x - mean) * gain
        # white noise of unit variance has E|F|^2 = S^2 per coefficient: scale it to the missing power
        white = torch.randn(x.shape, generator=generator)
        amplitude = (self.noise_power.float()[:, self._index] / self.size ** 2).sqrt()
        spectrum = spectrum + torch.fft.rfft2(white) * amplitude
        out = torch.fft.irfft2(spectrum, s=x.shape[-2:]) + mean
        return out.clamp(0.0, 1.0).to(images.dtype)

    def summary(self) -> dict:
        """What the camera looks like against the renderer, for the card: the amplitude gain at a quarter and at
        half the Nyquist frequency, and the noise added (grey levels, the standard deviation over the image)."""
        R = self.gain.shape[1] - 1
        grey = torch.full((4, 3, self.size, self.size), 0.5)
        noise = self(grey, torch.Generator().manual_seed(0)) - grey      # the added noise alone, on mid-grey
        return {"gain_at_quarter_nyquist": round(float(self.gain[:, R // 4].mean()), 3),
                "gain_at_half_nyquist": round(float(self.gain[:, R // 2].mean()), 3),
                "gain_at_nyquist": round(float(self.gain[:, R].mean()), 3),
                "noise_grey_levels": round(255.0 * float(noise.std()), 2)}
