"""fitting/: the compiled kinematic tree against yourdfpy's FK and RobotModel, analytic Jacobians against finite
differences, robust losses, the damped step, and the batched LM fit recovering random views of the three shipped
robots (exact and noisy projections, known joints, missing points, several starts). Seeded; numpy float64."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import yaml
import yourdfpy

from holo_pose_ros.data.generator import load_generator_config
from holo_pose_ros.evaluation.metrics import add_auc, add_per_frame, rotation_error_deg
from holo_pose_ros.fitting import BasePrior, Fitter, FitResult, KinematicTree, load_fitting_config
from holo_pose_ros.fitting import compiled
from holo_pose_ros.fitting.residuals import (
    project,
    reprojection_residuals_and_jacobian,
    robust_weights,
    so3_exp,
    transform_points,
)
from holo_pose_ros.fitting.synthetic import keypoints_in_camera, perturbed_start, sample_problem
from holo_pose_ros.resources import config_dir
from holo_pose_ros.robots.description import urdf_file
from holo_pose_ros.robots.kinematics import RobotModel
from holo_pose_ros.robots.spec import load_robot_spec

ROBOTS = ["panda", "kuka", "baxter"]


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py


@pytest.fixture(scope="module")
def models() -> dict[str, RobotModel]:
    return {}


def model_of(models: dict, name: str) -> RobotModel:
    """float64 RobotModel of a shipped robot, built once per module."""
    if name not in models:
        models[name] = RobotModel(name, dtype=torch.float64)
    return models[name]


def yourdfpy_fit_points(model: RobotModel, q: np.ndarray) -> np.ndarray:
    """(M, 3) fit keypoints in the spec's base frame from yourdfpy's own float64 FK (an independent reference)."""
    reference = yourdfpy.URDF.load(str(urdf_file(model.spec.urdf)), build_scene_graph=True, load_meshes=False)
    by_urdf = {j.urdf: v for j, v in zip(model.spec.joints, q)}
    cfg = [by_urdf.get(name, model.spec.fixed_joints.get(name, 0.0)) for name in reference.actuated_joint_names]
    reference.update_cfg(np.array(cfg))
    return np.stack([(reference.get_transform(k.link, model.spec.base_link) @ np.array([*k.xyz, 1.0]))[:3]
                     for k in model.spec.fit_keypoints])


# -- kinematic tree -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ROBOTS)
def test_tree_matches_yourdfpy_and_robot_model(models, name):
    """1e-9 m against yourdfpy's float64 FK; 1e-6 m against RobotModel, whose pytorch-kinematics chain parses the
    URDF origins in float32 (pytorch_kinematics/urdf.py), an error of ~1e-7 m on the float64 values."""
    model = model_of(models, name)
    tree = KinematicTree.from_robot(model)
    q = np.random.default_rng(0).uniform(model.lower.numpy(), model.upper.numpy(), (3, model.n_joints))
    ours = tree.points(q)
    assert ours.shape == (3, model.n_fit_keypoints, 3)
    np.testing.assert_allclose(ours, model.fit_keypoints(torch.from_numpy(q)).numpy(), atol=1e-6, rtol=0)
    np.testing.assert_allclose(ours[0], yourdfpy_fit_points(model, q[0]), atol=1e-9, rtol=0)


@pytest.mark.parametrize("name, base_link, fixed", [
    ("panda", "panda_link3", {}),                                    # base inside the chain: re-rooted tree
    ("baxter", "left_lower_elbow", {"l_gripper_l_finger_joint": 0.012, "r_gripper_l_finger_joint": -0.007}),
])
def test_tree_handles_another_base_link_and_fixed_joints(name, base_link, fixed):
    """A base_link below moving joints and non-zero fixed (non-estimated, mimicked) joints."""
    spec = load_robot_spec(name)
    spec = dataclasses.replace(spec, base_link=base_link, fixed_joints={**spec.fixed_joints, **fixed})
    model = RobotModel(spec, dtype=torch.float64)
    tree = KinematicTree.from_robot(model)
    q = np.random.default_rng(1).uniform(model.lower.numpy(), model.upper.numpy(), (2, model.n_joints))
    ours = tree.points(q)
    np.testing.assert_allclose(ours, model.fit_keypoints(torch.from_numpy(q)).numpy(), atol=1e-6, rtol=0)
    np.testing.assert_allclose(ours[1], yourdfpy_fit_points(model, q[1]), atol=1e-9, rtol=0)


@pytest.mark.parametrize("name", ROBOTS)
def test_tree_jacobian_matches_finite_differences(models, name):
    model = model_of(models, name)
    tree = KinematicTree.from_robot(model)
    q = np.random.default_rng(2).uniform(model.lower.numpy(), model.upper.numpy(), (2, model.n_joints))
    P, dP = tree.points_and_jacobian(q)
    np.testing.assert_allclose(P, tree.points(q), atol=1e-12)
    assert dP.shape == (2, tree.n_points, 3, tree.n_joints)
    eps = 1e-6
    for j in range(tree.n_joints):
        step = np.zeros(tree.n_joints)
        step[j] = eps
        numeric = (tree.points(q + step) - tree.points(q - step)) / (2 * eps)
        np.testing.assert_allclose(dP[..., j], numeric, atol=1e-8)


# -- residuals ------------------------------------------------------------------------------------------------
def _pose_problem(rng: np.random.Generator, S: int = 2, M: int = 9, J: int = 4):
    """Random base points, dP/dq, poses 1.5-2.5 m ahead and a K with skew."""
    P = rng.normal(0.0, 0.3, (S, M, 3))
    dP = rng.normal(size=(S, M, 3, J))
    R = so3_exp(rng.normal(size=(S, 3)))
    t = np.column_stack([rng.normal(0, 0.1, (S, 2)), rng.uniform(1.5, 2.5, S)])
    K = np.array([[610.0, 2.0, 318.0], [0.0, 605.0, 243.0], [0.0, 0.0, 1.0]])
    uv = rng.uniform(0, 480, (M, 2))
    return P, dP, R, t, K, uv


def test_residual_jacobian_matches_finite_differences():
    """Columns (dq, dphi, dt) with R <- R exp(dphi) (right increment) and t <- t + dt, by central differences of
    the residuals where P moves along dP/dq."""
    P, dP, R, t, K, uv = _pose_problem(np.random.default_rng(3))
    S, M, _, J = dP.shape
    r, jac = reprojection_residuals_and_jacobian(P, dP, R, t, K, uv, 0.05)
    np.testing.assert_allclose(r, project(transform_points(P, R, t), K, 0.05) - uv, atol=1e-12)
    assert jac.shape == (S, M, 2, J + 6)
    eps = 1e-6
    for k in range(J + 6):
        d = np.zeros(J + 6)
        d[k] = eps

        def res(sign):
            x = sign * d
            P_ = P + dP @ x[:J]
            return project(transform_points(P_, R @ so3_exp(np.tile(x[J:J + 3], (S, 1))), t + x[J + 3:]), K, 0.05) - uv

        np.testing.assert_allclose(jac[..., k], (res(1) - res(-1)) / (2 * eps), rtol=1e-5, atol=1e-5)
    _, jac_pose = reprojection_residuals_and_jacobian(P, None, R, t, K, uv, 0.05)
    np.testing.assert_allclose(jac_pose, jac[..., J:], atol=1e-12)


def test_points_behind_the_camera_stay_finite():
    """Depth clamped at min_depth_m: finite residuals, no depth derivative for the clamped points."""
    P, dP, R, t, K, uv = _pose_problem(np.random.default_rng(4))
    t = t.copy()
    t[:, 2] = 0.0                                                             # the camera inside the point cloud
    r, jac = reprojection_residuals_and_jacobian(P, dP, R, t, K, uv, 0.05)
    assert np.isfinite(r).all() and np.isfinite(jac).all()
    behind = (P @ np.swapaxes(R, 1, 2) + t[:, None])[..., 2] < 0.05
    assert behind.any()
    assert np.all(jac[..., -1][behind] == 0.0)                                 # d/dt_z


@pytest.mark.parametrize("loss", ["squared", "huber", "cauchy"])
def test_robust_weights_are_the_derivative_of_the_loss(loss):
    s = np.array([0.0, 1e-3, 4.0, 80.0, 99.0, 101.0, 400.0, 1e4])
    rho, drho = robust_weights(s, loss, 10.0)
    eps = 1e-6
    numeric = (robust_weights(s + eps, loss, 10.0)[0] - robust_weights(np.maximum(s - eps, 0), loss, 10.0)[0]) / (
        s + eps - np.maximum(s - eps, 0))
    np.testing.assert_allclose(drho, numeric, rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(rho[:3], s[:3], rtol=0.05)                     # quadratic for small residuals
    assert np.all((drho > 0) & (drho <= 1))
    with pytest.raises(ValueError):
        robust_weights(s, "tukey", 10.0)


# -- the fit --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def generator_config() -> dict:
    return load_generator_config("randomized")


def _record_joints(monkeypatch: pytest.MonkeyPatch) -> list[np.ndarray]:
    """Every q the fit linearizes at, i.e. every iterate of every start (the real linearization runs)."""
    seen: list[np.ndarray] = []
    real = compiled.linearize

    def recording(q, *args):
        seen.append(np.array(q, copy=True))
        return real(q, *args)

    monkeypatch.setattr(compiled, "linearize", recording)
    return seen


def _add_m(fitter: Fitter, result: FitResult, problem) -> float:
    """ADD (metres) over DREAM's keypoints (the first N fit points), camera frame."""
    n = fitter.robot.n_keypoints
    return float(add_per_frame(keypoints_in_camera(fitter.tree, result.q, result.T_cam_base, n)[None],
                               keypoints_in_camera(fitter.tree, problem.q, problem.T_cam_base, n)[None])[0])


