"""The evaluation report over a data set: per-frame results in, one JSON-serializable dict out (plain floats,
NaN as null), plus a terminal table. Means and medians are over found frames; AUC and ADD percentages count
frames where nothing was found as failures."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from holo_pose_ros.evaluation import metrics
from holo_pose_ros.evaluation.depth import format_depth_diagnostics

ADD_THRESHOLDS_MM = (10, 20, 40, 60)
# bins of the robot's apparent size (px, the larger side of its in-image keypoints' box) in the report's size table;
# a Panda 1.5 m from a 640x480 camera of 600 px focal length spans about 300 px
SIZE_BINS_PX = (0.0, 100.0, 150.0, 200.0, 300.0, float("inf"))


@dataclass
class FrameResult:
    """One frame's estimate and ground truth: metres, radians (prismatic joints metres), pixels, seconds."""

    name: str
    found: bool
    pred_keypoints_3d: np.ndarray | None  # (N, 3) camera frame
    gt_keypoints_3d: np.ndarray  # (N, 3) camera frame
    pred_joints: np.ndarray | None  # (J,)
    gt_joints: np.ndarray | None  # (J,)
    pred_R: np.ndarray | None  # (3, 3) rotation of the robot base in the camera
    gt_R: np.ndarray | None  # (3, 3)
    pred_root_depth_m: float | None
    gt_root_depth_m: float | None
    pred_uv: np.ndarray | None  # (N, 2)
    gt_uv: np.ndarray  # (N, 2)
    in_image: np.ndarray  # (N,) bool: GT keypoint inside the image
    seconds: float  # estimation time of the frame


def per_frame_add(results: list[FrameResult]) -> tuple[np.ndarray, np.ndarray]:
    """(F,) ADD in metres (NaN where not found) and (F,) found mask."""
    found = np.array([r.found for r in results], bool)
    add = np.full(len(results), np.nan)
    for i, r in enumerate(results):
        if r.found:
            if r.pred_keypoints_3d is None:
                raise ValueError(f"frame '{r.name}' is found but has no predicted keypoints")
            add[i] = metrics.add_per_frame(r.pred_keypoints_3d[None], r.gt_keypoints_3d[None])[0]
    return add, found


def _stats(values: np.ndarray) -> dict[str, float]:
    """Mean and median of the finite values (NaN when there are none)."""
    values = np.asarray(values, float)
    values = values[np.isfinite(values)]
    if values.size == 0:
        return {"mean": float("nan"), "median": float("nan")}
    return {"mean": float(values.mean()), "median": float(np.median(values))}


def _pairs(results: list[FrameResult], pred: str, gt: str) -> tuple[np.ndarray, np.ndarray]:
    """Stacked (pred, gt) attributes over the found frames where both are present (empty arrays if none)."""
    used = [r for r in results if r.found and getattr(r, pred) is not None and getattr(r, gt) is not None]
    return (np.array([getattr(r, pred) for r in used], float), np.array([getattr(r, gt) for r in used], float))


def _joint_section(results: list[FrameResult], joint_names: list[str], joint_types: list[str]) -> tuple[dict, int]:
    """The joint_error_deg dict (per joint, 'mean' deg, 'mean_mm' if prismatic, 'units') and its frame count."""
    units = {n: metrics.joint_unit(t) for n, t in zip(joint_names, joint_types)}
    pred, gt = _pairs(results, "pred_joints", "gt_joints")
    nan = float("nan")
    errors = metrics.joint_errors(pred, gt, joint_types) if len(pred) else {"per_joint": [nan] * len(joint_names)}
    section = dict(zip(joint_names, errors["per_joint"])) | {"mean": errors.get("mean_deg", nan)}
    if "mm" in units.values():
        section["mean_mm"] = errors.get("mean_mm", nan)
        units["mean_mm"] = "mm"
    return section | {"units": units | {"mean": "deg"}}, len(pred)


