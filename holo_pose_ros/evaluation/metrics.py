"""Per-frame error metrics and their summaries (HoRoPose / RoboPose protocol: every frame and every keypoint
counts; frames where nothing was found are failures at every ADD threshold). Metres and radians in, the unit
each function names out."""

from __future__ import annotations

import numpy as np

from holo_pose_ros.monitoring.joints import wrap_to_period

_ANGULAR_TYPES = ("revolute", "continuous")


def add_per_frame(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(F,) mean over the N keypoints of the Euclidean distance between (F,N,3) pred and gt, metres."""
    return np.linalg.norm(np.asarray(pred, float) - np.asarray(gt, float), axis=-1).mean(axis=-1)


def _found_mask(add_m: np.ndarray, found: np.ndarray | None) -> np.ndarray:
    """(F,) bool: `found`, or all True when None."""
    return np.ones(len(add_m), bool) if found is None else np.asarray(found, bool)


def add_accuracy_curve(add_m: np.ndarray, found: np.ndarray | None = None, max_m: float = 0.1,
                       step_m: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:
    """Thresholds np.arange(0, max_m, step_m) (metres) and the fraction (0..1) of ALL frames found with ADD <= each."""
    add_m = np.asarray(add_m, float)
    thresholds = np.arange(0.0, max_m, step_m)
    if len(add_m) == 0:
        return thresholds, np.zeros_like(thresholds)
    hits = np.sort(add_m[_found_mask(add_m, found)])
    return thresholds, np.searchsorted(hits, thresholds, side="right") / len(add_m)


def add_auc(add_m: np.ndarray, found: np.ndarray | None = None, max_m: float = 0.1, step_m: float = 1e-5) -> float:
    """Area under the ADD accuracy curve from 0 to max_m, normalised by max_m, in percent (0..100)."""
    _, acc = add_accuracy_curve(add_m, found, max_m, step_m)
    return float(np.trapezoid(acc, dx=step_m) / max_m * 100.0)


def fraction_below(add_m: np.ndarray, found: np.ndarray | None = None,
                   thresholds_mm: tuple[float, ...] = (10, 20, 40, 60)) -> dict[str, float]:
    """Percent of ALL frames found with ADD <= t, keyed by t in millimetres ('10', '20', ...)."""
    add_m = np.asarray(add_m, float)
    ok = _found_mask(add_m, found)
    n = max(len(add_m), 1)
    return {f"{t:g}": float(np.sum(ok & (add_m <= t / 1000.0)) / n * 100.0) for t in thresholds_mm}


def joint_unit(joint_type: str) -> str:
    """'deg' for revolute/continuous joints, 'mm' for prismatic ones; ValueError for any other URDF joint type."""
    if joint_type in _ANGULAR_TYPES:
        return "deg"
    if joint_type == "prismatic":
        return "mm"
    raise ValueError(f"unsupported joint type '{joint_type}' (revolute, continuous or prismatic)")


def joint_errors(pred_q: np.ndarray, gt_q: np.ndarray, joint_types: list[str]) -> dict:
    """Mean |q_pred - q_gt| per joint ('per_joint', list): revolute/continuous in degrees, prismatic in millimetres;
    'mean_deg' over revolute joints and 'mean_mm' over prismatic ones, each absent when there are none."""
    per_joint = np.abs(np.asarray(pred_q, float) - np.asarray(gt_q, float)).reshape(-1, len(joint_types)).mean(axis=0)
    angular = np.array([joint_unit(t) == "deg" for t in joint_types], bool)
    per_joint = np.where(angular, np.degrees(per_joint), per_joint * 1000.0)
    out: dict = {"per_joint": [float(e) for e in per_joint]}
    if angular.any():
        out["mean_deg"] = float(per_joint[angular].mean())
    if (~angular).any():
        out["mean_mm"] = float(per_joint[~angular].mean())
    return out


def joint_errors_modulo(pred_q: np.ndarray, gt_q: np.ndarray, joint_names: list[str],
                        periods_rad: dict[str, float]) -> dict[str, float]:
    """Mean |q_pred - q_gt| in degrees of each joint named in `periods_rad` (joint -> radians), the difference taken
    modulo the joint's period (wrapped to (-period/2, period/2], as the joint-state monitor wraps it): the error that remains when a joint's distal links
    look the same after that turn (a hand's roll), so that no image can tell the rest."""
    diff = (np.asarray(pred_q, float) - np.asarray(gt_q, float)).reshape(-1, len(joint_names))
    out = {}
    for name, period in periods_rad.items():
        d = diff[:, joint_names.index(name)]
        out[name] = float(np.degrees(np.abs(wrap_to_period(d, period)).mean())) if len(d) else float("nan")
    return out


def rotation_error_deg(R_pred: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """(F,) geodesic angle of R_pred^T R_gt for (F,3,3) rotations, degrees in [0, 180]."""
    trace = np.einsum("fij,fij->f", np.asarray(R_pred, float), np.asarray(R_gt, float))
    return np.degrees(np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)))


def depth_error_mm(pred_depth_m: np.ndarray, gt_depth_m: np.ndarray) -> np.ndarray:
    """(F,) absolute depth error, millimetres, from depths in metres."""
    return np.abs(np.asarray(pred_depth_m, float) - np.asarray(gt_depth_m, float)) * 1000.0


def reprojection_error_px(pred_uv: np.ndarray, gt_uv: np.ndarray, in_image: np.ndarray) -> np.ndarray:
    """(F,) mean pixel distance over the keypoints whose GT lies in the image; NaN for frames with none."""
    dist = np.linalg.norm(np.asarray(pred_uv, float) - np.asarray(gt_uv, float), axis=-1)
    mask = np.asarray(in_image, bool)
    count = mask.sum(axis=-1)
    total = np.where(mask, dist, 0.0).sum(axis=-1)
    return np.divide(total, count, out=np.full(len(count), np.nan), where=count > 0)


def keypoint_error_px(pred_uv: np.ndarray, gt_uv: np.ndarray, in_image: np.ndarray) -> np.ndarray:
    """(N,) median pixel distance of each keypoint over the frames (F, N) where its GT lies in the image; NaN for a
    keypoint never in the image. Says which links the 2D evidence gets wrong (distal ones, occluded ones)."""
    dist = np.linalg.norm(np.asarray(pred_uv, float) - np.asarray(gt_uv, float), axis=-1)
    dist = np.where(np.asarray(in_image, bool), dist, np.nan)
    out = np.full(dist.shape[-1], np.nan)
    seen = np.isfinite(dist).any(axis=0)
    out[seen] = np.nanmedian(dist[:, seen], axis=0)
    return out


def truncation_table(add_m: np.ndarray, found: np.ndarray | None, n_in_image: np.ndarray,
                     n_keypoints: int) -> list[dict]:
    """One row per number of in-image GT keypoints present (ascending): n_frames, add_auc (percent),
    add_mean_mm over found frames (NaN if none) and n_not_found, as in HoRoPose supplementary S2.2."""
    add_m = np.asarray(add_m, float)
    ok = _found_mask(add_m, found)
    counts = np.asarray(n_in_image, int)
    if counts.size and (counts.min() < 0 or counts.max() > n_keypoints):
        raise ValueError(f"in-image keypoint counts must lie in 0..{n_keypoints}")
    return [{"n_in_image": int(k), **_group_row(add_m, ok, counts == k)} for k in np.unique(counts)]


def apparent_size_px(gt_uv: np.ndarray, in_image: np.ndarray) -> float:
    """The robot's apparent size in one frame, pixels: the larger side of the bounding box of its in-image
    ground-truth keypoints (0 with fewer than two in the image)."""
    uv = np.asarray(gt_uv, float)[np.asarray(in_image, bool)]
    return float((uv.max(axis=0) - uv.min(axis=0)).max()) if len(uv) >= 2 else 0.0


def size_table(add_m: np.ndarray, found: np.ndarray | None, size_px: np.ndarray,
               edges_px: tuple[float, ...]) -> list[dict]:
    """One row per apparent-size bin [edges_px[i], edges_px[i+1]) that holds frames (ascending): min_px, max_px,
    n_frames, add_auc (percent), add_mean_mm over found frames (NaN if none) and n_not_found. A far camera sees a
    small robot: this says from what size on the estimate is useful."""
    add_m = np.asarray(add_m, float)
    ok = _found_mask(add_m, found)
    size_px = np.asarray(size_px, float)
    if len(edges_px) < 2 or np.any(np.diff(edges_px) <= 0):
        raise ValueError(f"size bin edges must be at least two increasing values, got {list(edges_px)}")
    bins = [(lo, hi, (size_px >= lo) & (size_px < hi)) for lo, hi in zip(edges_px[:-1], edges_px[1:])]
    return [{"min_px": float(lo), "max_px": float(hi), **_group_row(add_m, ok, sel)} for lo, hi, sel in bins if sel.any()]


def _group_row(add_m: np.ndarray, ok: np.ndarray, sel: np.ndarray) -> dict:
    """A table row of the frames `sel`: n_frames, add_auc (percent; frames not found count as failures), add_mean_mm
    over the found ones (NaN if none) and n_not_found."""
    found_add = add_m[sel & ok]
    return {"n_frames": int(sel.sum()), "add_auc": add_auc(add_m[sel], ok[sel]),
            "add_mean_mm": float(found_add.mean() * 1000.0) if found_add.size else float("nan"),
            "n_not_found": int((sel & ~ok).sum())}
