"""Synthetic fitting problems for tests and benchmarks: a random pose of the robot seen by a randomized camera
(the generator's ranges), the exact projections of its fit keypoints, and starts perturbed from the truth.
Metres, radians, pixels."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from holo_pose_ros.data.scene import sample_camera, sample_intrinsics
from holo_pose_ros.fitting.kinematic_tree import KinematicTree
from holo_pose_ros.fitting.residuals import project, so3_exp


@dataclass
class Problem:
    """One view: the true joints (J,), T_cam<-base (4, 4), K (3, 3), the fit keypoints' pixels (M, 2) and
    whether each lies in front of the camera and inside the image (M,)."""

    q: np.ndarray
    T_cam_base: np.ndarray
    K: np.ndarray
    uv: np.ndarray
    visible: np.ndarray


def sample_problem(tree: KinematicTree, lower: np.ndarray, upper: np.ndarray, generator_config: dict,
                   rng: np.random.Generator, width: int = 640, height: int = 480) -> Problem:
    """Joints uniform within [lower, upper]; K and the camera drawn as the synthetic generator does
    (data/scene.py: sample_intrinsics, sample_camera around the fit points' extent)."""
    q = rng.uniform(lower, upper)
    K = sample_intrinsics(generator_config["intrinsics"], rng, width, height)
    P = tree.points(q[None])[0]
    centre = (P.min(0) + P.max(0)) / 2.0
    radius = float(np.linalg.norm(P - centre, axis=1).max()) * 1.1 + 0.08
    T = sample_camera(generator_config["camera"], rng, centre, radius, K, height)
    X = P @ T[:3, :3].T + T[:3, 3]
    uv = project(X, K, 1e-6)
    visible = (X[:, 2] > 0.05) & (uv[:, 0] >= 0) & (uv[:, 0] <= width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= height - 1)
    return Problem(q, T, K, uv, visible)


def perturbed_start(problem: Problem, lower: np.ndarray, upper: np.ndarray, prismatic: np.ndarray,
                    rng: np.random.Generator, angle_deg: float = 30.0, depth_fraction: float = 0.1
                    ) -> tuple[np.ndarray, np.ndarray]:
    """A start (q0 (J,), T0 (4, 4)) off the truth: every revolute joint by +-angle_deg (random sign), every
    prismatic joint by +-angle_deg/120 of its range (a quarter of it at 30 deg), clamped to the limits; the base
    rotated by angle_deg about a random axis (in the base frame) and its distance scaled by 1 +- depth_fraction."""
    J = len(problem.q)
    sign = rng.choice([-1.0, 1.0], J)
    step = np.where(prismatic, (upper - lower) * angle_deg / 120.0, np.radians(angle_deg))
    q0 = np.clip(problem.q + sign * step, lower, upper)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    T0 = problem.T_cam_base.copy()
    T0[:3, :3] = T0[:3, :3] @ so3_exp(np.radians(angle_deg) * axis)
    T0[:3, 3] *= 1.0 + rng.choice([-1.0, 1.0]) * depth_fraction
    return q0, T0


def keypoints_in_camera(tree: KinematicTree, q: np.ndarray, T_cam_base: np.ndarray, n: int) -> np.ndarray:
    """(n, 3) the first n fit points (DREAM's keypoints) in the camera frame, metres."""
    P = tree.points(np.asarray(q, float)[None])[0, :n]
    return P @ T_cam_base[:3, :3].T + T_cam_base[:3, 3]