def _joint_symmetry_section(results: list[FrameResult], joint_names: list[str], joint_types: list[str],
                            joint_symmetry: dict[str, float]) -> dict:
    """The joint_error_modulo_symmetry_deg dict: each symmetric joint's mean error (deg) modulo its period, and
    `period_deg`. ValueError for a symmetric joint that is not angular."""
    for name in joint_symmetry:
        if metrics.joint_unit(joint_types[joint_names.index(name)]) != "deg":
            raise ValueError(f"joint symmetry: '{name}' is not a revolute or continuous joint")
    pred, gt = _pairs(results, "pred_joints", "gt_joints")
    errors = (metrics.joint_errors_modulo(pred, gt, joint_names, joint_symmetry) if len(pred)
              else {name: float("nan") for name in joint_symmetry})
    return errors | {"period_deg": {name: math.degrees(p) for name, p in joint_symmetry.items()}}


def _reprojection(results: list[FrameResult]) -> np.ndarray:
    """(F_used,) mean in-image reprojection error (px, NaN without in-image GT) of found frames with a pred_uv."""
    used = [r for r in results if r.found and r.pred_uv is not None]
    if not used:
        return np.zeros(0)
    return metrics.reprojection_error_px(np.array([r.pred_uv for r in used], float),
                                         np.array([r.gt_uv for r in used], float),
                                         np.array([r.in_image for r in used], bool))


def _keypoint_errors(results: list[FrameResult], keypoint_names: list[str]) -> dict[str, float]:
    """Median in-image 2D error (px) of each keypoint over the found frames with a pred_uv (NaN if never seen)."""
    used = [r for r in results if r.found and r.pred_uv is not None]
    if not used:
        return {name: float("nan") for name in keypoint_names}
    errors = metrics.keypoint_error_px(np.array([r.pred_uv for r in used], float),
                                       np.array([r.gt_uv for r in used], float),
                                       np.array([r.in_image for r in used], bool))
    return dict(zip(keypoint_names, errors.tolist()))


def _json_safe(value):
    """Plain Python containers and floats, NaN and infinities as None."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_json_safe(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def build_report(results: list[FrameResult], joint_names: list[str], joint_types: list[str],
                 keypoint_names: list[str], joint_symmetry: dict[str, float] | None = None) -> dict:
    """The evaluation report (ADD in mm, AUC and percentages in percent, angles in deg, fps in frames/s).
    `joint_symmetry` (joint -> period, radians; the robot YAML's) adds each such joint's error modulo its period."""
    add, found = per_frame_add(results)
    add_stats = _stats(add[found] * 1000.0)
    joint_section, n_joint = _joint_section(results, joint_names, joint_types)
    R_pred, R_gt = _pairs(results, "pred_R", "gt_R")
    depth_pred, depth_gt = _pairs(results, "pred_root_depth_m", "gt_root_depth_m")
    reproj = _reprojection(results)
    n_in_image = np.array([np.count_nonzero(r.in_image) for r in results], int)
    seconds = float(sum(r.seconds for r in results))
    report = {
        "n_frames": len(results),
        "n_not_found": int((~found).sum()),
        "n_found_for_means": int(found.sum()),
        "add_auc": metrics.add_auc(add, found),
        "add_mean_mm": add_stats["mean"],
        "add_median_mm": add_stats["median"],
        "add_below_mm": metrics.fraction_below(add, found, ADD_THRESHOLDS_MM),
        "joint_error_deg": joint_section,
        **({"joint_error_modulo_symmetry_deg": _joint_symmetry_section(results, joint_names, joint_types,
                                                                       joint_symmetry)} if joint_symmetry else {}),
        "rotation_error_deg": _stats(metrics.rotation_error_deg(R_pred, R_gt) if len(R_pred) else []),
        "depth_error_mm": _stats(metrics.depth_error_mm(depth_pred, depth_gt)),
        "reproj_error_px": _stats(reproj),
        "keypoint_error_px": _keypoint_errors(results, keypoint_names),
        "fps": len(results) / seconds if seconds > 0 else float("nan"),
        "truncation": metrics.truncation_table(add, found, n_in_image, len(keypoint_names)),
        "apparent_size": metrics.size_table(
            add, found, [metrics.apparent_size_px(r.gt_uv, r.in_image) for r in results], SIZE_BINS_PX),
        "extra": {"n_frames_used": {"joint_error": n_joint, "rotation_error": len(R_pred),
                                    "depth_error": len(depth_pred), "reproj_error": int(np.isfinite(reproj).sum())}},
    }
    return _json_safe(report)


def write_report(report: dict, path: str | Path) -> None:
    """Write the report as JSON (indent 2), creating the parent folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2, allow_nan=False) + "\n")


