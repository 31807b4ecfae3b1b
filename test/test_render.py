"""Real offscreen renders (Mesa EGL) of markers, primitives and the Panda: projection from K, labels, depth, and the
link-mesh disk cache."""

import pickle
import time

import numpy as np
import pytest

from holo_pose_ros.data.meshes import load_link_meshes
from holo_pose_ros.data.render import DISTRACTOR_LABEL, Light, Material, Primitive, Renderer
from holo_pose_ros.geometry.camera import look_at, project
from holo_pose_ros.robots.kinematics import RobotModel

W, H = 640, 480
K = np.array([[610.0, 0.0, 301.7], [0.0, 590.0, 262.3], [0.0, 0.0, 1.0]])  # principal point off the centre


def translation(x: float, y: float, z: float) -> np.ndarray:
    """A pure translation (4, 4), metres."""
    T = np.eye(4)
    T[:3, 3] = x, y, z
    return T


@pytest.fixture(scope="module")
def renderer():
    r = Renderer(W, H)
    yield r
    r.release()


@pytest.fixture(scope="module")
def panda(panda_meshes):
    """Panda model, meshes (built into a private cache) and its link poses in a camera ~1.5 m away."""
    model, meshes = panda_meshes
    T_cam_base = np.linalg.inv(look_at(np.array([1.2, 0.6, 0.9]), np.array([0.0, 0.0, 0.45])))
    transforms = model.link_transforms(model.neutral, list(meshes))
    poses = {k: T_cam_base @ v[0].double().numpy() for k, v in transforms.items()}
    return model, meshes, T_cam_base, poses


def test_projection_matches_K(renderer):
    """A small sphere centred on camera point P is drawn centred on pixel K P / z (pixel centres at integers)."""
    for P in [(0.0, 0.0, 1.0), (0.21, -0.13, 0.9), (-0.3, 0.25, 1.4), (0.037, 0.011, 0.6)]:
        marker = Primitive("sphere", (0.008, 0, 0), translation(*P))
        labels = renderer.render({}, {}, K, {}, Light(), [marker]).labels
        rows, cols = np.nonzero(labels == DISTRACTOR_LABEL)
        assert len(rows) > 20
        expected = project(np.array(P), K)
        assert np.hypot(cols.mean() - expected[0], rows.mean() - expected[1]) < 0.5, P


