"""fitting/parts.py: the chains of the shipped robots and the search by parts recovering Baxter
from its true 2D where the whole-tree fit from the same starts (the estimator's: the shipped lifter's best
hypotheses) falls into wrong basins. Seeded; numpy float64."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from holo_pose_ros.data.generator import load_generator_config
from holo_pose_ros.fitting import Fitter
from holo_pose_ros.fitting.parts import PartsFitter, chains_of
from holo_pose_ros.fitting.synthetic import keypoints_in_camera, sample_problem
from holo_pose_ros.geometry.crop import crop_box_from_keypoints
from holo_pose_ros.model.lifter import load_lifter, shipped_lifter
from holo_pose_ros.robots.kinematics import RobotModel

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py


@pytest.fixture(scope="module")
def fitters() -> dict[str, Fitter]:
    return {name: Fitter(RobotModel(name, dtype=torch.float64)) for name in ("panda", "baxter")}


def test_chains_split_baxter_into_head_and_arms(fitters):
    baxter = fitters["baxter"]
    chains = chains_of(baxter.tree)
    names = baxter.robot.joint_names
    assert chains.n_chains == 3
    groups = [{names[j] for j in np.flatnonzero(chains.joint_chain == c)} for c in range(3)]
    assert sorted(map(sorted, groups)) == sorted([["head_pan"], sorted(n for n in names if n.startswith("left_")),
                                                  sorted(n for n in names if n.startswith("right_"))])
    # a left hand point is moved by every left arm joint and by nothing else
    hand = [i for i, k in enumerate(baxter.robot.spec.fit_keypoints) if k.link == "left_hand_link"]
    assert hand and all(set(np.flatnonzero(chains.moves[i])) == {names.index(n) for n in names if n.startswith("left_")}
                        for i in hand)
    # the torso's and pedestal's points move with no joint; every arm point belongs to its arm's chain
    links = [k.link for k in baxter.robot.spec.fit_keypoints]
    assert all(chains.point_chain[i] == -1 for i, link in enumerate(links) if link in ("torso", "pedestal"))
    assert all(names[int(np.flatnonzero(chains.joint_chain == chains.point_chain[i])[0])].startswith("left_")
               for i, link in enumerate(links) if link.startswith("left_") and chains.point_chain[i] >= 0)
    panda = chains_of(fitters["panda"].tree)
    assert panda.n_chains == 1 and (panda.joint_chain == 0).all()


def test_a_fitter_restricted_to_some_points_fits_as_the_whole_one_with_the_others_weighing_0(fitters):
    """Fitter.restricted_to (the sweep's fits): Baxter restricted to its torso's and left arm's points, the bodies of
    the head and the right arm pruned, fits noisy 2D from a perturbed start to the same result as the whole robot
    whose other points weigh 0, with the depth prior on (its root point kept)."""
    baxter = fitters["baxter"]
    chains = chains_of(baxter.tree)
    left = chains.point_chain[[i for i, k in enumerate(baxter.robot.spec.fit_keypoints) if k.link == "left_hand_link"][0]]
    points = np.union1d(np.flatnonzero(np.isin(chains.point_chain, (left, -1))), baxter.depth_points)
    restricted = baxter.restricted_to(points)
    assert restricted.tree.n_points == len(points) and restricted.tree.n_bodies < baxter.tree.n_bodies
    rng = np.random.default_rng(31)
    problem = sample_problem(baxter.tree, baxter.lower, baxter.upper, load_generator_config("randomized"), rng)
    uv = problem.uv + rng.normal(0.0, 3.0, problem.uv.shape)
    w = np.zeros(len(uv))
    w[points] = rng.uniform(0.3, 1.0, len(points))
    q0 = np.clip(problem.q + rng.normal(0.0, 0.2, problem.q.shape), baxter.lower, baxter.upper)
    depth = baxter.prior_depth(problem.q, problem.T_cam_base)
    whole = baxter.fit(uv, w, problem.K, q0[None], problem.T_cam_base[None], depth_prior_m=depth)
    part = restricted.fit(uv[points], w[points], problem.K, q0[None], problem.T_cam_base[None], depth_prior_m=depth)
    assert np.isfinite(whole.cost) and part.cost == pytest.approx(whole.cost, rel=1e-9)
    np.testing.assert_allclose(part.q, whole.q, atol=1e-8)
    np.testing.assert_allclose(part.T_cam_base, whole.T_cam_base, atol=1e-8)
    assert not np.allclose(part.q, q0)                                   # it did fit
    with pytest.raises(ValueError, match="depth prior"):
        baxter.restricted_to(np.setdiff1d(points, baxter.depth_points))


def _lifter_starts(lifter, fitter: Fitter, problem, weights: np.ndarray, n_starts: int = 2):
    """The estimator's lifter starts from exact 2D: the `n_starts` hypotheses that reproject best."""
    n = fitter.robot.n_keypoints
    seen = problem.visible[:n]
    box = crop_box_from_keypoints(problem.uv[:n][seen] if seen.sum() >= 2 else problem.uv[:n], 640, 480)
    f32 = lambda a: torch.from_numpy(np.array(a, dtype=np.float32)[None])  # noqa: E731
    with torch.no_grad():
        q, T = lifter.hypotheses(f32(np.where(problem.visible[:, None], problem.uv, 0.0)), f32(weights), f32(box),
                                 f32(problem.K))
    q, T = q[0].double().numpy(), T[0].double().numpy()
    order = np.argsort(fitter.cost(problem.uv, weights, problem.K, q, T), kind="stable")[:n_starts]
    return q[order], T[order]


def test_parts_recover_baxter_from_true_2d_where_the_whole_fit_does_not(fitters):
    """Random Baxter views seen whole (every fit point in the image), exact 2D, the shipped lifter's two best
    hypotheses as starts: the search by parts recovers >= 95 % within 5 mm (ADD of DREAM's keypoints), the
    whole-tree fit from the same starts well under half; the search never ends above the plain fit's cost."""
    fitter = fitters["baxter"]
    parts = PartsFitter(fitter)
    lifter = load_lifter(shipped_lifter("baxter")).eval()
    generator = load_generator_config("randomized")
    rng = np.random.default_rng(21)
    n = fitter.robot.n_keypoints
    plain_ok, parts_ok = [], []
    while len(parts_ok) < 60:
        problem = sample_problem(fitter.tree, fitter.lower, fitter.upper, generator, rng)
        if not problem.visible.all():
            continue
        weights = np.ones(len(problem.uv))
        q0, T0 = _lifter_starts(lifter, fitter, problem, weights)
        true = keypoints_in_camera(fitter.tree, problem.q, problem.T_cam_base, n)
        plain, searched = fitter.fit(problem.uv, weights, problem.K, q0, T0), parts.fit(problem.uv, weights, problem.K, q0, T0)
        assert searched.cost <= plain.cost + 1e-9
        for result, ok in ((plain, plain_ok), (searched, parts_ok)):
            pred = keypoints_in_camera(fitter.tree, result.q, result.T_cam_base, n)
            ok.append(np.linalg.norm(pred - true, axis=1).mean() < 5e-3)
    assert np.mean(parts_ok) >= 0.95
    assert np.mean(plain_ok) < 0.5


def test_parts_with_known_joints_is_the_plain_pose_fit(fitters):
    fitter = fitters["panda"]
    rng = np.random.default_rng(4)
    problem = sample_problem(fitter.tree, fitter.lower, fitter.upper, load_generator_config("randomized"), rng)
    weights = np.ones(len(problem.uv))
    T0 = problem.T_cam_base.copy()
    T0[:3, 3] *= 1.05
    plain = fitter.fit(problem.uv, weights, problem.K, problem.q[None], T0[None], known_joints=problem.q)
    searched = PartsFitter(fitter).fit(problem.uv, weights, problem.K, problem.q[None], T0[None], known_joints=problem.q)
    assert np.array_equal(plain.q, searched.q) and np.allclose(plain.T_cam_base, searched.T_cam_base)
