"""The silhouette term of the fit (fitting/silhouette.py, fitting/surface.py, Fitter.fit(silhouette=...)): the signed
distance field against scipy's exact Euclidean distance transform and its gradient, outline points and normals, the
surface points riding the kinematic tree, finite-difference Jacobians of the residuals wrt (dq, dphi, dt), and on a
real render of Panda (the project's renderer and meshes) the depth recovered from the exact mask with the true
joints, and how much better that is than from a few noisy keypoints. Seeded; numpy float64."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import distance_transform_edt

from holo_pose_ros.data.meshes import load_link_meshes
from holo_pose_ros.data.render import DISTRACTOR_LABEL, Light, Renderer
from holo_pose_ros.fitting import Fitter, KinematicTree
from holo_pose_ros.fitting.residuals import project, reprojection_residuals_and_jacobian, so3_exp, transform_points
from holo_pose_ros.fitting.silhouette import (
    Silhouette,
    chamfer_residuals,
    contour_weights,
    signed_distance_residuals,
)
from holo_pose_ros.fitting.surface import sample_surface_points
from holo_pose_ros.geometry.camera import look_at
from holo_pose_ros.robots.kinematics import RobotModel

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py

W, H = 640, 480
K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
Q = np.array([0.3, -0.4, 0.2, -2.0, 0.1, 1.9, 0.6, 0.03])  # a typical working pose, radians (finger: metres)
FEW = np.array([0, 2, 4, 6])                                 # DREAM keypoints panda_link0, 3, 6 and hand


@pytest.fixture(scope="module")
def panda():
    """float64 Panda model, its link meshes and a Fitter with the silhouette's surface points."""
    model = RobotModel("panda", dtype=torch.float64)
    meshes = load_link_meshes(model)
    return model, meshes, Fitter(model, meshes=meshes)


@pytest.fixture(scope="module")
def scene(panda):
    """(T_cam<-base, exact robot mask (H, W) bool) of Panda at Q, seen from ~1.5 m, rendered by the project's
    renderer: the labels of the robot's links."""
    model, meshes, _ = panda
    T = np.linalg.inv(look_at(np.array([1.3, 0.6, 0.8]), np.array([0.0, 0.0, 0.45])))
    links = model.link_transforms(torch.from_numpy(Q[None]), list(meshes))
    renderer = Renderer(W, H)
    poses = {name: T @ pose[0].numpy() for name, pose in links.items()}
    labels = renderer.render(poses, meshes, K, {}, Light()).labels
    renderer.release()
    mask = (labels > 0) & (labels != DISTRACTOR_LABEL)
    assert mask.sum() > 10000 and not (mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())
    return T, mask


def reference_signed_distance(mask: np.ndarray) -> np.ndarray:
    """Distance to the nearest foreground minus distance to the nearest background pixel centre (scipy, exact)."""
    return distance_transform_edt(~mask) - distance_transform_edt(mask)


def blob_mask() -> np.ndarray:
    """(60, 80) mask: a disc, a rectangle with a hole, and a thin bar."""
    v, u = np.mgrid[:60, :80]
    mask = (u - 25) ** 2 + (v - 30) ** 2 < 12 ** 2
    mask |= (u >= 45) & (u < 65) & (v >= 15) & (v < 45) & ~((u >= 52) & (u < 57) & (v >= 25) & (v < 30))
    mask |= (u >= 10) & (u < 70) & (v >= 50) & (v < 52)
    return mask


# -- the distance field -------------------------------------------------------------------------------------
def test_signed_distance_is_exact_at_pixel_centres():
    mask = blob_mask()
    sil = Silhouette(mask, margin_px=4)
    h, w = sil.distance.shape
    v, u = np.mgrid[:h, :w]
    uv = np.stack([u, v], axis=-1) + sil.origin
    value, _ = sil.sample(uv)
    reference = reference_signed_distance(mask)[v + int(sil.origin[1]), u + int(sil.origin[0])]
    np.testing.assert_allclose(value, reference, atol=1e-4)
    assert (value[mask[v + int(sil.origin[1]), u + int(sil.origin[0])]] < 0).all()


def test_signed_distance_gradient_and_outline_of_a_half_plane():
    """Foreground u <= 40: d = u - 40 on the background, u - 41 on the foreground, 0 on the outline u = 40.5, and
    gradient (1, 0) at sub-pixel positions."""
    mask = np.zeros((60, 80), bool)
    mask[:, :41] = True
    sil = Silhouette(mask)
    rng = np.random.default_rng(0)
    u = np.concatenate([rng.uniform(20, 39.9, 50), rng.uniform(41.1, 55, 50)])
    uv = np.column_stack([u, rng.uniform(1, 58, 100)])
    value, grad = sil.sample(uv)
    np.testing.assert_allclose(value, np.where(uv[:, 0] > 40.5, uv[:, 0] - 40, uv[:, 0] - 41), atol=1e-6)
    np.testing.assert_allclose(grad, np.tile([1.0, 0.0], (100, 1)), atol=1e-6)
    assert abs(sil.sample(np.array([40.5, 30.0]))[0]) < 1e-6