def test_depth_is_metric_z(renderer):
    """Depth is z in metres: a fronto-parallel box face and, per pixel, the face plane of a tilted box."""
    box = Primitive("box", (0.4, 0.3, 0.2), translation(0.05, -0.02, 2.0))
    out = renderer.render({}, {}, K, {}, Light(), [box])
    hit = out.labels == DISTRACTOR_LABEL
    assert hit.sum() > 1000
    np.testing.assert_allclose(out.depth[hit], 1.9, atol=1e-3)
    assert (out.depth[~hit] == 0).all()
    assert (out.rgba[..., 3][hit] == 255).all() and (out.rgba[..., 3][~hit] == 0).all()

    angle = np.radians(35.0)
    T = translation(0.0, 0.0, 1.5)
    T[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    thin = Primitive("box", (0.5, 0.5, 0.001), T)
    out = renderer.render({}, {}, K, {}, Light(), [thin])
    rows, cols = np.nonzero(out.labels == DISTRACTOR_LABEL)
    rays = np.linalg.solve(K, np.stack([cols, rows, np.ones_like(cols)]).astype(float))  # (3, N), z = 1
    normal = T[:3, 2]
    z_plane = normal @ T[:3, 3] / (normal @ rays)  # ray-plane intersection depth (mid-plane of the thin box)
    np.testing.assert_allclose(out.depth[rows, cols], z_plane, atol=1e-3)


def test_panda_keypoints_lie_on_robot_pixels(renderer, panda):
    model, meshes, T_cam_base, poses = panda
    labels = renderer.render(poses, meshes, K, {}, Light()).labels
    robot = (labels > 0) & (labels < DISTRACTOR_LABEL)
    assert set(np.unique(labels)) <= set(range(len(meshes) + 1)) and robot.sum() > 5000
    keypoints = model.keypoints(model.neutral)[0].double().numpy()
    keypoints_cam = keypoints @ T_cam_base[:3, :3].T + T_cam_base[:3, 3]
    rows, cols = np.nonzero(robot)
    for name, (u, v) in zip(model.keypoint_names, project(keypoints_cam, K)):
        assert np.hypot(cols - u, rows - v).min() <= 3.0, name


def test_link_labels_only_where_the_link_is(renderer, panda):
    """Pixels labelled k are covered by link k rendered alone, at the same depth."""
    _, meshes, _, poses = panda
    full = renderer.render(poses, meshes, K, {}, Light())
    for k, (name, mesh) in enumerate(meshes.items(), start=1):
        alone = renderer.render(poses, {name: mesh}, K, {}, Light())
        mine = full.labels == k
        assert (alone.labels[mine] == 1).all(), name
        np.testing.assert_array_equal(full.depth[mine], alone.depth[mine])


def test_distractor_in_front_hides_robot(renderer, panda):
    _, meshes, _, poses = panda
    robot_only = renderer.render(poses, meshes, K, {}, Light())
    rows, cols = np.nonzero(robot_only.labels)
    centre = np.linalg.solve(K, [cols.mean(), rows.mean(), 1.0]) * 0.8  # on the ray through the robot, 0.8 m away
    box = Primitive("box", (0.15, 0.15, 0.05), translation(*centre), Material(color=(0.9, 0.1, 0.1)))
    box_only = renderer.render({}, {}, K, {}, Light(), [box]).labels == DISTRACTOR_LABEL
    both = renderer.render(poses, meshes, K, {}, Light(), [box])
    assert (both.labels[box_only] == DISTRACTOR_LABEL).all()
    assert (both.labels[~box_only] == robot_only.labels[~box_only]).all()
    assert (robot_only.labels[box_only] > 0).sum() > 1000  # the box did hide part of the robot


def test_patterns_change_colour_not_labels(renderer, panda):
    _, meshes, _, poses = panda
    plain = renderer.render(poses, meshes, K, {}, Light())
    for pattern in ("stripes", "checker", "noise"):
        material = Material(color=(0.9, 0.9, 0.9), color2=(0.1, 0.2, 0.6), pattern=pattern, pattern_scale=0.04)
        out = renderer.render(poses, meshes, K, {name: material for name in meshes}, Light())
        np.testing.assert_array_equal(out.labels, plain.labels)
        assert np.abs(out.rgba.astype(int) - plain.rgba).mean() > 5, pattern


def test_renderer_survives_pickling(panda):
    """A pickled Renderer carries no GL state and builds its own context on first use (generator workers)."""
    _, meshes, _, poses = panda
    r = pickle.loads(pickle.dumps(Renderer(160, 120)))
    out = r.render(poses, meshes, np.diag([0.25, 0.25, 1.0]) @ K, {}, Light())
    assert out.labels.shape == (120, 160) and (out.labels > 0).sum() > 100
    r.release()


def test_mesh_cache_roundtrip(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    model = RobotModel("panda")
    start = time.perf_counter()
    cold = load_link_meshes(model)
    cold_s = time.perf_counter() - start
    start = time.perf_counter()
    cached = load_link_meshes(model)
    cached_s = time.perf_counter() - start
    assert list(cached) == list(cold)
    for name in cold:
        for field in ("vertices", "normals", "faces", "color"):
            a, b = getattr(cold[name], field), getattr(cached[name], field)
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
    assert cached_s < 0.3 and cached_s < cold_s / 5
    assert len(list((tmp_path / "holo_pose_ros" / "meshes").glob("*.npz"))) == 1
