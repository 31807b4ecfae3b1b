"""The kinematic fit compiled with numba: forward kinematics of the fit keypoints, their reprojection residuals, robust
weights and the IRLS Gauss-Newton normal equations of every start in one pass (`linearize`); the grid costs of the
search by parts (`point_costs`); the Levenberg-Marquardt proposal (`propose`) and the whole loop (`lm_fit`) of fits
without a silhouette or a base prior. Pixels, metres, radians.

Why: the search by parts linearizes about 40 times a frame on a few starts and ~100 points; in numpy each
linearization was some 30 array operations on small arrays (0.3 ms, mostly call overhead) and built the whole
(S, M, 2, J + 6) Jacobian only to contract it. Compiled, a point's Jacobian rows go straight into H and g, and the
loop's bookkeeping costs nothing (fit by parts 23 -> 5 ms, docs/speed.md). The numpy code (kinematic_tree.py,
residuals.py, solver.normal_equations and Fitter.fit's loop) stays the reference that the tests compare with, and
serves the silhouette and the base prior. Matrix products are written out: numba's own go through SciPy's BLAS,
which this module does not need.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

LOSS_CODES = {"squared": 0, "huber": 1, "cauchy": 2}


@njit(cache=True, nogil=True)
def _robust(s: float, loss: int, scale: float) -> tuple[float, float]:
    """rho(s), rho'(s) of a squared residual norm s (px^2): residuals.robust_weights for one value."""
    if loss == 0:
        return s, 1.0
    c2 = scale * scale
    if loss == 1:
        if s <= c2:
            return s, 1.0
        norm = math.sqrt(s)
        return 2.0 * scale * norm - c2, scale / max(norm, 1e-300)
    return c2 * math.log1p(s / c2), 1.0 / (1.0 + s / c2)


@njit(cache=True, nogil=True)
def _body_poses(q: np.ndarray, parent: np.ndarray, C: np.ndarray, CK: np.ndarray, CKK: np.ndarray, Ca: np.ndarray,
                source: np.ndarray, gain: np.ndarray, bias: np.ndarray, T: np.ndarray) -> None:
    """T (B, 4, 4) <- every body's pose T_base<-body at joints q (J,), as KinematicTree.body_poses (bodies come
    after their parents; C, CK, CKK, Ca are the tree's per-moving-body pieces, index b - 1)."""
    B = parent.shape[0]
    for i in range(4):
        for j in range(4):
            T[0, i, j] = 1.0 if i == j else 0.0
    for b in range(1, B):
        theta = q[source[b]] * gain[b] + bias[b]
        s, c = math.sin(theta), 1.0 - math.cos(theta)
        p = parent[b]
        for i in range(4):
            for j in range(4):
                acc = 0.0
                for k in range(4):
                    L = C[b - 1, k, j] + s * CK[b - 1, k, j] + c * CKK[b - 1, k, j] + theta * Ca[b - 1, k, j]
                    acc += T[p, i, k] * L
                T[b, i, j] = acc


