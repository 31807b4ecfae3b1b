"""Reprojection residuals of base-frame points through a pose (R, t) and intrinsics K, their Jacobian with
respect to (dq, dphi, dt), robust (IRLS) weights, and the SO(3) exponential. Pixels, metres, radians; numpy float64.

Pose increment convention: R <- R exp([dphi]x) (right, i.e. dphi is a rotation about the robot base's own axes,
through its origin, which keeps rotation and translation far less coupled than rotating about the camera),
t <- t + dt (camera frame, metres).
"""

from __future__ import annotations

import numpy as np

ROBUST_LOSSES = ("squared", "huber", "cauchy")


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of axis-angle vectors phi (..., 3), radians (Rodrigues)."""
    phi = np.asarray(phi, float)
    theta = np.sqrt(np.sum(phi * phi, axis=-1))[..., None, None]
    safe = np.where(theta > 0.0, theta, 1.0)             # phi = 0 gives K = 0: any finite a, b do
    half = np.sin(0.5 * safe) / safe
    K = skew(phi)
    return np.eye(3) + (np.sin(safe) / safe) * K + (2.0 * half * half) * (K @ K)


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3, 3) cross-product matrices [v]x of vectors v (..., 3): [v]x w = v x w."""
    v = np.asarray(v, float)
    K = np.zeros(v.shape + (3,))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return K


def transform_points(P_base: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(S, M, 3) camera-frame points X = R P + t from base-frame P (S, M, 3), R (S, 3, 3), t (S, 3); metres."""
    return P_base @ np.swapaxes(R, -1, -2) + t[:, None, :]


def project(X_cam: np.ndarray, K: np.ndarray, min_depth_m: float) -> np.ndarray:
    """(..., 2) pixels of camera-frame points X (..., 3) through K (3x3, last row 0 0 1); depths below
    min_depth_m (points behind or at the camera) are clamped to it, so the result is always finite."""
    z = np.maximum(X_cam[..., 2], min_depth_m)
    x, y = X_cam[..., 0] / z, X_cam[..., 1] / z
    return np.stack((K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]), axis=-1)


def reprojection_residuals_and_jacobian(P_base: np.ndarray, dP_dq: np.ndarray | None, R: np.ndarray, t: np.ndarray,
                                        K: np.ndarray, uv: np.ndarray, min_depth_m: float
                                        ) -> tuple[np.ndarray, np.ndarray]:
    """Residuals r (S, M, 2) px and their Jacobian (S, M, 2, J + 6) with respect to (dq (J), dphi (3), dt (3))
    (see the module docstring for dphi, dt); dP_dq (S, M, 3, J) from the kinematic tree, or None to fit the pose
    only (J = 0). Where the depth is clamped (min_depth_m) the depth derivative is zero."""
    S, M, _ = P_base.shape
    X = transform_points(P_base, R, t)
    clamped = X[..., 2] < min_depth_m
    inv_z = 1.0 / np.where(clamped, min_depth_m, X[..., 2])
    x, y = X[..., 0] * inv_z, X[..., 1] * inv_z
    fx, s, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    r = np.stack((fx * x + s * y + cx, fy * y + cy), axis=-1) - uv
    # d(u, v)/dX (S, M, 2, 3); zero depth derivative where the depth is clamped
    n = 0 if dP_dq is None else dP_dq.shape[-1]
    jac = np.empty((S, M, 2, n + 6))
    A = jac[..., n + 3:]                                                      # dX/dt = I: these columns are A
    A[..., 0, 0], A[..., 0, 1], A[..., 1, 0], A[..., 1, 1] = fx * inv_z, s * inv_z, 0.0, fy * inv_z
    A[..., 0, 2] = np.where(clamped, 0.0, -(fx * x + s * y) * inv_z)
    A[..., 1, 2] = np.where(clamped, 0.0, -fy * y * inv_z)
    AR = (A.reshape(S, 2 * M, 3) @ R).reshape(S, M, 2, 3)                     # d(u, v)/dP_base
    if dP_dq is not None:
        np.matmul(AR, dP_dq, out=jac[..., :n])
    # dX/dphi = -R [P]x (right increment), so each row a of AR gives the row -(a^T [P]x) = P x a
    Px, Py, Pz = (P_base[:, :, None, i] for i in range(3))
    ax, ay, az = AR[..., 0], AR[..., 1], AR[..., 2]
    jac[..., n] = Py * az - Pz * ay
    jac[..., n + 1] = Pz * ax - Px * az
    jac[..., n + 2] = Px * ay - Py * ax
    return r, jac


def robust_weights(sq_norm: np.ndarray, loss: str, scale_px: float) -> tuple[np.ndarray, np.ndarray]:
    """rho(s) (cost, px^2) and rho'(s) (IRLS weight, 0..1) of squared residual norms s (px^2), elementwise.

    squared: rho = s. huber: rho = s inside scale_px, 2 c |r| - c^2 outside. cauchy: rho = c^2 log(1 + s / c^2).
    All three agree with s for small residuals, so costs are comparable in px^2.
    """
    s = np.asarray(sq_norm, float)
    if loss == "squared":
        return s, np.ones_like(s)
    c2 = float(scale_px) ** 2
    if loss == "huber":
        norm = np.sqrt(s)
        inside = s <= c2
        rho = np.where(inside, s, 2.0 * scale_px * norm - c2)
        return rho, np.where(inside, 1.0, scale_px / np.maximum(norm, 1e-300))
    if loss == "cauchy":
        return c2 * np.log1p(s / c2), 1.0 / (1.0 + s / c2)
    raise ValueError(f"unknown robust loss '{loss}'; one of {', '.join(ROBUST_LOSSES)}")