def _prismatic(model: RobotModel) -> np.ndarray:
    return np.array([t == "prismatic" for t in model.joint_types])


@pytest.mark.parametrize("name", ROBOTS)
def test_fit_recovers_random_views_from_30_degree_starts(models, generator_config, name, monkeypatch):
    """Joints uniform within the limits, a randomized camera (640x480), exact projections of every fit point in
    front of the camera; one start 30 degrees off (each joint, the base rotation) with 10 % depth error. Starts
    this far need the coarse-to-fine stages (2 levels; off by default, where the starts are closer): without them
    Baxter's long chains recover 84 % of the views, not 95 %."""
    model = model_of(models, name)
    fitter = Fitter(model, {"grow_chain_levels": 2})
    fitter.compiled_loop = False    # the numpy loop, whose iterates can be recorded (the compiled one agrees: below)
    seen = _record_joints(monkeypatch)
    rng = np.random.default_rng(10)
    adds = []
    for _ in range(50):
        problem = sample_problem(fitter.tree, fitter.lower, fitter.upper, generator_config, rng)
        q0, T0 = perturbed_start(problem, fitter.lower, fitter.upper, _prismatic(model), rng)
        result = fitter.fit(problem.uv, np.ones(len(problem.uv)), problem.K, q0[None], T0[None])
        adds.append(_add_m(fitter, result, problem))
    adds = np.array(adds)
    assert np.median(adds) < 1e-3
    assert np.mean(adds < 5e-3) >= 0.95
    every_q = np.concatenate(seen)
    assert np.all(every_q >= fitter.lower) and np.all(every_q <= fitter.upper)


