"""Camera, crop and rotation geometry against independent constructions."""

import numpy as np
import torch

from holo_pose_ros.geometry.camera import look_at, project
from holo_pose_ros.geometry.crop import (box_from_points, crop_affine, crop_image, crop_intrinsics, full_image_box,
                                         grid_to_frame_mask)
from holo_pose_ros.geometry.rotation import geodesic_angle, matrix_to_rot6d, rot6d_to_matrix


def random_rotations(n: int, seed: int = 0) -> torch.Tensor:
    q, _ = torch.linalg.qr(torch.randn(n, 3, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64))
    return q * torch.linalg.det(q)[:, None, None]


def test_rot6d_round_trip_and_orthonormal_decoding():
    R = random_rotations(64)
    assert torch.allclose(rot6d_to_matrix(matrix_to_rot6d(R)), R, atol=1e-12)
    noisy = rot6d_to_matrix(matrix_to_rot6d(R) + 0.1 * torch.randn(64, 6, dtype=torch.float64))
    eye = torch.eye(3, dtype=torch.float64).expand(64, 3, 3)
    assert torch.allclose(noisy.transpose(1, 2) @ noisy, eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(noisy), torch.ones(64, dtype=torch.float64))


def test_geodesic_angle_of_a_known_rotation():
    a = np.radians(30.0)
    Rz = torch.tensor([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]], dtype=torch.float64)
    R = random_rotations(8)
    assert torch.allclose(geodesic_angle(R, R @ Rz), torch.full((8,), a, dtype=torch.float64), atol=1e-6)


def test_projection_and_look_at():
    K = np.array([[600.0, 0, 300.0], [0, 610.0, 250.0], [0, 0, 1]])
    assert np.allclose(project(np.array([[0.1, -0.2, 2.0]]), K), [[330.0, 189.0]])
    T = look_at(np.array([2.0, 0.5, 1.0]), np.array([0.0, 0.0, 0.5]))
    target_cam = np.linalg.inv(T) @ np.array([0.0, 0.0, 0.5, 1.0])
    assert np.allclose(target_cam[:2], 0, atol=1e-12) and target_cam[2] > 0
    up_cam = np.linalg.inv(T)[:3, :3] @ np.array([0, 0, 1.0])
    assert up_cam[1] < 0  # world up is image up (y down)


def test_crop_intrinsics_agree_with_the_crop_of_the_image():
    K = np.array([[500.0, 0, 320.0], [0, 500.0, 240.0], [0, 0, 1]])
    points = np.array([[0.1, 0.05, 1.5], [-0.2, 0.1, 2.0], [0.0, -0.15, 1.0]])
    for box in (np.array([100.0, 60.0, 300.0]), np.array([-50.0, -80.0, 700.0]), full_image_box(640, 480)):
        for size in (192, 256):
            uv = project(points, K)
            expected = uv @ crop_affine(box, size)[:2, :2].T + crop_affine(box, size)[:2, 2]
            assert np.allclose(project(points, crop_intrinsics(K, box, size)), expected)
            image = np.zeros((480, 640, 3), np.uint8)
            u, v = np.round(uv[0]).astype(int)
            image[v - 3:v + 4, u - 3:u + 4] = 255   # a 7x7 white square centred on a pixel
            crop = crop_image(image, box, size).astype(float)[..., 0]
            ys, xs = np.nonzero(crop > 0)
            centroid = np.array([(xs * crop[ys, xs]).sum(), (ys * crop[ys, xs]).sum()]) / crop[ys, xs].sum()
            target = np.array([u, v]) @ crop_affine(box, size)[:2, :2].T + crop_affine(box, size)[:2, 2]
            assert np.abs(centroid - target).max() < 0.35, (box, size, centroid, target)


def test_box_from_points_and_letterbox():
    box = box_from_points(np.array([[100.0, 200.0], [300.0, 260.0]]), margin=0.25)
    assert np.isclose(box[2], 200.0 * 1.5)
    assert np.allclose(box[:2] + box[2] / 2, [200.5, 230.5])  # centre, in edge coordinates
    assert np.allclose(full_image_box(640, 480), [0.0, -80.0, 640.0])


def test_a_crop_grid_mask_lands_on_its_frame_pixels():
    """One positive cell of a 56 x 56 grid over a 224 px crop of the box (100, 50, side 448): 8 x 8 frame pixels
    centred where the cell's centre maps (crop pixel (j + 0.5) * 4 - 0.5, then back through the crop affine)."""
    logits = np.full((56, 56), -5.0)
    logits[10, 20] = 5.0
    box = np.array([100.0, 50.0, 448.0])
    mask = grid_to_frame_mask(logits, box, 224, 640, 480)
    rows, cols = np.nonzero(mask)
    centre = np.linalg.inv(crop_affine(box, 224)) @ np.array([(20 + 0.5) * 4 - 0.5, (10 + 0.5) * 4 - 0.5, 1.0])
    assert abs(cols.mean() - centre[0]) < 0.5 and abs(rows.mean() - centre[1]) < 0.5
    assert 40 <= mask.sum() <= 90                        # about one cell: (4 crop px * 2 frame px per crop px)^2
    assert not grid_to_frame_mask(np.full((56, 56), -5.0), box, 224, 640, 480).any()