def test_signed_distance_gradient_matches_finite_differences():
    sil = Silhouette(blob_mask())
    rng = np.random.default_rng(1)
    uv = rng.uniform(5, 70, (200, 2)) + 0.01                                   # off the pixel grid
    uv = uv[np.all(np.abs(uv - np.round(uv)) > 0.01, axis=1)]
    _, grad = sil.sample(uv)
    eps = 1e-6
    for k in range(2):
        step = np.zeros(2)
        step[k] = eps
        numeric = (sil.sample(uv + step)[0] - sil.sample(uv - step)[0]) / (2 * eps)
        np.testing.assert_allclose(grad[:, k], numeric, atol=1e-6)


def test_sampling_outside_the_window_and_the_image():
    """Beyond the window (in the image): the window's edge value plus the distance to it, pointing back; beyond the
    image: the image edge's value, no pull across the border."""
    mask = np.zeros((60, 80), bool)
    mask[20:30, 30:40] = True
    sil = Silhouette(mask, margin_px=3)                                        # window u 27..42, v 17..32
    edge, _ = sil.sample(np.array([42.0, 25.0]))
    value, grad = sil.sample(np.array([50.0, 25.0]))
    assert value == pytest.approx(edge + 8.0) and grad == pytest.approx([1.0, 0.0])
    touching = np.zeros((60, 80), bool)
    touching[20:30, :10] = True                                                # cut off by the image's left edge
    sil = Silhouette(touching)
    inside_edge, _ = sil.sample(np.array([0.0, 25.0]))
    value, grad = sil.sample(np.array([-7.0, 25.0]))
    assert value == pytest.approx(inside_edge) and grad[0] == 0.0


def test_outline_points_lie_on_the_outline_with_outward_normals():
    v, u = np.mgrid[:80, :100]
    centre = np.array([50.0, 40.0])
    disc = (u - centre[0]) ** 2 + (v - centre[1]) ** 2 <= 20 ** 2
    sil = Silhouette(disc, boundary_budget=60)
    assert len(sil.boundary) == 60
    radial = sil.boundary - centre
    distance = np.linalg.norm(radial, axis=1)
    assert np.all((distance > 19.4) & (distance < 21.1))                     # staircase of the pixel disc
    np.testing.assert_allclose(sil.sample(sil.boundary)[0], 0.0, atol=1e-6)  # midway: the zero crossing
    assert np.all(np.sum(sil.normals * radial / distance[:, None], axis=1) > 0.95)
    cut = np.zeros((40, 60), bool)
    cut[10:20, :10] = True                                                     # no outline along the image border
    boundary = Silhouette(cut).boundary
    across = boundary[:, 0] % 1.0 == 0.5                                       # between horizontal neighbours
    assert np.all(boundary[across, 0] == 9.5) and np.all(boundary[~across, 1] % 1.0 == 0.5)
    with pytest.raises(ValueError, match="no foreground"):
        Silhouette(np.zeros((10, 10), bool))


# -- surface points -------------------------------------------------------------------------------------------
def test_surface_points_are_vertices_spread_over_the_links(panda):
    _, meshes, fitter = panda
    surface = sample_surface_points(meshes, 400)
    counts = {name: len(p) for name, (p, _) in surface.items()}
    assert set(counts) == set(meshes) and min(counts.values()) >= 2 and abs(sum(counts.values()) - 400) <= len(meshes)
    for name, (points, normals) in surface.items():
        vertices = meshes[name].vertices.astype(float)
        assert np.min(np.linalg.norm(points[:, None] - vertices[None], axis=-1), axis=1).max() == 0.0
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    again = sample_surface_points(meshes, 400)
    assert all(np.array_equal(surface[n][0], again[n][0]) for n in surface)
    assert fitter.surface_tree.n_points == sum(counts.values())


