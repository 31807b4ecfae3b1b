"""Heatmap target encoding, decoding and loss (model/heatmaps.py), each on its own synthetic heatmaps."""

import math

import torch

from holo_pose_ros.model.heatmaps import decode_heatmaps, gaussian_targets, heatmap_cross_entropy, heatmap_flatness

SIZE, CROP = 48, 192


def random_points(n: int, margin: float = 12.0, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (margin + torch.rand(1, n, 2, generator=g, dtype=torch.float64) * (CROP - 2 * margin))


def test_targets_are_distributions_peaked_at_the_points():
    uv = random_points(20)
    t = gaussian_targets(uv, SIZE, CROP, 1.0)
    assert t.shape == (1, 20, SIZE, SIZE)
    torch.testing.assert_close(t.sum((-1, -2)), torch.ones(1, 20, dtype=t.dtype))
    peak = t.flatten(2).argmax(-1)
    cell = CROP / SIZE
    centres = torch.stack([(peak % SIZE + 0.5) * cell - 0.5, (peak // SIZE + 0.5) * cell - 0.5], -1)
    assert ((centres - uv).abs() <= cell / 2 + 1e-9).all()


def test_decoder_recovers_a_synthetic_peak_to_a_tenth_of_a_pixel():
    uv = random_points(200, seed=1)
    for sigma, scale in ((1.0, 1.0), (1.5, 3.0), (2.0, 0.5)):  # a network's logits: any positive scale of log p
        logits = scale * torch.log(gaussian_targets(uv, SIZE, CROP, sigma))
        decoded, confidence = decode_heatmaps(logits, CROP)
        error = (decoded - uv).norm(dim=-1)
        assert error.max() < 0.1, (sigma, scale, float(error.max()))
    assert confidence.shape == (1, 200)


def test_confidence_is_high_for_a_sharp_peak_and_low_for_a_flat_heatmap():
    uv = random_points(5, seed=2)
    _, sharp = decode_heatmaps(torch.log(gaussian_targets(uv, SIZE, CROP, 1.0)), CROP)
    _, flat = decode_heatmaps(torch.zeros(1, 5, SIZE, SIZE), CROP)
    _, wide = decode_heatmaps(torch.log(gaussian_targets(uv, SIZE, CROP, 8.0)), CROP)
    assert (sharp > 0.95).all()
    assert (flat < 25 / SIZE**2 + 1e-6).all()
    assert (wide < 0.3).all()


def test_cross_entropy_is_lowest_at_the_target_and_ignores_masked_points():
    uv = random_points(6, seed=3)
    target = gaussian_targets(uv, SIZE, CROP, 1.0)
    mask = torch.ones(1, 6, dtype=torch.bool)
    exact = heatmap_cross_entropy(torch.log(target + 1e-30), target, mask)
    shifted = heatmap_cross_entropy(torch.log(gaussian_targets(uv + 6.0, SIZE, CROP, 1.0) + 1e-30), target, mask)
    uniform = heatmap_cross_entropy(torch.zeros_like(target), target, mask)
    assert exact < shifted < uniform
    assert math.isclose(float(uniform), math.log(SIZE * SIZE), rel_tol=1e-5)
    half = mask.clone()
    half[0, 3:] = False
    garbage = torch.log(target + 1e-30).clone()
    garbage[0, 3:] = torch.randn(3, SIZE, SIZE) * 10
    first_three = heatmap_cross_entropy(torch.log(target[:, :3] + 1e-30), target[:, :3], mask[:, :3])
    torch.testing.assert_close(heatmap_cross_entropy(garbage, target, half), first_three, rtol=1e-6, atol=1e-6)
    assert float(heatmap_cross_entropy(garbage, target, torch.zeros_like(mask))) == 0.0


def test_cross_entropy_learns_a_point_by_gradient_descent():
    """The loss's gradient moves a free heatmap's decoded peak onto the target (no stalling at zero)."""
    uv = torch.tensor([[[70.3, 121.8]]])
    target = gaussian_targets(uv, SIZE, CROP, 1.0)
    logits = torch.zeros(1, 1, SIZE, SIZE, requires_grad=True)
    optimizer = torch.optim.Adam([logits], lr=0.5)
    for _ in range(60):
        optimizer.zero_grad()
        heatmap_cross_entropy(logits, target, torch.ones(1, 1, dtype=torch.bool)).backward()
        optimizer.step()
    decoded, confidence = decode_heatmaps(logits.detach(), CROP)
    assert (decoded - uv).norm() < 1.0 and confidence.item() > 0.8


def test_decoder_is_unbiased_at_and_beyond_the_crop_border():
    """Blobs at known sub-pixel positions along the border, on it and truncated by it (centres up to one cell
    outside the crop): the decoded position's mean bias stays below 0.05 cell on each axis (the depth issue's
    bound; padding by replication pulled border points up to half a cell inwards)."""
    cell = CROP / SIZE
    g = torch.Generator().manual_seed(5)
    offsets = torch.rand(400, generator=g, dtype=torch.float64) * 3.0 - 1.0      # cells from the first cell centre
    along = 12.0 + torch.rand(400, generator=g, dtype=torch.float64) * (CROP - 24.0)
    first = 0.5 * cell - 0.5                                                      # crop px of the first cell centre
    for side in range(4):
        across = first + offsets * cell if side < 2 else (CROP - 1 - first) - offsets * cell
        uv = torch.stack([across, along], -1) if side % 2 == 0 else torch.stack([along, across], -1)
        for sigma in (1.0, 1.5):
            decoded, _ = decode_heatmaps(torch.log(gaussian_targets(uv[None], SIZE, CROP, sigma)), CROP)
            bias_cells = ((decoded[0] - uv) / cell).mean(0).abs()
            worst_cells = ((decoded[0] - uv) / cell).abs().max()
            assert (bias_cells < 0.05).all(), (side, sigma, bias_cells)
            assert worst_cells < 0.1, (side, sigma, float(worst_cells))


def test_flatness_is_zero_for_a_flat_heatmap_and_teaches_an_unseen_point_a_low_confidence():
    """heatmap_flatness: 0 on a flat map, positive on a peaked one, masked points ignored; gradient descent on it
    turns a confident peak (a point the view cannot show) into a map whose decoded confidence is near 0."""
    flat = torch.zeros(1, 2, SIZE, SIZE)
    peaked = torch.log(gaussian_targets(random_points(2), SIZE, CROP, 1.0) + 1e-12)
    everywhere = torch.ones(1, 2, dtype=torch.bool)
    assert abs(float(heatmap_flatness(flat, everywhere))) < 1e-6
    assert float(heatmap_flatness(peaked, everywhere)) > 1.0
    assert float(heatmap_flatness(peaked, torch.zeros(1, 2, dtype=torch.bool))) == 0.0
    logits = peaked.clone().requires_grad_(True)
    assert float(decode_heatmaps(logits.detach(), CROP)[1].min()) > 0.9
    optimizer = torch.optim.SGD([logits], lr=50.0)
    for _ in range(100):
        optimizer.zero_grad()
        heatmap_flatness(logits, everywhere).backward()
        optimizer.step()
    assert float(decode_heatmaps(logits.detach(), CROP)[1].max()) < 0.05
