"""The 2D error of the network's keypoint evidence through the deployed detection path (localize, crop, heatmaps;
no fit), in pixels of the input image: what decides the fitted accuracy. DREAM's keypoints and the extra fit
keypoints are reported apart."""

from __future__ import annotations

import numpy as np
import torch
from tqdm import tqdm

from holo_pose_ros.geometry.camera import in_image, project


def detection_errors(estimator, reader, limit: int | None = None, progress: bool = False) -> dict:
    """Median / mean 2D error (px) of DREAM and of all fit keypoints over the in-image points of frames where the
    robot was detected, plus the count of frames it was missed in. Needs frames with joints and a base pose."""
    robot = estimator.robot
    n_dream = robot.n_keypoints
    dream, fit, missed, frames = [], [], 0, 0
    for frame in tqdm(list(reader)[:limit], desc="2D", unit="frame", disable=not progress):
        if frame.joints is None or frame.T_cam_base is None:
            continue
        frames += 1
        detection = estimator.detect(reader.load_image(frame), frame.K)
        if detection is None:
            missed += 1
            continue
        with torch.no_grad():
            points = robot.fit_keypoints_in_camera(torch.as_tensor(frame.joints[None], dtype=robot.dtype, device=robot.device),
                                                   torch.as_tensor(frame.T_cam_base[None], dtype=robot.dtype, device=robot.device))
        gt = project(points[0].double().cpu().numpy(), frame.K)
        inside = in_image(gt, frame.width, frame.height)
        error = np.linalg.norm(detection.uv[:len(gt)] - gt, axis=1)
        if len(detection.uv) < len(gt):  # a network without fit heatmaps: DREAM's keypoints only
            error = np.linalg.norm(detection.uv - gt[:len(detection.uv)], axis=1)
            inside = inside[:len(detection.uv)]
        dream.append(error[:n_dream][inside[:n_dream]])
        fit.append(error[inside])
    dream_all = np.concatenate(dream) if dream else np.array([])
    fit_all = np.concatenate(fit) if fit else np.array([])

    def stat(values: np.ndarray, f) -> float | None:
        return float(f(values)) if values.size else None

    return {"n_frames_2d": frames, "n_missed_2d": missed,
            "kp2d_dream_median_px": stat(dream_all, np.median), "kp2d_dream_mean_px": stat(dream_all, np.mean),
            "kp2d_fit_median_px": stat(fit_all, np.median), "kp2d_fit_mean_px": stat(fit_all, np.mean)}