def test_link_points_ride_the_tree(panda):
    """Points in link frames, placed by KinematicTree.with_link_points, against RobotModel's link poses; their
    Jacobian against finite differences; the fit keypoints' tree is left as it was."""
    model, meshes, fitter = panda
    tree = KinematicTree.from_robot(model)
    rng = np.random.default_rng(2)
    local = {name: rng.normal(0.0, 0.05, (3, 3)) for name in list(meshes)[::2]}
    extra = tree.with_link_points(local)
    q = rng.uniform(model.lower.numpy(), model.upper.numpy(), (2, model.n_joints))
    poses = model.link_transforms(torch.from_numpy(q), list(local))
    expected = np.concatenate([p @ np.swapaxes(poses[n].numpy()[:, :3, :3], 1, 2) + poses[n].numpy()[:, None, :3, 3]
                               for n, p in local.items()], axis=1)
    np.testing.assert_allclose(extra.points(q), expected, atol=1e-6)
    P, dP = extra.points_and_jacobian(q)
    eps = 1e-6
    for j in range(model.n_joints):
        step = np.zeros(model.n_joints)
        step[j] = eps
        np.testing.assert_allclose(dP[..., j], (extra.points(q + step) - extra.points(q - step)) / (2 * eps), atol=1e-8)
    np.testing.assert_array_equal(tree.points(q), fitter.tree.points(q))
    with pytest.raises(ValueError, match="not in the kinematic tree"):
        tree.with_link_points({"no_such_link": np.zeros((1, 3))})


# -- residual Jacobians ----------------------------------------------------------------------------------------
def _perturbed_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R (1, 3, 3), t (1, 3)) a little off T: 3 % nearer, shifted and turned, so points lie on both sides."""
    R = (T[:3, :3] @ so3_exp(np.radians(2.0) * np.array([0.4, -0.3, 0.5])))[None]
    return R, (T[:3, 3] * 0.97 + [0.01, -0.01, 0.0])[None]


@pytest.mark.parametrize("kind", ["signed_distance", "chamfer"])
def test_residual_jacobians_match_finite_differences(panda, scene, kind):
    """Columns (dq, dphi, dt) as in fitting/residuals.py, by central differences through the real FK and projection,
    checked wherever the residual is smooth there (the bilinear field has kinks on the pixel grid and the nearest
    matches may switch: entries where the one-sided differences disagree are left out, at most 2 %)."""
    model, _, fitter = panda
    T, mask = scene
    sil = fitter.silhouette(mask)
    tree = fitter.surface_tree
    R, t = _perturbed_pose(T)
    q = Q[None]

    def residuals(x: np.ndarray, with_jacobian: bool = False):
        qx = q + x[:model.n_joints]
        Rx, tx = R @ so3_exp(x[None, model.n_joints:model.n_joints + 3]), t + x[model.n_joints + 3:]
        P, dP = tree.points_and_jacobian(qx)
        if with_jacobian:
            uv, duv = reprojection_residuals_and_jacobian(P, dP, Rx, tx, K, np.zeros(2), 0.05)
        else:
            uv, duv = project(transform_points(P, Rx, tx), K, 0.05), None
        if kind == "signed_distance":
            return signed_distance_residuals(uv, duv, sil)
        return chamfer_residuals(uv, duv, sil.boundary, sil.normals)

    n = model.n_joints + 6
    r0, jac = residuals(np.zeros(n), True)
    assert jac.shape == r0.shape + (n,)
    eps, checked, total = 1e-6, 0, 0
    for k in range(n):
        x = np.zeros(n)
        x[k] = eps
        plus, minus = residuals(x)[0], residuals(-x)[0]
        smooth = np.abs((plus - r0) - (r0 - minus)) <= 1e-4 * np.abs(plus - minus) + 1e-10
        np.testing.assert_allclose(jac[..., k][smooth], ((plus - minus) / (2 * eps))[smooth], rtol=1e-4, atol=1e-5)
        checked, total = checked + smooth.sum(), total + smooth.size
    assert checked >= 0.98 * total


def test_contour_weights_pick_points_seen_edge_on():
    X = np.array([[[0.0, 0.0, 2.0], [0.0, 0.0, 2.0], [0.0, 0.0, 2.0]]])
    normals = np.array([[[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, np.sqrt(0.99), 0.1]]])
    np.testing.assert_allclose(contour_weights(normals, X, 0.2), [[1.0, 0.0, 0.75]])


# -- the fit --------------------------------------------------------------------------------------------------
def _start(T: np.ndarray, depth_factor: float) -> np.ndarray:
    """T_cam<-base with the base's distance scaled by depth_factor and 2 cm / 1.5 cm off sideways."""
    T0 = T.copy()
    T0[:3, 3] = T[:3, 3] * depth_factor + [0.02, -0.015, 0.0]
    return T0


def _depth_errors(fitter: Fitter, T_fit: np.ndarray, T: np.ndarray, q_fit: np.ndarray = Q) -> tuple[float, float]:
    """Relative errors of the root keypoint's (fitted at joints q_fit) and the base's camera depth."""
    return fitter.prior_depth(q_fit, T_fit) / fitter.prior_depth(Q, T) - 1.0, T_fit[2, 3] / T[2, 3] - 1.0


