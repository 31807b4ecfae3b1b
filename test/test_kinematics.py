"""RobotModel forward kinematics against yourdfpy's independent FK, on the real URDFs of the three robots."""

import numpy as np
import pytest
import torch
import yourdfpy

from holo_pose_ros.robots.description import urdf_file
from holo_pose_ros.robots.kinematics import RobotModel
from holo_pose_ros.robots.spec import available_robots, load_robot_spec

ROBOTS = ["panda", "kuka", "baxter"]


@pytest.fixture(scope="module", params=ROBOTS)
def pair(request):
    model = RobotModel(request.param, dtype=torch.float64)
    reference = yourdfpy.URDF.load(str(urdf_file(model.spec.urdf)), build_scene_graph=True, load_meshes=False)
    return model, reference


def reference_keypoints(model: RobotModel, reference: yourdfpy.URDF, q: np.ndarray) -> np.ndarray:
    """Keypoints (N,3) in the base frame from yourdfpy, driving its actuated joints by URDF name."""
    by_urdf = {j.urdf: v for j, v in zip(model.spec.joints, q)}
    cfg = [by_urdf.get(name, model.spec.fixed_joints.get(name, 0.0)) for name in reference.actuated_joint_names]
    reference.update_cfg(np.array(cfg))
    return np.stack([reference.get_transform(k.link, model.spec.base_link)[:3, 3] for k in model.spec.keypoints])


def test_shipped_robots_are_listed():
    assert set(ROBOTS) <= set(available_robots())


def test_fk_matches_yourdfpy_on_random_configurations(pair):
    model, reference = pair
    gen = torch.Generator().manual_seed(0)
    q = model.sample_uniform(16, gen)
    ours = model.keypoints(q).numpy()
    for b in range(q.shape[0]):
        np.testing.assert_allclose(ours[b], reference_keypoints(model, reference, q[b].numpy()), atol=1e-6)


def test_link_transforms_match_yourdfpy_for_every_link(pair):
    model, reference = pair
    q = model.sample_uniform(1, torch.Generator().manual_seed(1))
    reference_keypoints(model, reference, q[0].numpy())  # sets the reference configuration
    ours = model.link_transforms(q)
    for link, T in ours.items():
        np.testing.assert_allclose(T[0].numpy(), reference.get_transform(link, model.spec.base_link), atol=1e-6)


def test_shapes_limits_and_names(pair):
    model, _ = pair
    spec = model.spec
    assert model.keypoint_names == [k.name for k in spec.keypoints]
    assert model.joint_names == [j.name for j in spec.joints]
    assert model.lower.shape == (model.n_joints,) and bool((model.lower < model.upper).all())
    q = model.sample_uniform(5, torch.Generator().manual_seed(2))
    assert bool(((q >= model.lower) & (q <= model.upper)).all())
    assert model.keypoints(q).shape == (5, model.n_keypoints, 3)
    assert torch.equal(model.clamp(q + 10.0), model.upper.expand(5, -1))


def test_keypoints_in_root_frame_place_the_root_at_the_origin_and_keep_distances(pair):
    model, _ = pair
    q = model.sample_uniform(4, torch.Generator().manual_seed(3))
    base, root = model.keypoints(q), model.keypoints_in_root(q)
    assert torch.allclose(root[:, model.root_index], torch.zeros(4, 3, dtype=root.dtype), atol=1e-9)
    assert torch.allclose(torch.cdist(base, base), torch.cdist(root, root), atol=1e-9)
    T = model.root_transform(q)
    moved = root @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]
    assert torch.allclose(moved, base, atol=1e-9)


def test_fk_is_differentiable_in_the_joints(pair):
    model, _ = pair
    q = model.neutral[None].clone().requires_grad_(True)
    model.keypoints(q).sum().backward()
    assert q.grad is not None and torch.isfinite(q.grad).all() and q.grad.abs().sum() > 0


def test_panda_finger_mimic_follows_the_leader():
    model = RobotModel("panda", dtype=torch.float64)
    q = model.neutral[None].clone()
    q[0, -1] = 0.03
    full = model.full_configuration(q)[0]
    names = model.chain.get_joint_parameter_names()
    assert full[names.index("panda_finger_joint2")] == pytest.approx(0.03)


def test_unknown_robot_and_bad_yaml_get_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown robot 'r2d2'"):
        load_robot_spec("r2d2")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nurdf: {package: pybullet, path: pybullet_data/kuka_iiwa/model.urdf}\nbase_link: a\n")
    with pytest.raises(ValueError, match="missing required key 'keypoints'"):
        load_robot_spec(bad)


@pytest.mark.parametrize("robot", ROBOTS)
def test_fit_keypoints_start_with_dream_and_sit_at_their_link_offsets(robot):
    model = RobotModel(robot, dtype=torch.float64)
    reference = yourdfpy.URDF.load(str(urdf_file(model.spec.urdf)), build_scene_graph=True, load_meshes=False)
    q = model.sample_uniform(3, torch.Generator().manual_seed(1))
    fit = model.fit_keypoints(q).numpy()
    assert fit.shape == (3, model.n_fit_keypoints, 3) and model.n_fit_keypoints > model.n_keypoints + 50
    np.testing.assert_allclose(fit[:, :model.n_keypoints], model.keypoints(q).numpy(), atol=1e-12)
    by_urdf = {j.urdf: v for j, v in zip(model.spec.joints, q[0].numpy())}
    reference.update_cfg(np.array([by_urdf.get(n, model.spec.fixed_joints.get(n, 0.0)) for n in reference.actuated_joint_names]))
    for i, k in enumerate(model.spec.fit_keypoints):
        T = reference.get_transform(k.link, model.spec.base_link)
        np.testing.assert_allclose(fit[0, i], T[:3, :3] @ np.array(k.xyz) + T[:3, 3], atol=1e-6)


@pytest.mark.parametrize("robot", ROBOTS)
def test_every_estimated_joint_moves_at_least_two_fit_keypoints(robot):
    """Observability: a small change of any one joint moves several fit points (so the fit can see it)."""
    model = RobotModel(robot, dtype=torch.float64)
    q = model.sample_uniform(8, torch.Generator().manual_seed(2))
    q = torch.maximum(torch.minimum(q, model.upper - 0.05), model.lower + 0.05)
    base = model.fit_keypoints(q)
    for j, kind in enumerate(model.joint_types):
        moved = q.clone()
        moved[:, j] += 0.01 if kind == "prismatic" else 0.1
        shift = (model.fit_keypoints(moved) - base).norm(dim=-1)  # (B, M) metres
        threshold = 0.004 if kind == "prismatic" else 0.003
        assert ((shift > threshold).sum(1) >= 2).all(), f"{robot}: joint {model.joint_names[j]} barely moves any point"