def _num(value: float | None, digits: int = 2) -> str:
    """A number for the terminal, 'n/a' for None."""
    return "n/a" if value is None else f"{value:.{digits}f}"


def keypoint_error_lines(report: dict, estimate: bool = True) -> list[str]:
    """Per-keypoint median 2D errors (px, in-image): of the estimate's projection (when `estimate`) and, when the
    report has them, of the network's heatmap peaks before any fit."""
    names = list(report.get("keypoint_error_px") or {})
    rows = [("estimate", list(report["keypoint_error_px"].values()) if estimate and names else None),
            ("network", report.get("kp2d_dream_median_px_per_keypoint"))]
    return [f"2D error, {label:<9} " + "  ".join(f"{n} {_num(v, 1)}" for n, v in zip(names, values)) + " px (median)"
            for label, values in rows if names and values]


def _size_bin(row: dict) -> str:
    """'100-150' or '300+' (an open last bin is null in JSON)."""
    hi = row["max_px"]
    return f"{row['min_px']:.0f}+" if hi is None or not math.isfinite(hi) else f"{row['min_px']:.0f}-{hi:.0f}"


def format_report(report: dict) -> str:
    """A compact human-readable table of the report for the terminal (with its depth diagnostics, if any)."""
    joints = report["joint_error_deg"]
    units = joints["units"]
    below = "  ".join(f"<={k}mm {_num(v, 1)}%" for k, v in report["add_below_mm"].items())
    lines = [
        f"frames              {report['n_frames']}  (not found {report['n_not_found']}, "
        f"means over {report['n_found_for_means']})",
        f"ADD AUC (0-100 mm)  {_num(report['add_auc'])}",
        f"ADD mean / median   {_num(report['add_mean_mm'])} / {_num(report['add_median_mm'])} mm",
        f"ADD                 {below}",
        f"joint error mean    {_num(joints['mean'])} deg"
        + (f"  (prismatic {_num(joints['mean_mm'])} mm)" if "mean_mm" in joints else ""),
    ]
    modulo = report.get("joint_error_modulo_symmetry_deg") or {}
    lines += [f"  {name:<18} {_num(joints[name])} {unit}"
              + (f"  ({_num(modulo[name])} modulo its {modulo['period_deg'][name]:g} deg symmetry)"
                 if name in modulo and name != "period_deg" else "")
              for name, unit in units.items() if name not in ("mean", "mean_mm")]
    for key, label, unit in (("rotation_error_deg", "rotation error", "deg"),
                             ("depth_error_mm", "root depth error", "mm"),
                             ("reproj_error_px", "reprojection error", "px")):
        lines.append(f"{label:<20}{_num(report[key]['mean'])} / {_num(report[key]['median'])} {unit} (mean / median)")
    lines += keypoint_error_lines(report)
    lines.append(f"fps                 {_num(report['fps'], 1)}")
    if report.get("n_skipped"):
        first = report["skipped"][0]
        lines.append(f"skipped malformed   {report['n_skipped']} (first: {first['file']}: field '{first['field']}': "
                     f"{first['message']})")
    lines.append("in-image kps  frames  not found  ADD AUC  ADD mean mm")
    lines += [f"{row['n_in_image']:>12}  {row['n_frames']:>6}  {row['n_not_found']:>9}  {_num(row['add_auc']):>7}  "
              f"{_num(row['add_mean_mm']):>11}" for row in report["truncation"]]
    if report.get("apparent_size"):
        lines.append("robot size px  frames  not found  ADD AUC  ADD mean mm")
        lines += [f"{_size_bin(row):>13}  {row['n_frames']:>6}  {row['n_not_found']:>9}  {_num(row['add_auc']):>7}  "
                  f"{_num(row['add_mean_mm']):>11}" for row in report["apparent_size"]]
    if report.get("depth_diagnostics"):
        lines += format_depth_diagnostics(report["depth_diagnostics"])
    return "\n".join(lines)
