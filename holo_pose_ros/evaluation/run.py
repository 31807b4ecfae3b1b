"""Run the deployed estimator over a DREAM folder (no ground truth reaches it, except the true joints in
known-joints mode) and score it."""

from __future__ import annotations

import time

import numpy as np
from tqdm import tqdm

from holo_pose_ros.data.dream import DreamFormatError, DreamReader
from holo_pose_ros.estimator import METHODS, Estimate, Estimator
from holo_pose_ros.evaluation.depth import DepthFrame, build_depth_diagnostics, depth_frame, format_depth_diagnostics
from holo_pose_ros.evaluation.detection import ground_truth_fit_keypoints, keypoint_errors_px, summarize_2d
from holo_pose_ros.evaluation.report import FrameResult, build_report, keypoint_error_lines


def frame_result(frame, estimate: Estimate, seconds: float, robot) -> FrameResult:
    """Pair one estimate with its frame's ground truth."""
    root = robot.root_index
    gt_R = None if frame.T_cam_base is None else frame.T_cam_base[:3, :3]
    found = estimate.found
    return FrameResult(
        name=frame.name, found=found,
        pred_keypoints_3d=estimate.keypoints_3d if found else None, gt_keypoints_3d=frame.keypoints_3d,
        pred_joints=estimate.joints if found else None, gt_joints=frame.joints,
        pred_R=estimate.T_cam_base[:3, :3] if found else None, gt_R=gt_R,
        pred_root_depth_m=float(estimate.keypoints_3d[root, 2]) if found else None,
        gt_root_depth_m=float(frame.keypoints_3d[root, 2]),
        pred_uv=estimate.keypoints_2d if found else None, gt_uv=frame.keypoints_2d, in_image=frame.in_image,
        seconds=seconds,
    )


def depth_sources(estimator: Estimator, detection, K: np.ndarray, known_joints: np.ndarray | None,
                  estimates: dict[str, Estimate]) -> dict[str, Estimate]:
    """One detection's estimates per DEPTH_SOURCES (evaluation/depth.py): DepthNet's (the feed-forward one of
    `estimates`), the fit without the depth prior (2D evidence only; fitted here) and the shipped one."""
    no_prior = estimator.estimate_detection(detection, K, known_joints, ("fitted",), depth_prior=False,
                                            static_camera_step=False)["fitted"]  # a second look: not the stream's
    return {"depthnet": estimates["feed-forward"], "fit_no_prior": no_prior,
            "shipped": estimates[estimator.method(calibrating=False)]}


def diagnosed_estimate(estimator: Estimator, image: np.ndarray, K: np.ndarray, known_joints: np.ndarray | None
                       ) -> tuple[Estimate, float, dict[str, Estimate]]:
    """One untracked frame: the shipped estimate (exactly what `estimate` returns), its seconds, and the estimates
    of the same detection per DEPTH_SOURCES (the fit without the depth prior run after the timing)."""
    timings, start = {}, time.perf_counter()
    method = estimator.method(calibrating=False)
    detection = estimator.detect(image, K, timings)
    methods = tuple(dict.fromkeys(("feed-forward", method)))
    estimates = estimator.estimate_detection(detection, K, known_joints, methods, timings=timings, start=start)
    seconds = time.perf_counter() - start
    return estimates[method], seconds, depth_sources(estimator, detection, K, known_joints, estimates)


def _wants_depth_diagnostics(estimator: Estimator, depth_diagnostics: bool | None) -> bool:
    """Whether evaluate_folder runs the depth diagnostics: by default unless the estimator tracks (they take apart
    `estimate` into its untracked steps, detection and fit, to fit the same detection twice)."""
    if depth_diagnostics and estimator.tracking:
        raise ValueError("the depth diagnostics need untracked frames: evaluate without tracking or without them")
    return not estimator.tracking if depth_diagnostics is None else depth_diagnostics


def evaluate_folder(estimator: Estimator, reader: DreamReader, known_joints: bool = False, limit: int | None = None,
                    progress: bool = True, keep_images: int = 0, depth_diagnostics: bool | None = None
                    ) -> tuple[dict, list[FrameResult], list[np.ndarray]]:
    """Estimate every frame (in file order, tracking state reset between frames unless the estimator tracks) and
    build the report; also return the per-frame results and the first `keep_images` images (for plots). With
    `depth_diagnostics` (None: unless the estimator tracks) each detection is also fitted without the depth prior
    (untimed: fps is the product's) and the report gets its depth_diagnostics section (evaluation/depth.py)."""
    frames = list(reader)[:limit]
    results, images, errors, missed, n_2d = [], [], [], 0, 0
    depth_frames: list[DepthFrame] = []
    diagnose = _wants_depth_diagnostics(estimator, depth_diagnostics)
    robot = estimator.robot
    skipped_before = len(reader.problems)
    for frame, image in tqdm(reader.images(frames), total=len(frames), desc="evaluate", unit="frame",
                             disable=not progress):
        if known_joints and frame.joints is None:
            raise ValueError(f"{frame.name}: --known-joints needs ground-truth joints in every frame")
        joints = frame.joints if known_joints else None
        if diagnose:
            estimate, seconds, sources = diagnosed_estimate(estimator, image, frame.K, joints)
            depth_frames.append(depth_frame(robot, frame, sources))
        else:
            start = time.perf_counter()
            estimate = estimator.estimate(image, frame.K, joints)
            seconds = time.perf_counter() - start
        results.append(frame_result(frame, estimate, seconds, robot))
        gt = ground_truth_fit_keypoints(robot, frame)
        if gt is not None:
            n_2d += 1
            if estimate.detected_2d is None:
                missed += 1
            else:
                errors.append(keypoint_errors_px(estimate.detected_2d, gt, frame.width, frame.height))
        if len(images) < keep_images:
            images.append(image)
    if frames and not results:
        raise DreamFormatError(f"{reader.folder}: none of its {len(frames)} frames has a readable image (first: "
                               f"{reader.problems[-1][0]}: {reader.problems[-1][2]})")
    spec = robot.spec
    report = build_report(results, spec.joint_names, robot.joint_types, spec.keypoint_names, spec.joint_symmetry)
    report.update(summarize_2d(errors, robot.n_keypoints, n_2d, missed))
    report.update(skipped_frames(reader, skipped_before))
    if diagnose:
        report["depth_diagnostics"] = build_depth_diagnostics(depth_frames, estimator.method(calibrating=False))
    return report, results, images


