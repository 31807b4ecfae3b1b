"""Run the deployed estimator over a DREAM folder (no ground truth reaches it, except the true joints in
known-joints mode) and score it."""

from __future__ import annotations

import time

import numpy as np
from tqdm import tqdm

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.estimator import Estimate, Estimator
from holo_pose_ros.evaluation.report import FrameResult, build_report


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


def evaluate_folder(estimator: Estimator, reader: DreamReader, known_joints: bool = False, limit: int | None = None,
                    progress: bool = True, keep_images: int = 0) -> tuple[dict, list[FrameResult], list[np.ndarray]]:
    """Estimate every frame (in file order, tracking state reset between frames unless the estimator tracks) and
    build the report; also return the per-frame results and the first `keep_images` images (for plots)."""
    frames = list(reader)[:limit]
    results, images = [], []
    robot = estimator.robot
    for frame in tqdm(frames, desc="evaluate", unit="frame", disable=not progress):
        image = reader.load_image(frame)
        if known_joints and frame.joints is None:
            raise ValueError(f"{frame.name}: --known-joints needs ground-truth joints in every frame")
        start = time.perf_counter()
        estimate = estimator.estimate(image, frame.K, frame.joints if known_joints else None)
        results.append(frame_result(frame, estimate, time.perf_counter() - start, robot))
        if len(images) < keep_images:
            images.append(image)
    spec = robot.spec
    report = build_report(results, spec.joint_names, robot.joint_types, spec.keypoint_names)
    return report, results, images