@pytest.mark.parametrize("depth_factor", [1.05, 0.95])
def test_silhouette_alone_recovers_the_depth(panda, scene, depth_factor):
    """True joints, no keypoint (all weights 0), a start 5 % off in depth: root and base depth within 0.5 %."""
    _, _, fitter = panda
    T, mask = scene
    M = fitter.tree.n_points
    result = fitter.fit(np.zeros((M, 2)), np.zeros(M), K, Q[None], _start(T, depth_factor)[None], known_joints=Q,
                        silhouette=fitter.silhouette(mask))
    assert result.n_points == 0 and np.isfinite(result.cost) and result.silhouette_cost is not None
    root, base = _depth_errors(fitter, result.T_cam_base, T)
    assert abs(root) < 5e-3 and abs(base) < 5e-3, (root, base)


def test_few_noisy_keypoints_place_the_robot_worse_without_the_silhouette(panda, scene):
    """Four DREAM keypoints with 2 px noise (8 draws), true joints, a start 5 % too far: their depth errors are
    several times those of the same keypoints with the silhouette."""
    _, _, fitter = panda
    T, mask = scene
    sil = fitter.silhouette(mask)
    M = fitter.tree.n_points
    exact = project(transform_points(fitter.tree.points(Q[None]), T[None, :3, :3], T[None, :3, 3]), K, 0.05)[0]
    weights = np.zeros(M)
    weights[FEW] = 1.0
    rng = np.random.default_rng(3)
    errors = {False: [], True: []}
    for _ in range(8):
        uv = exact + rng.normal(0.0, 2.0, exact.shape)
        for with_silhouette in (False, True):
            result = fitter.fit(uv, weights, K, Q[None], _start(T, 1.05)[None], known_joints=Q,
                                silhouette=sil if with_silhouette else None)
            errors[with_silhouette].append(abs(_depth_errors(fitter, result.T_cam_base, T)[0]))
    assert np.mean(errors[True]) < 5e-3
    assert np.mean(errors[True]) < 0.5 * np.mean(errors[False]), errors


def test_fit_without_a_silhouette_is_unchanged(panda, scene):
    """A Fitter built with meshes fits keypoints exactly as one without; the silhouette needs the meshes."""
    model, _, fitter = panda
    T, mask = scene
    plain = Fitter(model)
    rng = np.random.default_rng(4)
    M = fitter.tree.n_points
    uv = project(transform_points(fitter.tree.points(Q[None]), T[None, :3, :3], T[None, :3, 3]), K, 0.05)[0]
    uv = uv + rng.normal(0.0, 1.0, uv.shape)
    q0 = np.clip(Q + rng.normal(0.0, 0.2, Q.shape), fitter.lower, fitter.upper)
    a = fitter.fit(uv, np.ones(M), K, q0[None], _start(T, 1.05)[None])
    b = plain.fit(uv, np.ones(M), K, q0[None], _start(T, 1.05)[None])
    assert np.array_equal(a.q, b.q) and np.array_equal(a.T_cam_base, b.T_cam_base) and a.cost == b.cost
    assert a.silhouette_cost is None
    with pytest.raises(ValueError, match="meshes"):
        plain.fit(uv, np.ones(M), K, q0[None], _start(T, 1.05)[None], silhouette=fitter.silhouette(mask))


def test_full_fit_with_silhouette_and_keypoints(panda, scene):
    """Joints and pose from a start 0.15 rad off per joint, 5 % off in depth, with noisy keypoints (all fit points,
    2 px) and the silhouette: the depth within 1 % and no worse than the keypoints alone; the cost with the
    silhouette matches Fitter.cost."""
    _, _, fitter = panda
    T, mask = scene
    sil = fitter.silhouette(mask)
    rng = np.random.default_rng(5)
    M = fitter.tree.n_points
    uv = project(transform_points(fitter.tree.points(Q[None]), T[None, :3, :3], T[None, :3, 3]), K, 0.05)[0]
    uv = uv + rng.normal(0.0, 2.0, uv.shape)
    q0 = np.clip(Q + rng.choice([-0.15, 0.15], Q.shape) * np.r_[np.ones(7), 0.0], fitter.lower, fitter.upper)
    starts = (np.stack([q0, q0]), np.stack([_start(T, 1.05), _start(T, 0.95)]))
    with_sil = fitter.fit(uv, np.ones(M), K, *starts, silhouette=sil)
    without = fitter.fit(uv, np.ones(M), K, *starts)
    root_with = abs(_depth_errors(fitter, with_sil.T_cam_base, T, with_sil.q)[0])
    root_without = abs(_depth_errors(fitter, without.T_cam_base, T, without.q)[0])
    assert root_with < 1e-2 and root_with <= root_without + 1e-3, (root_with, root_without)
    np.testing.assert_allclose(fitter.cost(uv, np.ones(M), K, with_sil.q[None], with_sil.T_cam_base[None], sil),
                               [with_sil.cost], rtol=1e-9)
