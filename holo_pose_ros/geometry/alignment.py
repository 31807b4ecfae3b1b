"""Rigid alignment of point sets (Kabsch without scale) and rotation <-> quaternion conversions, numpy float64.
Quaternions are [x, y, z, w] (the DREAM/NDDS order); translations are in whatever unit the points use (metres)."""

from __future__ import annotations

import numpy as np

UE_TO_OPENCV = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
"""R_NORMAL_UE: right-multiplied onto R(quaternion_xyzw) of a DREAM object, it gives R_cam<-base in OpenCV axes."""
UE_TO_OPENCV.setflags(write=False)


def _points(x, name: str) -> np.ndarray:
    """`x` as a finite (N, 3) float64 array, or a ValueError naming the argument."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (N, 3), got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: contains NaN or inf")
    return a


def _weights(weights, n: int) -> np.ndarray:
    """Per-point weights as a (N,) float64 array summing to 1 (uniform when None)."""
    if weights is None:
        return np.full(n, 1.0 / n)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != (n,) or not np.isfinite(w).all() or (w < 0).any() or w.sum() <= 0:
        raise ValueError(f"weights: expected {n} finite non-negative values with a positive sum")
    return w / w.sum()


def rigid_align(src, dst, weights=None) -> tuple[np.ndarray, float]:
    """The rotation + translation T (4, 4) (det R = +1) minimising the weighted squared distances between
    T·src and dst, and the weighted RMS residual after alignment (same unit as the points, e.g. metres)."""
    p, q = _points(src, "src"), _points(dst, "dst")
    if p.shape != q.shape or len(p) < 3:
        raise ValueError(f"rigid_align: need two (N, 3) arrays with N >= 3, got {p.shape} and {q.shape}")
    w = _weights(weights, len(p))
    p_mean, q_mean = w @ p, w @ q
    cov = (w[:, None] * (p - p_mean)).T @ (q - q_mean)
    u, _, vt = np.linalg.svd(cov)
    d = 1.0 if np.linalg.det(vt.T @ u.T) >= 0 else -1.0  # reflection guard: proper rotation only
    R = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, q_mean - R @ p_mean
    residual = float(np.sqrt(w @ np.sum((p @ R.T + T[:3, 3] - q) ** 2, axis=1)))
    return T, residual


def quaternion_xyzw_to_matrix(q) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) [x, y, z, w], normalised first (any non-zero norm)."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1:] != (4,):
        raise ValueError(f"quaternion: expected shape (..., 4), got {q.shape}")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.isfinite(q).all() or (norm < 1e-12).any():
        raise ValueError("quaternion: must be finite with a non-zero norm")
    x, y, z, w = np.moveaxis(q / norm, -1, 0)
    R = np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], axis=-1)
    return R.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quaternion_xyzw(R) -> np.ndarray:
    """Unit quaternions (..., 4) [x, y, z, w] with w >= 0 of rotation matrices (..., 3, 3); a slightly
    non-orthogonal matrix gives its nearest rotation's quaternion (Bar-Itzhack's eigenvector method)."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3) or not np.isfinite(R).all():
        raise ValueError(f"rotation: expected finite (..., 3, 3), got shape {R.shape}")
    m = {f"{i}{j}": R[..., i, j] for i in range(3) for j in range(3)}
    # Symmetric 4x4 matrix whose top eigenvector is the quaternion [x, y, z, w].
    K = np.stack([
        m["00"] - m["11"] - m["22"], m["10"] + m["01"], m["20"] + m["02"], m["21"] - m["12"],
        m["10"] + m["01"], m["11"] - m["00"] - m["22"], m["21"] + m["12"], m["02"] - m["20"],
        m["20"] + m["02"], m["21"] + m["12"], m["22"] - m["00"] - m["11"], m["10"] - m["01"],
        m["21"] - m["12"], m["02"] - m["20"], m["10"] - m["01"], m["00"] + m["11"] + m["22"],
    ], axis=-1).reshape(R.shape[:-2] + (4, 4)) / 3.0
    _, vectors = np.linalg.eigh(K)
    q = vectors[..., :, -1]
    return q * np.where(q[..., 3:] < 0, -1.0, 1.0)


def rotation_log(R) -> np.ndarray:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3), radians, through the unit quaternion (w >= 0):
    2 atan2(|xyz|, w) along xyz, well defined up to an angle of pi."""
    q = matrix_to_quaternion_xyzw(R)
    xyz, w = q[..., :3], q[..., 3:]
    norm = np.linalg.norm(xyz, axis=-1, keepdims=True)
    return np.where(norm > 1e-12, xyz * (2.0 * np.arctan2(norm, w) / np.maximum(norm, 1e-12)), 2.0 * xyz)