@njit(cache=True, nogil=True)
def linearize(q: np.ndarray, R: np.ndarray, t: np.ndarray, P_known: np.ndarray, pose_only: bool,
              parent: np.ndarray, C: np.ndarray, CK: np.ndarray, CKK: np.ndarray, Ca: np.ndarray, source: np.ndarray,
              gain: np.ndarray, bias: np.ndarray, axis: np.ndarray, prismatic: np.ndarray, point_body: np.ndarray,
              point_local: np.ndarray, n_joints: int, K: np.ndarray, uv: np.ndarray, weights: np.ndarray, loss: int,
              scale: float, min_depth: float, depth_points: np.ndarray):
    """At every start s (q (S, J), R (S, 3, 3), t (S, 3); with pose_only the points are P_known (S, M, 3) and
    only the pose is a parameter): the squared residual norms sq, robust costs rho and IRLS weights drho (S, M);
    the normal equations H (S, P, P) and g (S, P) of the parameters (dq, dphi, dt) (residuals.py's conventions,
    P = J + 6, or 6) weighing point m by weights[m] * drho; the depth prior's points' mean camera depth z (S,)
    and its gradient jz (S, P)."""
    S, M = R.shape[0], point_body.shape[0]
    nq = 0 if pose_only else n_joints
    P = nq + 6
    sq, rho, drho = np.empty((S, M)), np.empty((S, M)), np.empty((S, M))
    H, g = np.zeros((S, P, P)), np.zeros((S, P))
    z, jz = np.zeros(S), np.zeros((S, P))
    B = parent.shape[0]
    T = np.empty((B, 4, 4))
    omega_axis = np.empty((B, 3))            # each body's joint axis in the base frame
    Pm, dP, AR, row = np.empty(3), np.zeros((3, max(nq, 1))), np.empty((2, 3)), np.empty((2, P))
    depth_mask = np.zeros(M, np.bool_)
    for k in depth_points:
        depth_mask[k] = True
    n_depth = depth_points.shape[0]
    fx, sk, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    for s in range(S):
        if not pose_only:
            _body_poses(q[s], parent, C, CK, CKK, Ca, source, gain, bias, T)
            for b in range(1, B):
                for i in range(3):
                    omega_axis[b, i] = T[b, i, 0] * axis[b, 0] + T[b, i, 1] * axis[b, 1] + T[b, i, 2] * axis[b, 2]
        centroid = np.zeros(3)
        dcentroid = np.zeros((3, max(nq, 1)))
        for m in range(M):
            if pose_only:
                for i in range(3):
                    Pm[i] = P_known[s, m, i]
            else:
                bm = point_body[m]
                for i in range(3):
                    Pm[i] = (T[bm, i, 0] * point_local[m, 0] + T[bm, i, 1] * point_local[m, 1]
                             + T[bm, i, 2] * point_local[m, 2] + T[bm, i, 3])
                dP[:, :] = 0.0
                b = bm
                while b > 0:                      # every joint on the point's path to the base moves it
                    j, a = source[b], omega_axis[b]
                    if prismatic[b]:
                        for i in range(3):
                            dP[i, j] += gain[b] * a[i]
                    else:
                        d0, d1, d2 = Pm[0] - T[b, 0, 3], Pm[1] - T[b, 1, 3], Pm[2] - T[b, 2, 3]
                        dP[0, j] += gain[b] * (a[1] * d2 - a[2] * d1)
                        dP[1, j] += gain[b] * (a[2] * d0 - a[0] * d2)
                        dP[2, j] += gain[b] * (a[0] * d1 - a[1] * d0)
                    b = parent[b]
            # camera frame, projection and its derivative A = d(u, v)/dX (zero depth column where clamped)
            X0 = R[s, 0, 0] * Pm[0] + R[s, 0, 1] * Pm[1] + R[s, 0, 2] * Pm[2] + t[s, 0]
            X1 = R[s, 1, 0] * Pm[0] + R[s, 1, 1] * Pm[1] + R[s, 1, 2] * Pm[2] + t[s, 1]
            X2 = R[s, 2, 0] * Pm[0] + R[s, 2, 1] * Pm[1] + R[s, 2, 2] * Pm[2] + t[s, 2]
            if depth_mask[m]:
                for i in range(3):
                    centroid[i] += Pm[i] / n_depth
                    for j in range(nq):
                        dcentroid[i, j] += dP[i, j] / n_depth
            clamped = X2 < min_depth
            inv_z = 1.0 / (min_depth if clamped else X2)
            x, y = X0 * inv_z, X1 * inv_z
            r0 = fx * x + sk * y + cx - uv[m, 0]
            r1 = fy * y + cy - uv[m, 1]
            sqm = r0 * r0 + r1 * r1
            rh, dr = _robust(sqm, loss, scale)
            sq[s, m], rho[s, m], drho[s, m] = sqm, rh, dr
            omega = weights[m] * dr
            if omega == 0.0:
                continue
            a00, a01, a02 = fx * inv_z, sk * inv_z, 0.0 if clamped else -(fx * x + sk * y) * inv_z
            a11, a12 = fy * inv_z, 0.0 if clamped else -fy * y * inv_z
            for i in range(3):
                AR[0, i] = a00 * R[s, 0, i] + a01 * R[s, 1, i] + a02 * R[s, 2, i]
                AR[1, i] = a11 * R[s, 1, i] + a12 * R[s, 2, i]
            for d in range(2):
                for j in range(nq):
                    row[d, j] = AR[d, 0] * dP[0, j] + AR[d, 1] * dP[1, j] + AR[d, 2] * dP[2, j]
                ax, ay, az = AR[d, 0], AR[d, 1], AR[d, 2]
                row[d, nq] = Pm[1] * az - Pm[2] * ay          # dX/dphi = -R [P]x: the row P x a
                row[d, nq + 1] = Pm[2] * ax - Pm[0] * az
                row[d, nq + 2] = Pm[0] * ay - Pm[1] * ax
            row[0, nq + 3], row[0, nq + 4], row[0, nq + 5] = a00, a01, a02
            row[1, nq + 3], row[1, nq + 4], row[1, nq + 5] = 0.0, a11, a12
            for i in range(P):
                wi0, wi1 = omega * row[0, i], omega * row[1, i]
                g[s, i] += wi0 * r0 + wi1 * r1
                for j in range(i, P):
                    H[s, i, j] += wi0 * row[0, j] + wi1 * row[1, j]
        for i in range(P):
            for j in range(i + 1, P):
                H[s, j, i] = H[s, i, j]
        # the depth prior's mean depth: linear in the points, so that of their centroid
        rz0, rz1, rz2 = R[s, 2, 0], R[s, 2, 1], R[s, 2, 2]
        z[s] = rz0 * centroid[0] + rz1 * centroid[1] + rz2 * centroid[2] + t[s, 2]
        for j in range(nq):
            jz[s, j] = rz0 * dcentroid[0, j] + rz1 * dcentroid[1, j] + rz2 * dcentroid[2, j]
        jz[s, nq] = centroid[1] * rz2 - centroid[2] * rz1
        jz[s, nq + 1] = centroid[2] * rz0 - centroid[0] * rz2
        jz[s, nq + 2] = centroid[0] * rz1 - centroid[1] * rz0
        jz[s, nq + 5] = 1.0
    return sq, rho, drho, H, g, z, jz