def test_fit_with_2px_noise_keeps_add_auc_above_80(models, generator_config):
    """Panda, 2 px Gaussian noise on every fit point, one 30-degree start: ADD AUC (0-100 mm) >= 80."""
    model = model_of(models, "panda")
    fitter = Fitter(model)
    rng = np.random.default_rng(11)
    adds, rms = [], []
    for _ in range(100):
        problem = sample_problem(fitter.tree, fitter.lower, fitter.upper, generator_config, rng)
        q0, T0 = perturbed_start(problem, fitter.lower, fitter.upper, _prismatic(model), rng)
        uv = problem.uv + rng.normal(0.0, 2.0, problem.uv.shape)
        result = fitter.fit(uv, np.ones(len(uv)), problem.K, q0[None], T0[None])
        adds.append(_add_m(fitter, result, problem))
        rms.append(result.rms_px)
    assert add_auc(np.array(adds)) >= 80.0
    assert 2.5 < np.median(rms) < 2.9                     # the noise (2 sqrt(2) = 2.83 px per point), not more


def test_known_joints_fits_only_the_pose(models, generator_config):
    model = model_of(models, "kuka")
    fitter = Fitter(model)
    rng = np.random.default_rng(12)
    for _ in range(5):
        problem = sample_problem(fitter.tree, fitter.lower, fitter.upper, generator_config, rng)
        q0, T0 = perturbed_start(problem, fitter.lower, fitter.upper, _prismatic(model), rng)
        result = fitter.fit(problem.uv, np.ones(len(problem.uv)), problem.K, q0[None], T0[None],
                            known_joints=problem.q)
        assert np.array_equal(result.q, problem.q)
        assert _add_m(fitter, result, problem) < 1e-4
        assert rotation_error_deg(result.T_cam_base[None, :3, :3], problem.T_cam_base[None, :3, :3])[0] < 0.01