def skipped_frames(reader: DreamReader, images_from: int) -> dict:
    """The report's account of malformed input: frames skipped at reading (bad JSON fields) and, from
    reader.problems[images_from:], at decoding their images; each as {file, field, message}."""
    problems = reader.problems[:reader.n_malformed_files] + reader.problems[images_from:]
    return {"n_skipped": len(problems),
            "skipped": [{"file": f, "field": field, "message": m} for f, field, m in problems]}


def evaluate_methods(estimator: Estimator, reader: DreamReader, limit: int | None = None, progress: bool = True,
                     known_joints: bool = True, depth_diagnostics: bool = True) -> dict[str, dict]:
    """The ablation on the same frames and the same detections: one report per estimation method (feed-forward,
    lifter, fitted) and, when the frames have joints and `known_joints`, 'fitted, known joints' (only the pose
    fitted). Each report also has the detection's median 2D errors (DREAM and fit keypoints, px) and, with
    `depth_diagnostics`, the depth_diagnostics section (evaluation/depth.py; one more fit a frame, untimed)."""
    frames = list(reader)[:limit]
    robot = estimator.robot
    method = estimator.method(calibrating=False)
    results: dict[str, list[FrameResult]] = {}
    depth_frames: list[DepthFrame] = []
    errors, missed, n_2d = [], 0, 0
    skipped_before = len(reader.problems)
    for frame, image in tqdm(reader.images(frames), total=len(frames), desc="ablation", unit="frame",
                             disable=not progress):
        start = time.perf_counter()
        detection = estimator.detect(image, frame.K)
        estimates = estimator.estimate_detection(detection, frame.K, None, METHODS)
        seconds = time.perf_counter() - start
        if known_joints and frame.joints is not None:
            estimates["fitted, known joints"] = estimator.estimate_detection(detection, frame.K, frame.joints,
                                                                             ("fitted",))["fitted"]
        for name, estimate in estimates.items():
            results.setdefault(name, []).append(frame_result(frame, estimate, seconds, robot))
        if depth_diagnostics:
            sources = depth_sources(estimator, detection, frame.K, None, estimates)
            depth_frames.append(depth_frame(robot, frame, sources))
        gt = ground_truth_fit_keypoints(robot, frame)
        if gt is not None:
            n_2d += 1
            detected = estimates["fitted"].detected_2d
            if detected is None:
                missed += 1
            else:
                errors.append(keypoint_errors_px(detected, gt, frame.width, frame.height))
    spec = robot.spec
    shared = summarize_2d(errors, robot.n_keypoints, n_2d, missed) | skipped_frames(reader, skipped_before)
    if depth_diagnostics:
        shared["depth_diagnostics"] = build_depth_diagnostics(depth_frames, method)
    return {name: {**build_report(r, spec.joint_names, robot.joint_types, spec.keypoint_names, spec.joint_symmetry),
                    **shared}
            for name, r in results.items()}


def format_ablation(reports: dict[str, dict]) -> str:
    """A Markdown table of the ablation: one row per method."""
    lines = ["| method | ADD AUC | mean ADD mm | median ADD mm | joint error deg | rotation error deg | not found |",
             "|---|---|---|---|---|---|---|"]
    fmt = lambda v, d=1: "n/a" if v is None else f"{v:.{d}f}"  # noqa: E731
    for method, r in reports.items():
        lines.append(f"| {method} | {fmt(r['add_auc'])} | {fmt(r['add_mean_mm'])} | {fmt(r['add_median_mm'])} | "
                     f"{fmt(r['joint_error_deg']['mean'])} | {fmt(r['rotation_error_deg']['mean'])} | "
                     f"{r['n_not_found']}/{r['n_frames']} |")
    any_report = next(iter(reports.values()))
    lines.append(f"\nnetwork 2D error (median, px): DREAM keypoints {fmt(any_report['kp2d_dream_median_px'])}, "
                 f"fit keypoints {fmt(any_report['kp2d_fit_median_px'])} "
                 f"({any_report['n_missed_2d']}/{any_report['n_frames_2d']} frames without a detection)")
    lines += keypoint_error_lines(any_report, estimate=False)
    if any_report.get("depth_diagnostics"):
        lines += ["", *format_depth_diagnostics(any_report["depth_diagnostics"])]
    return "\n".join(lines)