@njit(cache=True, nogil=True)
def point_costs(q: np.ndarray, R: np.ndarray, t: np.ndarray, parent: np.ndarray, C: np.ndarray, CK: np.ndarray,
                CKK: np.ndarray, Ca: np.ndarray, source: np.ndarray, gain: np.ndarray, bias: np.ndarray,
                axis: np.ndarray, prismatic: np.ndarray, point_body: np.ndarray, point_local: np.ndarray,
                n_joints: int, K: np.ndarray, uv: np.ndarray, loss: int, scale: float, min_depth: float):
    """Robust costs rho and squared reprojection errors (S, M), px^2, of every fit point at joints q (S, J) and
    poses (R (S, 3, 3), t (S, 3)), unweighted, without derivatives: the search by parts' grids, hundreds of
    candidate joints a step (residuals.project and robust_weights, per point)."""
    S, M, B = R.shape[0], point_body.shape[0], parent.shape[0]
    rho, sq = np.empty((S, M)), np.empty((S, M))
    T = np.empty((B, 4, 4))
    fx, sk, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    for s in range(S):
        _body_poses(q[s], parent, C, CK, CKK, Ca, source, gain, bias, T)
        for m in range(M):
            bm = point_body[m]
            l0, l1, l2 = point_local[m, 0], point_local[m, 1], point_local[m, 2]
            p0 = T[bm, 0, 0] * l0 + T[bm, 0, 1] * l1 + T[bm, 0, 2] * l2 + T[bm, 0, 3]
            p1 = T[bm, 1, 0] * l0 + T[bm, 1, 1] * l1 + T[bm, 1, 2] * l2 + T[bm, 1, 3]
            p2 = T[bm, 2, 0] * l0 + T[bm, 2, 1] * l1 + T[bm, 2, 2] * l2 + T[bm, 2, 3]
            X0 = R[s, 0, 0] * p0 + R[s, 0, 1] * p1 + R[s, 0, 2] * p2 + t[s, 0]
            X1 = R[s, 1, 0] * p0 + R[s, 1, 1] * p1 + R[s, 1, 2] * p2 + t[s, 1]
            X2 = R[s, 2, 0] * p0 + R[s, 2, 1] * p1 + R[s, 2, 2] * p2 + t[s, 2]
            inv_z = 1.0 / max(X2, min_depth)
            x, y = X0 * inv_z, X1 * inv_z
            r0, r1 = fx * x + sk * y + cx - uv[m, 0], fy * y + cy - uv[m, 1]
            sq[s, m] = r0 * r0 + r1 * r1
            rho[s, m] = _robust(sq[s, m], loss, scale)[0]
    return rho, sq


