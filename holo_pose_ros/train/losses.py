"""Supervised losses (paper §3.5, reference §5.1), each masked to the samples it applies to: 3D terms on `crop`
views, 2D keypoints on every view with a robot (`close_up` views too), presence on all. Metres, crop pixels / S, normalized joints."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from holo_pose_ros.data.training import MODES
from holo_pose_ros.model.heatmaps import expected_positions, gaussian_targets, heatmap_cross_entropy, heatmap_flatness

CROP, FULL, NEGATIVE, CLOSE_UP = (MODES.index(m) for m in ("crop", "full", "negative", "close_up"))


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of `values` where `mask` (same leading shape) is true; 0 (with gradient) when nothing is."""
    mask = mask.to(values.dtype)
    while mask.ndim < values.ndim:
        mask = mask.unsqueeze(-1)
    return (values * mask).sum() / mask.expand_as(values).sum().clamp(min=1.0)


def project_batch(points: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(B, N, 3) camera points -> (B, N, 2) pixels through (B, 3, 3) K; depth clamped to 1 cm."""
    p = points @ K.transpose(1, 2)
    return p[..., :2] / p[..., 2:3].clamp(min=0.01)


def mask_loss(mask_logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy of the (B, 1, h, w) robot-foreground logits against each cell's robot fraction of the
    (B, S, S) bool mask at the input's resolution (training views' masks and adaptation's rendered silhouettes)."""
    logits = mask_logits[:, 0].float()
    target = F.adaptive_avg_pool2d(mask.float()[:, None], logits.shape[-2:])[:, 0]
    return F.binary_cross_entropy_with_logits(logits, target)


def supervised_losses(out: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], joint_mid: torch.Tensor,
                      joint_half: torch.Tensor, crop_size: int, heatmap_sigma: float = 1.0) -> dict[str, torch.Tensor]:
    """Every loss term (unweighted) of one batch: network output (with `add_kinematics`) against the targets.
    `heatmap` (cross-entropy of the fit keypoints' 2D heatmaps, every view with a robot, in-crop points),
    `heatmap_out_of_view` (their flatness where the view cannot show them: outside the image or the crop) and
    `fit_coord` (L1 of their soft-argmax, heatmap cells) are there when the network has fit heatmaps; `mask`
    (binary cross-entropy of the robot foreground against each cell's robot fraction, every view) with a
    segmentation head."""
    mode, crop = batch["mode"], batch["mode"] == CROP
    robot = mode != NEGATIVE
    visible = batch["visible"] & robot[:, None]
    gt_norm = (batch["joints"] - joint_mid) / joint_half
    P = batch["keypoints_3d"]
    kp_fk, kp_reg = out["keypoints_fk"].float(), out["keypoints_reg"]
    uv_fk = project_batch(kp_fk, batch["K_crop"])
    extra = {}
    if "heatmap_logits" in out:
        logits = out["heatmap_logits"]
        targets = gaussian_targets(batch["uv_fit"], logits.shape[-1], crop_size, heatmap_sigma)
        seen = batch["visible_fit"] & robot[:, None]
        extra["heatmap"] = heatmap_cross_entropy(logits, targets, seen)
        extra["heatmap_out_of_view"] = heatmap_flatness(logits, ~batch["visible_fit"] & robot[:, None])
        cell_px = crop_size / logits.shape[-1]
        extra["fit_coord"] = _masked_mean((expected_positions(logits, crop_size) - batch["uv_fit"]).abs().sum(-1) / cell_px, seen)
    if "mask_logits" in out:
        extra["mask"] = mask_loss(out["mask_logits"], batch["mask"])
    return {**extra,
        "joints": _masked_mean(F.smooth_l1_loss(out["joints_norm"], gt_norm, reduction="none", beta=0.1), crop),
        "rotation": _masked_mean((out["R"] - batch["R_root"]).square().sum((1, 2)), crop),
        "translation": _masked_mean((out["t"] - batch["t_root"]).norm(dim=-1), crop),
        "depth": _masked_mean((out["depth"] - batch["t_root"][:, 2]).abs(), crop),
        "kp2d_reg": _masked_mean((out["uv"] - batch["uv"]).norm(dim=-1) / crop_size, visible),
        "kp3d_reg": _masked_mean((kp_reg - P).norm(dim=-1).mean(1), crop),
        "kp2d_fk": _masked_mean(((uv_fk - batch["uv"]).norm(dim=-1) / crop_size).clamp(max=1.0), visible & crop[:, None]),
        "kp3d_fk": _masked_mean((kp_fk - P).norm(dim=-1).mean(1), crop),
        "presence": F.binary_cross_entropy_with_logits(out["presence_logit"], batch["presence"]),
    }


def total_loss(terms: dict[str, torch.Tensor], weights: dict[str, float]) -> torch.Tensor:
    """Weighted sum of the terms named in `weights` (a stage's loss)."""
    return sum(weights[k] * terms[k] for k in weights if weights[k])
