"""adaptation/camera_match.py: a camera model measured from two sets of images makes rendered images' mean power
spectrum the user's: blur and noise are recovered from blurred, noisy copies of the same kind of scene; a set matched
with images like its own is left nearly as it was; image means never move."""

import cv2
import numpy as np
import pytest
import torch

from holo_pose_ros.adaptation.camera_match import CameraMatch, radial_power

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py


def scenes(n: int, seed: int, size: int = 64) -> torch.Tensor:
    """(n, 3, S, S) images in [0, 1]: random flat-coloured rectangles on a flat background (sharp edges)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        image = np.zeros((size, size, 3), np.float32) + rng.uniform(0, 1, 3).astype(np.float32)
        for _ in range(8):
            a, b = rng.integers(0, size, 2), rng.integers(0, size, 2)
            cv2.rectangle(image, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), rng.uniform(0, 1, 3).tolist(), -1)
        out.append(image.transpose(2, 0, 1))
    return torch.from_numpy(np.stack(out))


def camera(images: torch.Tensor, blur_px: float, noise: float, seed: int) -> torch.Tensor:
    """The images as a camera with a Gaussian blur of `blur_px` and white noise of std `noise` would give them."""
    blurred = np.stack([cv2.GaussianBlur(x.transpose(1, 2, 0), (0, 0), blur_px).transpose(2, 0, 1)
                        for x in images.numpy()])
    generator = torch.Generator().manual_seed(seed)
    return (torch.from_numpy(blurred) + noise * torch.randn(images.shape, generator=generator)).clamp(0, 1)


def test_rendered_views_take_the_users_spectrum_blur_and_noise():
    rendered, user = scenes(200, 0), camera(scenes(200, 1), blur_px=1.5, noise=0.03, seed=2)
    match = CameraMatch(user, rendered)
    styled = match(rendered, torch.Generator().manual_seed(3))
    p_user, p_rendered, p_styled = radial_power(user), radial_power(rendered), radial_power(styled)
    bins = slice(1, None)
    error = (p_styled[:, bins].log() - p_user[:, bins].log()).abs()
    assert float(error.max()) < 0.1                               # within 10 % at every frequency and channel
    assert float((p_rendered[:, bins].log() - p_user[:, bins].log()).abs().max()) > 1.0   # they differed
    summary = match.summary()
    assert summary["gain_at_half_nyquist"] < 0.6                   # the blur: mid frequencies attenuated
    assert 0.5 * 0.03 * 255 < summary["noise_grey_levels"] < 1.5 * 0.03 * 255   # the noise floor, 7.6 levels
    assert torch.allclose(styled.mean((2, 3)), rendered.mean((2, 3)), atol=0.01)  # means stay (clipping aside)


def test_images_like_the_renders_leave_them_nearly_unchanged():
    rendered, user = scenes(200, 0), scenes(200, 1)
    match = CameraMatch(user, rendered)
    styled = match(rendered, torch.Generator().manual_seed(3))
    assert match.summary()["noise_grey_levels"] < 1.0
    assert float((styled - rendered).abs().mean()) < 0.02


def test_crops_of_different_sizes_are_refused():
    with pytest.raises(ValueError, match="square crops of one size"):
        CameraMatch(torch.rand(4, 3, 32, 32), torch.rand(4, 3, 64, 64))
