"""fitting/compiled.py: the compiled linearization against the numpy reference it replaces in the fit (the
kinematic tree's points and Jacobian, residuals.py's reprojection residuals, Jacobian and robust weights,
solver.normal_equations) on random joints and poses of the three shipped robots, every robust loss, points
behind the camera, the pose-only fit; the depth prior's term against finite differences."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from holo_pose_ros.fitting import KinematicTree, compiled
from holo_pose_ros.fitting.residuals import (
    project,
    reprojection_residuals_and_jacobian,
    robust_weights,
    so3_exp,
    transform_points,
)
from holo_pose_ros.fitting.solver import normal_equations
from holo_pose_ros.robots.kinematics import RobotModel

K = np.array([[610.0, 2.0, 318.0], [0.0, 605.0, 243.0], [0.0, 0.0, 1.0]])


def _problem(name: str, seed: int, S: int = 3):
    """The robot's tree, random joints within the limits, poses 1-2 m ahead, observations near the projections
    (some far off, so every robust loss leaves its quadratic part) and weights with zeros."""
    model = RobotModel(name, dtype=torch.float64)
    tree = KinematicTree.from_robot(model)
    rng = np.random.default_rng(seed)
    q = rng.uniform(model.lower.numpy(), model.upper.numpy(), (S, model.n_joints))
    R = so3_exp(rng.normal(size=(S, 3)))
    t = np.column_stack([rng.normal(0, 0.1, (S, 2)), rng.uniform(1.0, 2.0, S)])
    P = tree.points(q)
    X = P @ np.swapaxes(R, 1, 2) + t[:, None]
    uv = (X[0, :, :2] / X[0, :, 2:]) @ K[:2, :2].T + K[:2, 2] + rng.normal(0, 15.0, (tree.n_points, 2))
    w = rng.uniform(0.0, 1.0, tree.n_points) * (rng.uniform(size=tree.n_points) > 0.2)
    return model, tree, q, R, t, uv, w


def _run(tree, q, R, t, uv, w, loss, pose_only=False, min_depth=0.05, depth_points=(0,)):
    P_known = np.ascontiguousarray(tree.points(q)) if pose_only else np.zeros((1, 1, 3))
    return compiled.linearize(q, R, t, P_known, pose_only, *tree.compiled_arrays, K, uv, w, compiled.LOSS_CODES[loss],
                              10.0, min_depth, np.array(depth_points, np.int64))


@pytest.mark.parametrize("name", ["panda", "kuka", "baxter"])
@pytest.mark.parametrize("loss", ["squared", "huber", "cauchy"])
def test_normal_equations_match_the_numpy_reference(name, loss):
    _, tree, q, R, t, uv, w = _problem(name, 1)
    sq, rho, drho, H, g, _, _ = _run(tree, q, R, t, uv, w, loss)
    P, dP = tree.points_and_jacobian(q)
    r, jac = reprojection_residuals_and_jacobian(P, dP, R, t, K, uv, 0.05)
    sq_ref = np.sum(r * r, axis=-1)
    rho_ref, drho_ref = robust_weights(sq_ref, loss, 10.0)
    H_ref, g_ref = normal_equations(r, jac, w * drho_ref)
    np.testing.assert_allclose(sq, sq_ref, rtol=1e-10)
    np.testing.assert_allclose(rho, rho_ref, rtol=1e-10)
    np.testing.assert_allclose(drho, drho_ref, rtol=1e-10)
    scale = np.abs(H_ref).max()
    np.testing.assert_allclose(H, H_ref, rtol=1e-9, atol=1e-10 * scale)
    np.testing.assert_allclose(g, g_ref, rtol=1e-9, atol=1e-10 * np.abs(g_ref).max())
    assert np.abs(H_ref[:, :tree.n_joints, :tree.n_joints]).max() > 0      # the joints' block is exercised


def test_pose_only_and_points_behind_the_camera():
    """Known joints: only (dphi, dt); a camera inside the robot: clamped points, finite and as the reference."""
    _, tree, q, R, t, uv, w = _problem("panda", 2)
    t = t.copy()
    t[:, 2] = 0.2
    sq, _, drho, H, g, _, _ = _run(tree, q, R, t, uv, w, "cauchy", pose_only=True)
    P = tree.points(q)
    assert ((P @ np.swapaxes(R, 1, 2) + t[:, None])[..., 2] < 0.05).any()
    r, jac = reprojection_residuals_and_jacobian(P, None, R, t, K, uv, 0.05)
    _, drho_ref = robust_weights(np.sum(r * r, axis=-1), "cauchy", 10.0)
    H_ref, g_ref = normal_equations(r, jac, w * drho_ref)
    assert H.shape == (len(q), 6, 6) and np.isfinite(H).all() and np.isfinite(g).all()
    np.testing.assert_allclose(H, H_ref, rtol=1e-9, atol=1e-10 * np.abs(H_ref).max())
    np.testing.assert_allclose(g, g_ref, rtol=1e-9, atol=1e-10 * np.abs(g_ref).max())


def test_depth_term_matches_finite_differences():
    """The depth prior's mean camera depth of its points and its (dq, dphi, dt) gradient (the fit's increments:
    R <- R exp(dphi), t <- t + dt)."""
    model, tree, q, R, t, uv, w = _problem("panda", 3)
    points = (0, 5, 40)
    *_, z, jz = _run(tree, q, R, t, uv, w, "cauchy", depth_points=points)
    P = tree.points(q)[:, list(points)]
    np.testing.assert_allclose(z, np.einsum("smi,si->sm", P, R[:, 2]).mean(1) + t[:, 2], atol=1e-12)
    J, eps = model.n_joints, 1e-6
    for k in range(J + 6):
        x = np.zeros(J + 6)
        x[k] = eps
        moved = [_run(tree, q + s * x[:J], R @ so3_exp(np.tile(s * x[J:J + 3], (len(q), 1))), t + s * x[J + 3:],
                      uv, w, "cauchy", depth_points=points)[5] for s in (1.0, -1.0)]
        np.testing.assert_allclose(jz[:, k], (moved[0] - moved[1]) / (2 * eps), rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("loss", ["squared", "huber", "cauchy"])
def test_point_costs_match_the_numpy_reference(loss):
    """The search by parts' grid costs: every point's robust cost and squared error, 200 candidate poses of Kuka."""
    _, tree, _, _, _, uv, _ = _problem("kuka", 4)
    _, _, q, R, t, _, _ = _problem("kuka", 5, S=200)
    rho, sq = compiled.point_costs(q, R, t, *tree.compiled_arrays, K, uv, compiled.LOSS_CODES[loss], 10.0, 0.05)
    r = project(transform_points(tree.points(q), R, t), K, 0.05) - uv
    rho_ref, _ = robust_weights(np.sum(r * r, axis=-1), loss, 10.0)
    np.testing.assert_allclose(sq, np.sum(r * r, axis=-1), rtol=1e-10)
    np.testing.assert_allclose(rho, rho_ref, rtol=1e-10)


def _damped(A: np.ndarray, b: np.ndarray, damping: float) -> np.ndarray:
    """The reference LM step: solve (A + damping diag(A)) dx = -b."""
    return np.linalg.solve(A + damping * np.diag(np.diag(A)), -b)


def test_propose_solves_the_damped_system_with_the_priors():
    """The LM proposal: the joints' prior and the depth prior join the normal equations, the damped system is
    solved, and the candidate is (q + dq, R exp(dphi), t + dt) while no joint meets a limit."""
    rng = np.random.default_rng(5)
    S, J = 3, 4
    P = J + 6
    A = rng.normal(size=(S, 2 * P, P))
    H, g = np.swapaxes(A, 1, 2) @ A, rng.normal(size=(S, P))
    q, q_start = rng.uniform(-0.5, 0.5, (S, J)), rng.uniform(-0.5, 0.5, (S, J))
    R, t = so3_exp(rng.normal(size=(S, 3))), rng.normal(size=(S, 3))
    prior, z, jz = rng.uniform(0.5, 2.0, J), rng.uniform(1.0, 2.0, S), rng.normal(size=(S, P))
    damping = np.array([0.0, 1e-2, 10.0])
    lower, upper = np.full(J, -100.0), np.full(J, 100.0)
    q_c, R_c, t_c = compiled.propose(q, R, t, H, g, q_start, prior, z, jz, 3.0, 1.5, lower, upper, damping, False)
    for s in range(S):
        A_s = H[s] + 3.0 * np.outer(jz[s], jz[s])
        A_s[:J, :J] += np.diag(prior)
        b_s = g[s] + 3.0 * (z[s] - 1.5) * jz[s]
        b_s[:J] += prior * (q[s] - q_start[s])
        dx = _damped(A_s, b_s, damping[s])
        np.testing.assert_allclose(q_c[s], q[s] + dx[:J], rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(R_c[s], R[s] @ so3_exp(dx[J:J + 3]), rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(t_c[s], t[s] + dx[J + 3:], rtol=1e-8, atol=1e-10)
    assert np.all(H == np.swapaxes(A, 1, 2) @ A)                              # its inputs are not modified


def test_propose_holds_joints_pushed_past_a_limit_and_poses_only():
    """A joint on its limit whose descent points outward stays there (the others solve the system without it), a
    joint the step would carry past a limit stops at it; a pose-only fit moves (R, t) alone."""
    rng = np.random.default_rng(6)
    J, P = 3, 9
    A = rng.normal(size=(1, 2 * P, P))
    H, g = np.swapaxes(A, 1, 2) @ A, rng.normal(size=(1, P))
    g[0, 0] = abs(g[0, 0]) + 1.0                                             # descent lowers joint 0
    q = np.array([[-1.0, 0.0, 0.0]])
    lower, upper = np.array([-1.0, -5.0, -5.0]), np.array([1.0, 5.0, 5.0])
    R, t = np.eye(3)[None], np.zeros((1, 3))
    q_c, R_c, t_c = compiled.propose(q, R, t, H, g, q, np.zeros(J), np.ones(1), np.zeros((1, P)), 0.0, 0.0, lower,
                                     upper, np.array([1e-3]), False)
    free = np.arange(1, P)
    dx = _damped(H[0][np.ix_(free, free)], g[0, free], 1e-3)
    assert q_c[0, 0] == -1.0
    np.testing.assert_allclose(q_c[0, 1:], np.clip(dx[:J - 1], -5.0, 5.0), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(t_c[0], dx[-3:], rtol=1e-8, atol=1e-10)
    Hp, gp = H[:, J:, J:].copy(), g[:, J:].copy()
    q_c, R_c, t_c = compiled.propose(q, R, t, Hp, gp, q, np.zeros(J), np.ones(1), np.zeros((1, 6)), 0.0, 0.0, lower,
                                     upper, np.array([1e-3]), True)
    dx = _damped(Hp[0], gp[0], 1e-3)
    np.testing.assert_array_equal(q_c, q)
    np.testing.assert_allclose(R_c[0], so3_exp(dx[:3]), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(t_c[0], dx[3:], rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("name", ["panda", "kuka", "baxter"])
def test_the_compiled_loop_fits_as_the_numpy_loop(name, monkeypatch):
    """compiled.lm_fit against Fitter.fit's numpy loop on noisy views with outliers and zero weights: from several
    starts, with and without the depth prior and the chain-growing stages, with known joints; the same fits."""
    from holo_pose_ros.data.generator import load_generator_config
    from holo_pose_ros.fitting import Fitter
    from holo_pose_ros.fitting.synthetic import perturbed_start, sample_problem

    model = RobotModel(name, dtype=torch.float64)
    rng = np.random.default_rng(8)
    generator = load_generator_config("randomized")
    prismatic = np.array([t == "prismatic" for t in model.joint_types])
    for config, depth in (({}, False), ({"grow_chain_levels": 2}, True), ({"robust_loss": "huber"}, True)):
        compiled_fitter, numpy_fitter = Fitter(model, config), Fitter(model, config)
        numpy_fitter.compiled_loop = False
        for _ in range(3):
            problem = sample_problem(compiled_fitter.tree, compiled_fitter.lower, compiled_fitter.upper, generator, rng)
            starts = [perturbed_start(problem, compiled_fitter.lower, compiled_fitter.upper, prismatic, rng, 30.0, 0.1)
                      for _ in range(3)]
            q0, T0 = np.stack([s[0] for s in starts]), np.stack([s[1] for s in starts])
            uv = problem.uv + rng.normal(0, 3.0, problem.uv.shape)
            uv[rng.uniform(size=len(uv)) < 0.1] += 80.0                    # outliers
            weights = rng.uniform(0.0, 1.0, len(uv)) * (rng.uniform(size=len(uv)) > 0.15)
            depth_m = float(problem.T_cam_base[2, 3]) * 1.03 if depth else None
            for known in (None, problem.q):
                a = compiled_fitter.fit(uv, weights, problem.K, q0, T0, known_joints=known, depth_prior_m=depth_m)
                b = numpy_fitter.fit(uv, weights, problem.K, q0, T0, known_joints=known, depth_prior_m=depth_m)
                assert a.iterations == b.iterations and a.start_index == b.start_index
                np.testing.assert_allclose(a.costs, b.costs, rtol=1e-7, atol=1e-9)
                np.testing.assert_allclose(a.q_starts, b.q_starts, atol=1e-7)
                np.testing.assert_allclose(a.T_starts, b.T_starts, atol=1e-7)
                assert a.rms_px == pytest.approx(b.rms_px, rel=1e-7)
