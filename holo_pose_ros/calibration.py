"""Camera-to-robot calibration from trusted joints: per frame the estimator fits only T_cam<-base (the joints are
the robot's own), and a robust average over a window of frames gives the calibration and its covariance. The
robot may move; the camera must not (relative to the robot's base). ROS-free; metres, radians, camera frame."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from holo_pose_ros.geometry.alignment import rotation_log

MAD_TO_SIGMA = 1.4826  # median absolute deviation -> standard deviation of a normal distribution


@dataclass(frozen=True)
class Calibration:
    """A robust average of camera-to-base poses. The covariance is that of the average (the inliers' spread / n):
    rows x, y, z (m) then rotations about the camera's x, y, z axes (rad), ROS PoseWithCovariance order."""

    T_cam_base: np.ndarray          # (4, 4)
    covariance: np.ndarray          # (6, 6)
    n_used: int                     # inlier frames averaged
    n_rejected: int                 # frames of the window rejected as outliers
    translation_spread_m: float     # RMS distance of the inliers to the average
    rotation_spread_deg: float      # RMS angle of the inliers to the average


def _angle_between(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Geodesic angles (rad) between rotations Ra (..., 3, 3) and Rb (..., 3, 3)."""
    cos = (np.trace(np.swapaxes(Ra, -1, -2) @ Rb, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def _project_to_so3(M: np.ndarray) -> np.ndarray:
    """The rotation nearest M in the Frobenius norm (the chordal mean of rotations summed into M)."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def average_poses(poses: np.ndarray, max_translation_m: float, max_rotation_deg: float,
                  min_sigma_m: float = 1e-3, min_sigma_deg: float = 0.1) -> Calibration:
    """Robust average of poses T_cam<-base (N, 4, 4): start from the coordinate-wise median translation and the
    medoid rotation, reject poses farther than `max_translation_m` / `max_rotation_deg` or than 3 robust sigmas
    (MAD, floored at `min_sigma_*`), then average the inliers (mean translation, chordal mean rotation)."""
    T = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(T) == 0 or not np.isfinite(T).all():
        raise ValueError("average_poses needs at least one pose, all finite")
    R, t = T[:, :3, :3], T[:, :3, 3]
    centre_t = np.median(t, axis=0)
    pairwise = _angle_between(R[:, None], R[None, :])
    centre_R = R[int(np.argmin(pairwise.sum(1)))]
    d_t = np.linalg.norm(t - centre_t, axis=1)
    d_r = _angle_between(R, centre_R[None])
    limit_t = min(max_translation_m, max(3 * MAD_TO_SIGMA * np.median(d_t), 3 * min_sigma_m))
    limit_r = min(np.radians(max_rotation_deg), max(3 * MAD_TO_SIGMA * np.median(d_r), 3 * np.radians(min_sigma_deg)))
    inliers = (d_t <= limit_t) & (d_r <= limit_r)
    if not inliers.any():  # no consensus: the medoid alone
        inliers = np.zeros(len(T), bool)
        inliers[int(np.argmin(pairwise.sum(1)))] = True
    mean_t = t[inliers].mean(0)
    mean_R = _project_to_so3(R[inliers].sum(0))
    residuals = np.concatenate([t[inliers] - mean_t, rotation_log(R[inliers] @ mean_R.T)], axis=1)  # (n, 6)
    n = int(inliers.sum())
    floor = np.array([min_sigma_m] * 3 + [np.radians(min_sigma_deg)] * 3) ** 2
    spread = np.cov(residuals.T) if n >= 2 else np.zeros((6, 6))
    covariance = spread / n + np.diag(floor / n)
    result = np.eye(4)
    result[:3, :3], result[:3, 3] = mean_R, mean_t
    return Calibration(result, covariance, n, int(len(T) - n),
                       float(np.sqrt(np.mean(np.sum(residuals[:, :3] ** 2, 1)))),
                       float(np.degrees(np.sqrt(np.mean(np.sum(residuals[:, 3:] ** 2, 1))))))


class RunningCalibration:
    """The calibration over the last `window` per-frame poses, recomputed on demand."""

    def __init__(self, window: int, max_translation_m: float, max_rotation_deg: float):
        if window < 1:
            raise ValueError(f"calibration window must be at least 1 frame, got {window}")
        self.poses: deque[np.ndarray] = deque(maxlen=int(window))
        self.max_translation_m, self.max_rotation_deg = float(max_translation_m), float(max_rotation_deg)

    def add(self, T_cam_base: np.ndarray) -> None:
        T = np.asarray(T_cam_base, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError("a calibration pose must be a finite 4 x 4 matrix")
        self.poses.append(T)

    def estimate(self) -> Calibration | None:
        """The robust average of the window, None before the first pose."""
        if not self.poses:
            return None
        return average_poses(np.stack(self.poses), self.max_translation_m, self.max_rotation_deg)


def pose_error(T_estimate: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error deg) between two T_cam<-base."""
    dt = float(np.linalg.norm(T_estimate[:3, 3] - T_true[:3, 3]))
    return dt, float(np.degrees(_angle_between(T_estimate[:3, :3], T_true[:3, :3])))
