"""2D keypoint heatmaps: Gaussian target encoding, the cross-entropy loss of the heatmap softmax, and sub-pixel
decoding with a per-keypoint confidence. Three separate functions (mmpose / SimpleBaseline style), so the decoder
can be tested on a synthetic heatmap and swapped without touching the network. Heatmap cell (i, j) is centred on
crop pixel ((j + 0.5) * S / W - 0.5, (i + 0.5) * S / H - 0.5); coordinates are crop pixels."""

from __future__ import annotations

import torch


def cell_centres(size: int, crop_size: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(size,) crop-pixel coordinate of each heatmap cell centre along one axis."""
    return (torch.arange(size, device=device, dtype=dtype) + 0.5) * crop_size / size - 0.5


def gaussian_targets(uv: torch.Tensor, size: int, crop_size: int, sigma_cells: float) -> torch.Tensor:
    """(B, K, 2) crop pixels -> (B, K, size, size) Gaussian distributions (each sums to 1) centred on the points,
    sigma in heatmap cells. Points far outside the crop give a valid but meaningless distribution: mask them in
    the loss."""
    c = cell_centres(size, crop_size, uv.device, uv.dtype)
    sigma_px = sigma_cells * crop_size / size
    gx = -((c[None, None] - uv[..., 0:1]) ** 2) / (2 * sigma_px**2)   # (B, K, W)
    gy = -((c[None, None] - uv[..., 1:2]) ** 2) / (2 * sigma_px**2)   # (B, K, H)
    log = gy[..., :, None] + gx[..., None, :]
    return torch.softmax(log.flatten(2), -1).view_as(log)


def heatmap_cross_entropy(logits: torch.Tensor, targets: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Cross-entropy between each keypoint's heatmap softmax (B, K, H, W logits) and its target distribution,
    averaged over the keypoints where `mask` (B, K) is true; 0 when none is. MSE on Gaussians stalls at the
    all-zero heatmap; this learns at once (the campaign issue's probe)."""
    log_p = torch.log_softmax(logits.flatten(2).float(), -1)
    ce = -(targets.flatten(2) * log_p).sum(-1)                          # (B, K)
    m = mask.to(ce.dtype)
    return (ce * m).sum() / m.sum().clamp(min=1.0)


def decode_heatmaps(logits: torch.Tensor, crop_size: int, window: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, K, H, W) logits -> (uv (B, K, 2) crop pixels, confidence (B, K) in [0, 1]).

    The peak is the arg-max cell, refined to sub-cell precision by the vertex of a parabola through the
    log-probabilities of the cell and its two neighbours along each axis (exact for a Gaussian-shaped peak; the
    shift is clamped to half a cell). The confidence is the softmax mass within `window` cells of the peak: a
    sharp, single peak gives ~1, an occluded or out-of-crop point a spread or flat heatmap and a low value."""
    B, K, H, W = logits.shape
    log_p = torch.log_softmax(logits.flatten(2).float(), -1).view(B, K, H, W)
    index = log_p.flatten(2).argmax(-1)
    iy, ix = index // W, index % W
    padded = torch.nn.functional.pad(log_p, (1, 1, 1, 1), mode="replicate")
    flat = padded.flatten(2)

    def at(dy: int, dx: int) -> torch.Tensor:
        return flat.gather(-1, ((iy + 1 + dy) * (W + 2) + ix + 1 + dx).unsqueeze(-1)).squeeze(-1)

    centre = at(0, 0)
    x = ix.to(log_p.dtype) + _vertex(at(0, -1), centre, at(0, 1))
    y = iy.to(log_p.dtype) + _vertex(at(-1, 0), centre, at(1, 0))
    u = (x + 0.5) * crop_size / W - 0.5
    v = (y + 0.5) * crop_size / H - 0.5
    rows = torch.arange(H, device=logits.device).view(1, 1, H, 1)
    cols = torch.arange(W, device=logits.device).view(1, 1, 1, W)
    near = ((rows - iy[..., None, None]).abs() <= window) & ((cols - ix[..., None, None]).abs() <= window)
    confidence = (log_p.exp() * near).sum((-1, -2)).clamp(0.0, 1.0)
    return torch.stack([u, v], -1), confidence


def _vertex(left: torch.Tensor, centre: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
    """Offset in (-0.5, 0.5) of the vertex of the parabola through (-1, left), (0, centre), (1, right)."""
    curvature = left - 2 * centre + right
    shift = 0.5 * (left - right) / torch.where(curvature < -1e-6, curvature, torch.full_like(curvature, -1e-6))
    return shift.clamp(-0.5, 0.5)