@njit(cache=True, nogil=True)
def _damped_solve(A: np.ndarray, b: np.ndarray, damping: float, fixed: np.ndarray) -> np.ndarray:
    """dx solving (A + damping diag(A)) dx = b (one start; A, b are overwritten), a floor on the diagonal, dx = 0 where
    fixed, by Cholesky. A is a Gauss-Newton matrix, so the damped one is positive definite; where rounding (or a NaN)
    says otherwise the step is 0, which the fit rejects and retries with more damping."""
    P = b.shape[0]
    top = 1e-12
    for i in range(P):
        top = max(top, A[i, i])
    floor = 1e-9 * top
    for i in range(P):
        if fixed[i]:
            for j in range(P):
                A[i, j] = 0.0
                A[j, i] = 0.0
            A[i, i], b[i] = 1.0, 0.0
        else:
            A[i, i] += damping * max(A[i, i], floor)
    dx = np.zeros(P)
    L = np.zeros((P, P))
    for j in range(P):                                   # Cholesky A = L L^T
        d = A[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:
            return dx
        L[j, j] = math.sqrt(d)
        for i in range(j + 1, P):
            v = A[i, j]
            for k in range(j):
                v -= L[i, k] * L[j, k]
            L[i, j] = v / L[j, j]
    y = np.empty(P)
    for i in range(P):
        v = b[i]
        for k in range(i):
            v -= L[i, k] * y[k]
        y[i] = v / L[i, i]
    for i in range(P - 1, -1, -1):
        v = y[i]
        for k in range(i + 1, P):
            v -= L[k, i] * dx[k]
        dx[i] = v / L[i, i]
    return dx


@njit(cache=True, nogil=True)
def _matmul3(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A B of (3, 3) matrices, written out (numba's matrix products go through SciPy's BLAS)."""
    out = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]
    return out


@njit(cache=True, nogil=True)
def _so3_exp(phi: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of the axis-angle vector phi (radians), as residuals.so3_exp."""
    theta = math.sqrt(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
    out = np.eye(3)
    if theta == 0.0:
        return out
    a, half = math.sin(theta) / theta, math.sin(0.5 * theta) / theta
    b = 2.0 * half * half
    K = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    KK = _matmul3(K, K)
    for i in range(3):
        for j in range(3):
            out[i, j] += a * K[i, j] + b * KK[i, j]
    return out


@njit(cache=True, nogil=True)
def propose(q: np.ndarray, R: np.ndarray, t: np.ndarray, H: np.ndarray, g: np.ndarray, q_start: np.ndarray,
            prior: np.ndarray, z: np.ndarray, jz: np.ndarray, depth_precision: float, depth_m: float,
            lower: np.ndarray, upper: np.ndarray, damping: np.ndarray, pose_only: bool):
    """One Levenberg-Marquardt proposal per start from its normal equations H (S, P, P), g (S, P) (not modified):
    the depth prior (depth_precision * (z - depth_m)^2 with z's gradient jz (S, P); none when depth_precision is 0)
    and the joints' prior (precision prior (J,) about q_start (S, J)) join them, joints on a limit whose descent points
    outward are held (projected Newton), the damped system is solved; returns the candidate (q clipped to
    [lower, upper], R exp([dphi]x), t + dt) as residuals.py's increments."""
    S, P = g.shape
    nq = 0 if pose_only else q.shape[1]
    q_c, R_c, t_c = q.copy(), np.empty_like(R), np.empty_like(t)
    fixed = np.zeros(P, np.bool_)
    for s in range(S):
        A, b = H[s].copy(), np.empty(P)
        for i in range(P):
            b[i] = g[s, i]
        if depth_precision > 0.0:
            e = depth_precision * (z[s] - depth_m)
            for i in range(P):
                b[i] += e * jz[s, i]
                for j in range(P):
                    A[i, j] += depth_precision * jz[s, i] * jz[s, j]
        for j in range(nq):
            A[j, j] += prior[j]
            b[j] += prior[j] * (q[s, j] - q_start[s, j])
            fixed[j] = (q[s, j] <= lower[j] and b[j] > 0.0) or (q[s, j] >= upper[j] and b[j] < 0.0)
        dx = _damped_solve(A, -b, damping[s], fixed)
        for j in range(nq):
            q_c[s, j] = min(max(q[s, j] + dx[j], lower[j]), upper[j])
        Rs = _matmul3(R[s], _so3_exp(dx[nq:nq + 3]))
        for i in range(3):
            t_c[s, i] = t[s, i] + dx[nq + 3 + i]
            for j in range(3):
                R_c[s, i, j] = Rs[i, j]
    return q_c, R_c, t_c


@njit(cache=True, nogil=True)
def _objective(rho: np.ndarray, weights: np.ndarray, q: np.ndarray, q_start: np.ndarray, prior: np.ndarray,
               z: np.ndarray, depth_precision: float, depth_m: float, pose_only: bool) -> np.ndarray:
    """(S,) the fit's objective per start: robust keypoint costs weighed by `weights`, the joints' prior, the depth
    prior (px^2)."""
    S, M = rho.shape
    F = np.zeros(S)
    for s in range(S):
        for m in range(M):
            F[s] += rho[s, m] * weights[m]
        if not pose_only:
            for j in range(q.shape[1]):
                F[s] += prior[j] * (q[s, j] - q_start[s, j]) ** 2
        if depth_precision > 0.0:
            F[s] += depth_precision * (z[s] - depth_m) ** 2
    return F


@njit(cache=True, nogil=True)
def _weighted_sums(a: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(S,) sum_m a[s, m] w[m], written out (numba's matrix products need SciPy's BLAS)."""
    out = np.zeros(a.shape[0])
    for s in range(a.shape[0]):
        for m in range(a.shape[1]):
            out[s] += a[s, m] * w[m]
    return out


@njit(cache=True, nogil=True)
def lm_fit(q0: np.ndarray, R0: np.ndarray, t0: np.ndarray, stages: np.ndarray, w: np.ndarray, P_known: np.ndarray,
           pose_only: bool, parent: np.ndarray, C: np.ndarray, CK: np.ndarray, CKK: np.ndarray, Ca: np.ndarray,
           source: np.ndarray, gain: np.ndarray, bias: np.ndarray, axis: np.ndarray, prismatic: np.ndarray,
           point_body: np.ndarray, point_local: np.ndarray, n_joints: int, K: np.ndarray, uv: np.ndarray, loss: int,
           scale: float, min_depth: float, depth_points: np.ndarray, prior: np.ndarray, depth_precision: float,
           depth_m: float, lower: np.ndarray, upper: np.ndarray, iterations: int, damping_init: float,
           damping_up: float, damping_down: float, damping_min: float, damping_max: float,
           relative_tolerance: float, absolute_tolerance: float):
    """Fitter.fit's Levenberg-Marquardt loop, compiled, for fits without a silhouette or a base prior (the estimator's
    every fit but the static camera's): all starts in lockstep from (q0, R0, t0), the chain-growing stages' point
    weights (rows of `stages`, then w), the joints' and the depth prior, the same acceptance, damping schedule and
    convergence test as the numpy loop (solver.py), which stays the reference. Returns the final (q, R, t), the data
    costs sum w rho and sum w |r|^2 (S,) at the end and at the start, and the iterations run."""
    S = q0.shape[0]
    n_stages = stages.shape[0]
    first = stages[0] if n_stages > 0 else w
    sq, rho, drho, H, g, z, jz = linearize(q0, R0, t0, P_known, pose_only, parent, C, CK, CKK, Ca, source, gain, bias,
                                           axis, prismatic, point_body, point_local, n_joints, K, uv, first, loss,
                                           scale, min_depth, depth_points)
    begin_rho, begin_sq = _weighted_sums(rho, w), _weighted_sums(sq, w)
    q, R, t = q0.copy(), R0.copy(), t0.copy()
    q_start = q0.copy()
    damping = np.full(S, damping_init)
    converged = np.zeros(S, np.bool_)
    stage_of_state = 0 if n_stages > 0 else -1              # which weights the state's H, g were built with
    it = 0
    for it in range(1, iterations + 1):
        final = it > n_stages
        stage = -1 if final else it - 1
        wk = w if final else stages[stage]
        if stage != stage_of_state:
            sq, rho, drho, H, g, z, jz = linearize(q, R, t, P_known, pose_only, parent, C, CK, CKK, Ca, source, gain,
                                                   bias, axis, prismatic, point_body, point_local, n_joints, K, uv, wk,
                                                   loss, scale, min_depth, depth_points)
            stage_of_state = stage
        F = _objective(rho, wk, q, q_start, prior, z, depth_precision, depth_m, pose_only)
        q_c, R_c, t_c = propose(q, R, t, H, g, q_start, prior, z, jz, depth_precision, depth_m, lower, upper, damping,
                                pose_only)
        sq_c, rho_c, drho_c, H_c, g_c, z_c, jz_c = linearize(q_c, R_c, t_c, P_known, pose_only, parent, C, CK, CKK,
                                                             Ca, source, gain, bias, axis, prismatic, point_body,
                                                             point_local, n_joints, K, uv, wk, loss, scale, min_depth,
                                                             depth_points)
        F_c = _objective(rho_c, wk, q_c, q_start, prior, z_c, depth_precision, depth_m, pose_only)
        for s in range(S):
            accept = F_c[s] < F[s]                                     # False for NaN
            if final:
                if accept:
                    data = 0.0
                    for m in range(w.shape[0]):
                        data += rho_c[s, m] * w[m]
                    if (F[s] - F_c[s]) < relative_tolerance * F[s] or data < absolute_tolerance:
                        converged[s] = True
                elif damping[s] >= damping_max:
                    converged[s] = True
            if accept:
                q[s], R[s], t[s] = q_c[s], R_c[s], t_c[s]
                sq[s], rho[s], drho[s], H[s], g[s], z[s], jz[s] = sq_c[s], rho_c[s], drho_c[s], H_c[s], g_c[s], \
                    z_c[s], jz_c[s]
                damping[s] = min(max(damping[s] * damping_down, damping_min), damping_max)
            else:
                damping[s] = min(max(damping[s] * damping_up, damping_min), damping_max)
        if converged.all():
            break
    return q, R, t, _weighted_sums(rho, w), _weighted_sums(sq, w), begin_rho, begin_sq, it