def test_depth_prior_corrects_detections_shrunk_about_their_centre(models, generator_config):
    """2D points shrunk by 4 % about their centroid (the bias of today's heatmaps) put the robot too far, even with
    the true joints; the prior at the true depth (of the root keypoint: config depth_prior_on, weight and sigma) takes well over half of that error away."""
    model = model_of(models, "panda")
    fitter = Fitter(model)
    rng = np.random.default_rng(14)
    errors = {False: [], True: []}
    for _ in range(20):
        problem = sample_problem(fitter.tree, fitter.lower, fitter.upper, generator_config, rng)
        centre = problem.uv.mean(0)
        uv = centre + 0.96 * (problem.uv - centre)
        z_true = fitter.prior_depth(problem.q, problem.T_cam_base)
        for prior in (False, True):
            result = fitter.fit(uv, np.ones(len(uv)), problem.K, problem.q[None], problem.T_cam_base[None],
                                known_joints=problem.q, depth_prior_m=z_true if prior else None)
            errors[prior].append(abs(fitter.prior_depth(result.q, result.T_cam_base) - z_true))
    assert np.median(errors[False]) > 0.03                 # ~4 % of 1-3 m
    assert np.median(errors[True]) < 0.5 * np.median(errors[False])


def test_the_known_joints_weight_weighs_the_depth_prior_only_when_the_joints_are_known(models, generator_config):
    """`known_joints_depth_prior_weight` (the calibration mode's) replaces depth_prior_weight in a fit with known
    joints: at 0 the shrunk points of the test above put the robot exactly where they do without a prior, at null
    the prior pulls as before; a fit of the joints too is the same whatever that weight."""
    model = model_of(models, "panda")
    fitters = {w: Fitter(model, {"known_joints_depth_prior_weight": w}) for w in (None, 0.0)}
    rng = np.random.default_rng(16)
    errors = {False: [], True: []}
    for _ in range(8):
        problem = sample_problem(fitters[None].tree, fitters[None].lower, fitters[None].upper, generator_config, rng)
        centre = problem.uv.mean(0)
        uv = centre + 0.96 * (problem.uv - centre)
        z_true = fitters[None].prior_depth(problem.q, problem.T_cam_base)
        depth = {}
        for w, fitter in fitters.items():
            for prior in (False, True):
                result = fitter.fit(uv, np.ones(len(uv)), problem.K, problem.q[None], problem.T_cam_base[None],
                                    known_joints=problem.q, depth_prior_m=z_true if prior else None)
                depth[w, prior] = fitter.prior_depth(result.q, result.T_cam_base)
        assert depth[0.0, True] == pytest.approx(depth[0.0, False], abs=1e-9)
        for prior in (False, True):
            errors[prior].append(abs(depth[None, prior] - z_true))
        q0 = np.clip(problem.q + 0.1, fitters[None].lower, fitters[None].upper)
        free = [f.fit(uv, np.ones(len(uv)), problem.K, q0[None], problem.T_cam_base[None], depth_prior_m=z_true)
                for f in fitters.values()]
        assert np.array_equal(free[0].q, free[1].q) and np.array_equal(free[0].T_cam_base, free[1].T_cam_base)
    assert np.median(errors[True]) < 0.5 * np.median(errors[False])


