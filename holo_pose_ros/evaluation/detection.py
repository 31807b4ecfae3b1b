"""The 2D error of the network's keypoint evidence (heatmap peaks of the fit keypoints, before any fit), in pixels
of the input image: what decides the fitted accuracy. DREAM's keypoints and all fit keypoints are reported apart."""

from __future__ import annotations

import numpy as np
import torch

from holo_pose_ros.geometry.camera import in_image, project


def fit_keypoints_px(robot, joints: np.ndarray, T_cam_base: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(M, 2) pixels of every fit keypoint of the robot at joints (J,) and base pose T_cam_base (4, 4), through K."""
    with torch.no_grad():
        q = torch.as_tensor(np.array(joints[None]), dtype=robot.dtype, device=robot.device)
        T = torch.as_tensor(np.array(T_cam_base[None]), dtype=robot.dtype, device=robot.device)
        points = robot.fit_keypoints_in_camera(q, T)[0].double().cpu().numpy()
    return project(points, K)


def ground_truth_fit_keypoints(robot, frame) -> np.ndarray | None:
    """(M, 2) pixels of every fit keypoint from a frame's true joints and base pose; None when it lacks them."""
    if frame.joints is None or frame.T_cam_base is None:
        return None
    return fit_keypoints_px(robot, frame.joints, frame.T_cam_base, frame.K)


def keypoint_errors_px(detected: np.ndarray, gt: np.ndarray, width: int, height: int) -> np.ndarray:
    """(M,) pixel distance of detected to true fit keypoints, NaN where the true point is outside the image."""
    error = np.linalg.norm(np.asarray(detected, float) - gt, axis=1)
    error[~in_image(gt, width, height)] = np.nan
    return error


def summarize_2d(errors: list[np.ndarray], n_dream: int, n_frames: int, n_missed: int) -> dict:
    """Median / mean 2D error (px) of DREAM's and of all fit keypoints over per-frame (M,) error arrays, and the
    median of each DREAM keypoint (None where it was never in the image)."""
    def stat(values: np.ndarray, f) -> float | None:
        values = values[np.isfinite(values)]
        return float(f(values)) if values.size else None

    dream = np.concatenate([e[:n_dream] for e in errors]) if errors else np.zeros(0)
    fit = np.concatenate(errors) if errors else np.zeros(0)
    per_keypoint = np.stack([e[:n_dream] for e in errors]) if errors else np.zeros((0, n_dream))
    return {"n_frames_2d": n_frames, "n_missed_2d": n_missed,
            "kp2d_dream_median_px_per_keypoint": [stat(column, np.median) for column in per_keypoint.T],
            "kp2d_dream_median_px": stat(dream, np.median), "kp2d_dream_mean_px": stat(dream, np.mean),
            "kp2d_fit_median_px": stat(fit, np.median), "kp2d_fit_mean_px": stat(fit, np.mean)}
