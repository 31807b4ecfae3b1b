"""Depth and scale diagnostics of an evaluation: the depth study of December 2026 made routine, so every look
measures its own depth bias. On the same detections: the signed root-depth error of DepthNet (the feed-forward
depth, which the fit's depth prior holds), of the fit without that prior (2D evidence only) and of the shipped
estimate; and the radial scale of 2D keypoints about the true centroid (the detections, both fits' projections).

report["depth_diagnostics"] (stable keys; scripts/ship_model.py copies them into model cards; None: not measured):
  shipped_method         'fitted' or 'feed-forward': the estimate the product outputs, the 'shipped' rows
  confidence_thresholds  {confident_above: 0.8, unconfident_below: 0.3}: the heatmap confidences of the
                         detected_confident and detected_unconfident rows
  root_depth_error       {depthnet, fit_no_prior, shipped} -> {n_frames, median_mm, mean_mm, abs_median_mm,
                         relative_median_percent}: predicted minus true depth (camera z) of the root keypoint over
                         the frames where that source found the robot; > 0: too far. relative: of the true depth
  add_auc                {fit_no_prior, shipped} -> ADD AUC, percent (0-100 mm; frames not found are failures)
  keypoint_scale         {detected, detected_confident, detected_unconfident, fit_no_prior, shipped} ->
                         {n_frames, median, p10, p90, error_median_px}: per frame, the least-squares s of
                         p - c = s (g - c) over the row's keypoints whose true point g is in the image (p the row's
                         point: heatmap peak or fit projection; c the centroid of all true in-image fit keypoints);
                         s < 1: shrunk towards the centroid. error_median_px: median |p - g| of those points
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from holo_pose_ros.evaluation import metrics
from holo_pose_ros.evaluation.detection import fit_keypoints_px, ground_truth_fit_keypoints
from holo_pose_ros.geometry.camera import in_image

if TYPE_CHECKING:
    from holo_pose_ros.estimator import Estimate

CONFIDENT_ABOVE = 0.8      # heatmap confidence of the detected_confident row (sharp peaks: unbiased in the study)
UNCONFIDENT_BELOW = 0.3    # ... and of the detected_unconfident row (the points the study found shrunk)
MIN_SCALE_KEYPOINTS = 3    # a row with fewer in-image keypoints in a frame gives no scale for that frame
DEPTH_SOURCES = ("depthnet", "fit_no_prior", "shipped")
FIT_SOURCES = ("fit_no_prior", "shipped")
SCALE_ROWS = ("detected", "detected_confident", "detected_unconfident", *FIT_SOURCES)
_LABELS = {"depthnet": "DepthNet", "fit_no_prior": "fit, no depth prior", "detected": "detected, all",
           "detected_confident": f"detected, conf > {CONFIDENT_ABOVE:g}",
           "detected_unconfident": f"detected, conf < {UNCONFIDENT_BELOW:g}"}


@dataclass
class DepthFrame:
    """One frame's diagnostics: root depths (metres) per DEPTH_SOURCES and ADD (metres) per FIT_SOURCES, NaN where
    not found; the scale per SCALE_ROWS (NaN: not measurable) and the 2D errors (px) of each row's points."""

    true_root_depth_m: float
    root_depth_m: dict[str, float]
    add_m: dict[str, float]
    scale: dict[str, float]
    error_px: dict[str, np.ndarray]


def radial_scale(points_px: np.ndarray, true_px: np.ndarray, centre_px: np.ndarray) -> float:
    """Least-squares scale of points (K, 2) relative to their true points (K, 2) about a centre (2,), pixels:
    argmin_s sum |(p - c) - s (g - c)|^2 = sum <p - c, g - c> / sum |g - c|^2; s < 1: shrunk towards c. NaN with
    fewer than MIN_SCALE_KEYPOINTS points or every true point at c."""
    p = np.asarray(points_px, float) - centre_px
    g = np.asarray(true_px, float) - centre_px
    spread = float(np.sum(g * g))
    if len(g) < MIN_SCALE_KEYPOINTS or spread <= 0.0:
        return float("nan")
    return float(np.sum(p * g) / spread)


def _stat(values: np.ndarray, f) -> float | None:
    """f of the finite values, None when there are none."""
    values = np.asarray(values, float)
    values = values[np.isfinite(values)]
    return float(f(values)) if values.size else None


def signed_error_summary(pred_m: np.ndarray, true_m: np.ndarray) -> dict:
    """Signed error pred - true of depths (F,) in metres over the frames where both are finite and the true depth
    positive: n_frames, median_mm, mean_mm, abs_median_mm, relative_median_percent (median of (pred - true) / true)."""
    pred, true = np.asarray(pred_m, float), np.asarray(true_m, float)
    ok = np.isfinite(pred) & np.isfinite(true) & (true > 0)
    error_m = pred[ok] - true[ok]
    return {"n_frames": int(ok.sum()), "median_mm": _stat(error_m * 1000.0, np.median),
            "mean_mm": _stat(error_m * 1000.0, np.mean), "abs_median_mm": _stat(np.abs(error_m) * 1000.0, np.median),
            "relative_median_percent": _stat(error_m / true[ok] * 100.0, np.median)}


def scale_summary(scales: np.ndarray, errors_px: np.ndarray) -> dict:
    """Median and p10 / p90 of per-frame scales (F,; NaN frames left out, n_frames the others) and the median of
    the 2D errors (px) of the points they were measured on."""
    return {"n_frames": int(np.isfinite(np.asarray(scales, float)).sum()), "median": _stat(scales, np.median),
            "p10": _stat(scales, lambda v: np.percentile(v, 10)), "p90": _stat(scales, lambda v: np.percentile(v, 90)),
            "error_median_px": _stat(errors_px, np.median)}