def test_base_prior_pulls_the_base_pose_towards_it(models, generator_config):
    """Joints and base fitted to noisy 2D (2 px): a base prior at the true pose takes most of the base's error
    away; a tight prior 5 cm off holds the base there; one of sigma 10 m changes nothing. Invalid priors are
    refused."""
    model = model_of(models, "panda")
    fitter = Fitter(model)
    rng = np.random.default_rng(15)
    errors = {"none": [], "truth": [], "loose": [], "held": []}
    for _ in range(15):
        problem = sample_problem(fitter.tree, fitter.lower, fitter.upper, generator_config, rng)
        uv = problem.uv + rng.normal(0, 2.0, problem.uv.shape)
        off = problem.T_cam_base.copy()
        off[:3, 3] += [0.05, 0.0, 0.0]
        priors = {"none": None, "truth": BasePrior(problem.T_cam_base, 0.005, np.radians(0.5)),
                  "loose": BasePrior(problem.T_cam_base, 10.0, np.pi), "held": BasePrior(off, 0.001, np.radians(0.05))}
        for name, prior in priors.items():
            result = fitter.fit(uv, np.ones(len(uv)), problem.K, problem.q[None], problem.T_cam_base[None],
                                base_prior=prior)
            target = off if name == "held" else problem.T_cam_base
            errors[name].append(np.linalg.norm(result.T_cam_base[:3, 3] - target[:3, 3]))
    median = {k: float(np.median(v)) for k, v in errors.items()}
    assert median["none"] > 0.002, median                       # 2 px of noise leave the base millimetres off
    assert median["truth"] < 0.5 * median["none"], median
    assert abs(median["loose"] - median["none"]) < 0.1 * median["none"], median
    assert median["held"] < 0.005, median                       # the 5 cm offset is held
    with pytest.raises(ValueError, match="positive sigmas"):
        BasePrior(np.eye(4), 0.0, 0.1)
    with pytest.raises(ValueError, match="finite 4 x 4"):
        BasePrior(np.eye(3), 0.01, 0.1)


def test_several_starts_lowest_cost_wins(models, generator_config):
    """One 30-degree start among three random ones (joints anywhere, base rotated 90 degrees): all solved
    together, the result is the start of lowest final cost and matches Fitter.cost."""
    model = model_of(models, "panda")
    fitter = Fitter(model)
    rng = np.random.default_rng(13)
    problem = sample_problem(fitter.tree, fitter.lower, fitter.upper, generator_config, rng)
    good = perturbed_start(problem, fitter.lower, fitter.upper, _prismatic(model), rng)
    bad = [(rng.uniform(fitter.lower, fitter.upper),
            perturbed_start(problem, fitter.lower, fitter.upper, _prismatic(model), rng, 90.0)[1]) for _ in range(3)]
    starts = bad[:2] + [good] + bad[2:]
    q0, T0 = np.stack([s[0] for s in starts]), np.stack([s[1] for s in starts])
    weights = np.ones(len(problem.uv))
    result = fitter.fit(problem.uv, weights, problem.K, q0, T0)
    assert result.costs.shape == (4,)
    assert result.start_index == int(np.argmin(result.costs)) and result.cost == result.costs.min()
    assert _add_m(fitter, result, problem) < 1e-3
    np.testing.assert_allclose(fitter.cost(problem.uv, weights, problem.K, result.q[None], result.T_cam_base[None]),
                               [result.cost], rtol=1e-9)
    before = fitter.cost(problem.uv, weights, problem.K, q0, T0)                 # the starts' own costs
    assert before.shape == (4,) and np.all(before > result.cost)


