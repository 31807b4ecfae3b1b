"""A static camera's base pose, learnt from the stream: when neither the camera nor the robot's base moves, every
frame sees the same T_cam<-base, so the robust average of earlier frames' fits is a prior on the next frame's base
pose (fitting/solver.py BasePrior). The window restarts when frames keep disagreeing with it (the camera was moved).
ROS-free; metres, radians. Defaults and their meaning: config/static_camera.yaml."""

from __future__ import annotations

import math
from collections import deque
from pathlib import Path

import numpy as np

from holo_pose_ros.calibration import average_poses, pose_error
from holo_pose_ros.fitting.solver import BasePrior
from holo_pose_ros.resources import config_with_overrides


def load_static_camera_config(config: dict | str | Path | None = None) -> dict:
    """config/static_camera.yaml's defaults, overridden by `config` (a dict or a YAML path of the same keys)."""
    cfg = config_with_overrides("static_camera.yaml", config, "static camera parameters")
    if int(cfg["window"]) < 1 or not 1 <= int(cfg["min_frames"]) <= int(cfg["window"]) or int(cfg["jump_frames"]) < 1:
        raise ValueError("static camera: need 1 <= min_frames <= window and jump_frames >= 1, got "
                         f"window {cfg['window']}, min_frames {cfg['min_frames']}, jump_frames {cfg['jump_frames']}")
    if not (cfg["sigma_m"] > 0 and cfg["sigma_deg"] > 0 and cfg["jump_m"] > 0 and cfg["jump_deg"] > 0):
        raise ValueError("static camera: sigmas and jump limits must be positive")
    return cfg


class StaticCamera:
    """The running base pose of a static camera. Per frame, with its own fit T: `prior()` (None until min_frames
    frames were seen) where `agrees(T)`, then `observe(T)` once the frame is known to be found."""

    def __init__(self, config: dict | str | Path | None = None):
        self.config = load_static_camera_config(config)
        self.poses: deque[np.ndarray] = deque(maxlen=int(self.config["window"]))
        self._disagreeing: list[np.ndarray] = []
        self._average: np.ndarray | None = None
        self.restarts = 0  # times the window restarted because the camera moved

    def reset(self) -> None:
        """Forget every pose (e.g. the stream changed cameras)."""
        self.poses.clear()
        self._disagreeing.clear()
        self._average = None

    @property
    def average(self) -> np.ndarray | None:
        """(4, 4) the window's robust average T_cam<-base once it holds min_frames poses, else None."""
        if self._average is None and len(self.poses) >= int(self.config["min_frames"]):
            cfg = self.config
            self._average = average_poses(np.stack(self.poses), cfg["max_translation_m"],
                                          cfg["max_rotation_deg"]).T_cam_base
        return self._average

    def agrees(self, T_cam_base: np.ndarray) -> bool:
        """Whether a frame's own fit lies within the jump limits of the average (True before there is one)."""
        average = self.average
        if average is None:
            return True
        dt, dr = pose_error(np.asarray(T_cam_base, float), average)
        return dt <= self.config["jump_m"] and dr <= self.config["jump_deg"]

    def prior(self) -> BasePrior | None:
        """The base prior of the next frame's fit: the average, once there is one."""
        if self.average is None:
            return None
        return BasePrior(self.average, float(self.config["sigma_m"]), math.radians(float(self.config["sigma_deg"])))

    def observe(self, T_cam_base: np.ndarray) -> None:
        """Add a found frame's own fitted base pose where it agrees with the average; `jump_frames` disagreeing
        frames in a row restart the window from them: the camera moved."""
        T = np.asarray(T_cam_base, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError("a static camera pose must be a finite 4 x 4 matrix")
        if self.agrees(T):
            self._disagreeing.clear()
            self.poses.append(T)
            self._average = None
            return
        self._disagreeing.append(T)
        if len(self._disagreeing) >= int(self.config["jump_frames"]):
            moved = list(self._disagreeing)
            self.reset()
            self.poses.extend(moved)
            self.restarts += 1