def _row_points(robot, K: np.ndarray, estimates: dict[str, Estimate]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each SCALE_ROW's fit keypoints (M, 2) px and which of them the row keeps (M,) bool; rows without points this
    frame (no detection, a fit that found nothing) are absent."""
    rows = {}
    shipped = estimates["shipped"]
    if shipped.detected_2d is not None:
        confidence = shipped.detected_confidence
        rows = {"detected": (shipped.detected_2d, np.ones(len(confidence), bool)),
                "detected_confident": (shipped.detected_2d, confidence > CONFIDENT_ABOVE),
                "detected_unconfident": (shipped.detected_2d, confidence < UNCONFIDENT_BELOW)}
    for source in FIT_SOURCES:
        estimate = estimates[source]
        if estimate.found:
            points = fit_keypoints_px(robot, estimate.joints, estimate.T_cam_base, K)
            rows[source] = (points, np.ones(len(points), bool))
    return rows


def _frame_scales(robot, frame, estimates: dict[str, Estimate]) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """Scale and 2D errors (px) of each SCALE_ROW in one frame, about the centroid of its true in-image fit
    keypoints (NaN and no errors where not measurable)."""
    scale = {row: float("nan") for row in SCALE_ROWS}
    errors = {row: np.zeros(0) for row in SCALE_ROWS}
    true_px = ground_truth_fit_keypoints(robot, frame)
    if true_px is None:
        return scale, errors
    inside = in_image(true_px, frame.width, frame.height)
    if not inside.any():
        return scale, errors
    centre_px = true_px[inside].mean(axis=0)
    for row, (points_px, kept) in _row_points(robot, frame.K, estimates).items():
        used = kept & inside
        scale[row] = radial_scale(points_px[used], true_px[used], centre_px)
        errors[row] = np.linalg.norm(points_px[used] - true_px[used], axis=1)
    return scale, errors


def depth_frame(robot, frame, estimates: dict[str, Estimate]) -> DepthFrame:
    """One frame's diagnostics from its estimates per DEPTH_SOURCES (all from one detection; 'depthnet' the
    feed-forward one, whose root depth is DepthNet's) and the frame's ground truth (a DreamFrame)."""
    nan = float("nan")
    depth = {s: float(estimates[s].root_depth_m) if estimates[s].found else nan for s in DEPTH_SOURCES}
    add = {s: float(metrics.add_per_frame(estimates[s].keypoints_3d[None], frame.keypoints_3d[None])[0])
           if estimates[s].found else nan for s in FIT_SOURCES}
    scale, errors = _frame_scales(robot, frame, estimates)
    return DepthFrame(float(frame.keypoints_3d[robot.root_index, 2]), depth, add, scale, errors)


def build_depth_diagnostics(frames: list[DepthFrame], shipped_method: str) -> dict:
    """The report's depth_diagnostics section (keys in the module docstring) over the frames' diagnostics."""
    true_m = np.array([f.true_root_depth_m for f in frames], float)
    add_m = {s: np.array([f.add_m[s] for f in frames], float) for s in FIT_SOURCES}
    return {
        "shipped_method": shipped_method,
        "confidence_thresholds": {"confident_above": CONFIDENT_ABOVE, "unconfident_below": UNCONFIDENT_BELOW},
        "root_depth_error": {s: signed_error_summary(np.array([f.root_depth_m[s] for f in frames], float), true_m)
                             for s in DEPTH_SOURCES},
        "add_auc": {s: metrics.add_auc(add_m[s], np.isfinite(add_m[s])) for s in FIT_SOURCES},
        "keypoint_scale": {row: scale_summary(np.array([f.scale[row] for f in frames], float),
                                              np.concatenate([np.zeros(0)] + [f.error_px[row] for f in frames]))
                           for row in SCALE_ROWS},
    }


def _fmt(value: float | None, spec: str) -> str:
    """A number for the terminal, 'n/a' for None."""
    return "n/a" if value is None else format(value, spec)


def format_depth_diagnostics(section: dict) -> list[str]:
    """Terminal lines of the depth_diagnostics section: the signed root-depth error of each source, then the 2D
    keypoint scale of each row."""
    labels = _LABELS | {"shipped": f"shipped ({section['shipped_method']})"}
    lines = ["depth, signed (predicted - true root depth; > 0: too far)",
             "  source                frames  median mm  mean mm  |err| median mm  median %  ADD AUC"]
    for source, row in section["root_depth_error"].items():
        auc = section["add_auc"].get(source)
        lines.append(f"  {labels[source]:<20}  {row['n_frames']:>6}  {_fmt(row['median_mm'], '+.1f'):>9}  "
                     f"{_fmt(row['mean_mm'], '+.1f'):>7}  {_fmt(row['abs_median_mm'], '.1f'):>15}  "
                     f"{_fmt(row['relative_median_percent'], '+.2f'):>8}  {_fmt(auc, '.2f'):>7}")
    lines += ["2D keypoint scale about the true centroid (< 1: shrunk)",
              "  points                frames  median  p10 - p90      2D error median px"]
    for name, row in section["keypoint_scale"].items():
        spread = f"{_fmt(row['p10'], '.3f')} - {_fmt(row['p90'], '.3f')}"
        lines.append(f"  {labels[name]:<20}  {row['n_frames']:>6}  {_fmt(row['median'], '.3f'):>6}  {spread:<13}  "
                     f"{_fmt(row['error_median_px'], '.1f'):>18}")
    return lines