def test_missing_points_do_not_break_the_fit(models, generator_config):
    """Zero weights (missing points), NaN pixels on them, all but 3 zero, all zero: a result every time."""
    model = model_of(models, "baxter")
    fitter = Fitter(model)
    rng = np.random.default_rng(14)
    problem = sample_problem(fitter.tree, fitter.lower, fitter.upper, generator_config, rng)
    q0, T0 = perturbed_start(problem, fitter.lower, fitter.upper, _prismatic(model), rng)
    M = len(problem.uv)
    weights = (rng.random(M) < 0.6).astype(float)
    uv = np.where(weights[:, None] > 0, problem.uv, np.nan)
    result = fitter.fit(uv, weights, problem.K, q0[None], T0[None])
    assert result.n_points == int(weights.sum())
    assert _add_m(fitter, result, problem) < 5e-3
    for n_kept in (3, 0):
        weights = np.zeros(M)
        weights[rng.choice(M, n_kept, replace=False)] = 1.0
        result = fitter.fit(problem.uv, weights, problem.K, np.stack([q0, q0]), np.stack([T0, T0]))
        assert result.n_points == n_kept and result.cost == np.inf and result.iterations == 0
        assert np.all(np.isfinite(result.q)) and np.all(np.isfinite(result.T_cam_base))
        assert np.all(result.q >= fitter.lower) and np.all(result.q <= fitter.upper)
    assert result.rms_px == np.inf
    assert np.all(fitter.cost(uv, np.zeros(M), problem.K, q0[None], T0[None]) == np.inf)


def test_coarse_to_fine_stages_grow_from_the_base(models):
    """Stage weights: nested point sets growing from the base, each short of all points; none when off."""
    model = model_of(models, "baxter")
    fitter = Fitter(model, {"grow_chain_levels": 2})
    w = np.ones(model.n_fit_keypoints)
    stages = fitter._stage_weights(w)
    assert len(stages) >= 2
    counts = [np.count_nonzero(s) for s in stages]
    assert counts == sorted(counts) and counts[-1] < len(w) and counts[0] >= fitter.config["min_points"]
    for a, b in zip(stages, stages[1:]):
        assert np.all(b[a > 0] > 0)
    assert np.all(fitter.tree.point_depth[stages[0] > 0] == 0)
    assert Fitter(model)._stage_weights(w) == []  # off by default


def test_start_with_points_behind_the_camera_returns_finite_result(models, generator_config):
    """A start whose base sits at the camera (half the robot behind it): clamped depths, a finite fit."""
    model = model_of(models, "panda")
    fitter = Fitter(model)
    rng = np.random.default_rng(15)
    problem = sample_problem(fitter.tree, fitter.lower, fitter.upper, generator_config, rng)
    T0 = problem.T_cam_base.copy()
    T0[:3, 3] = [0.0, 0.0, 0.1]
    result = fitter.fit(problem.uv, np.ones(len(problem.uv)), problem.K, problem.q[None], T0[None])
    assert np.isfinite(result.cost) and np.all(np.isfinite(result.T_cam_base))


def test_prior_depth_is_the_root_keypoints_or_the_centroids(models):
    model = model_of(models, "panda")
    q = np.zeros(model.n_joints)
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 2.0]
    P = Fitter(model).tree.points(q[None])[0]
    assert Fitter(model, {"depth_prior_on": "root"}).prior_depth(q, T) == pytest.approx(P[model.root_index, 2] + 2.0)
    assert Fitter(model, {"depth_prior_on": "centroid"}).prior_depth(q, T) == pytest.approx(P[:, 2].mean() + 2.0)
    with pytest.raises(ValueError, match="depth_prior_on"):
        Fitter(model, {"depth_prior_on": "tip"})


def test_config_defaults_overrides_and_errors(tmp_path):
    path = config_dir() / "fitting.yaml"
    defaults = yaml.safe_load(path.read_text())
    assert load_fitting_config() == defaults
    for line in path.read_text().splitlines():                                 # every parameter documented
        if line and not line.startswith((" ", "#")):
            assert "#" in line, line
    override = tmp_path / "fit.yaml"
    override.write_text("iterations: 3\nrobust_loss: cauchy\n")
    cfg = load_fitting_config(str(override))
    assert cfg["iterations"] == 3 and cfg["robust_loss"] == "cauchy" and cfg["min_points"] == defaults["min_points"]
    assert load_fitting_config({"robust_scale_px": 4.0})["robust_scale_px"] == 4.0
    with pytest.raises(ValueError, match="unknown fitting parameters"):
        load_fitting_config({"iteratons": 3})
    with pytest.raises(ValueError, match="robust_loss"):
        load_fitting_config({"robust_loss": "tukey"})
