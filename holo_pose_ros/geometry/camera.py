"""Pinhole camera helpers (OpenCV convention: x right, y down, z forward; pixel (0, 0) is the centre of the
top-left pixel). Metres and pixels."""

from __future__ import annotations

import numpy as np


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """3x3 K from focal lengths and principal point (pixels)."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def project(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(..., 3) camera-frame points (metres) -> (..., 2) pixels, u = fx x/z + cx, v = fy y/z + cy."""
    p = np.asarray(points_cam, dtype=np.float64)
    z = p[..., 2:3]
    return (p[..., :2] / z) * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])


def in_image(uv: np.ndarray, width: int, height: int, margin_px: float = 0.0) -> np.ndarray:
    """(N,) bool: pixel inside the image, DREAM's inclusive rule 0 <= u <= W, 0 <= v <= H; with `margin_px`, at
    least that far inside every border."""
    m = margin_px
    return (uv[..., 0] >= m) & (uv[..., 0] <= width - m) & (uv[..., 1] >= m) & (uv[..., 1] <= height - m)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0]), roll: float = 0.0) -> np.ndarray:
    """T_world<-cam (4x4) of an OpenCV camera at `eye` looking at `target`, `up` pointing up in the image,
    rolled by `roll` radians about the optical axis."""
    forward = np.asarray(target, float) - np.asarray(eye, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-6:  # looking straight up or down: any right vector will do
        right = np.cross(forward, np.array([1.0, 0.0, 0.0]))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = np.cos(roll), np.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, forward], axis=1)
    T[:3, 3] = eye
    return T
