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


def heatmap_flatness(logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """KL divergence from the uniform distribution to each keypoint's heatmap softmax (B, K, H, W logits), averaged
    over the keypoints where `mask` (B, K) is true; 0 for flat heatmaps, 0 when none is masked. For points the view
    cannot show (outside the image): a flat heatmap has no peak, so its decoded confidence is ~0 and the fit gives
    the guess no weight, where a heatmap left untrained peaks anywhere."""
    log_p = torch.log_softmax(logits.flatten(2).float(), -1)
    kl = -log_p.mean(-1) - torch.log(torch.tensor(float(log_p.shape[-1]), device=logits.device))   # (B, K)
    return torch.where(mask, kl, torch.zeros_like(kl)).sum() / mask.sum().clamp(min=1).to(kl.dtype)


def expected_positions(logits: torch.Tensor, crop_size: int) -> torch.Tensor:
    """(B, K, H, W) logits -> (B, K, 2) crop pixels: the expectation of each heatmap's softmax (soft-argmax). A
    loss on it (integral regression) makes the decoded position unbiased, where the cross-entropy alone rewards
    any peaked distribution near the point."""
    B, K, H, W = logits.shape
    p = torch.softmax(logits.flatten(2).float(), -1).view(B, K, H, W)
    x = (p.sum(2) * cell_centres(W, crop_size, logits.device)).sum(-1)
    y = (p.sum(3) * cell_centres(H, crop_size, logits.device)).sum(-1)
    return torch.stack([x, y], -1)


def decode_heatmaps(logits: torch.Tensor, crop_size: int, window: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, K, H, W) logits -> (uv (B, K, 2) crop pixels, confidence (B, K) in [0, 1]).

    The peak is the arg-max cell, refined to sub-cell precision by the vertex of a parabola through the
    log-probabilities of three neighbouring cells along each axis (exact for a Gaussian-shaped peak). At the
    map's border the three cells are the border cell and the two inside it, and the vertex may lie up to 1.5 cells
    beyond the border: a point truncated by the crop's edge decodes where it is, not pulled half a cell inwards
    (padding by replication did that, a bias towards the crop's centre). Elsewhere the shift is clamped to half a
    cell. The confidence is the softmax mass within `window` cells of the peak: a sharp, single peak gives ~1, an
    occluded or out-of-crop point a spread or flat heatmap and a low value."""
    B, K, H, W = logits.shape
    log_p = torch.log_softmax(logits.flatten(2).float(), -1).view(B, K, H, W)
    index = log_p.flatten(2).argmax(-1)
    iy, ix = index // W, index % W
    x = _refine(log_p, iy, ix, W, axis=-1)
    y = _refine(log_p, iy, ix, H, axis=-2)
    u = (x + 0.5) * crop_size / W - 0.5
    v = (y + 0.5) * crop_size / H - 0.5
    rows = torch.arange(H, device=logits.device).view(1, 1, H, 1)
    cols = torch.arange(W, device=logits.device).view(1, 1, 1, W)
    near = ((rows - iy[..., None, None]).abs() <= window) & ((cols - ix[..., None, None]).abs() <= window)
    confidence = (log_p.exp() * near).sum((-1, -2)).clamp(0.0, 1.0)
    return torch.stack([u, v], -1), confidence


def _refine(log_p: torch.Tensor, iy: torch.Tensor, ix: torch.Tensor, n: int, axis: int) -> torch.Tensor:
    """Sub-cell position (cells) along `axis` (-1: columns, -2: rows, length n >= 3) of each arg-max (iy, ix):
    the parabola vertex through the cells centre - 1, centre, centre + 1, the centre moved inside the map at a
    border; clamped to the peak cell +- 0.5, or to 1.5 cells beyond the map where the peak is on its border."""
    W = log_p.shape[-1]
    flat = log_p.flatten(2)
    peak = ix if axis == -1 else iy
    centre = peak.clamp(1, n - 2)
    step = 1 if axis == -1 else W

    def at(offset: int) -> torch.Tensor:
        index = (iy * W + ix) + (centre - peak + offset) * step
        return flat.gather(-1, index.unsqueeze(-1)).squeeze(-1)

    left, mid, right = at(-1), at(0), at(1)
    curvature = left - 2 * mid + right
    shift = 0.5 * (left - right) / torch.where(curvature < -1e-6, curvature, torch.full_like(curvature, -1e-6))
    position = centre.to(log_p.dtype) + shift
    low = torch.where(peak == 0, -1.5, peak - 0.5).to(log_p.dtype)
    high = torch.where(peak == n - 1, n + 0.5, peak + 0.5).to(log_p.dtype)
    return torch.minimum(torch.maximum(position, low), high)
