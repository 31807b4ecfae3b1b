"""msg_adapters on real message types (rclpy's sensor_msgs, and rosbags' for the duck typing): every encoding
with row padding, every rejection with its reason, CameraInfo K and P, and Estimate -> messages."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header
from visualization_msgs.msg import Marker

from holo_pose_ros.estimator import Estimate
from msg_adapters import (DEFAULT_MAX_PIXELS, CameraInfoError, ImageConversionError, camera_info_to_K,
                          check_image_size, image_to_rgb, joint_positions, keypoints_2d_from_msg, pose_array_points,
                          pose_to_matrix, rgb_to_image, to_joint_state, to_keypoints_2d, to_keypoints_3d, to_markers,
                          to_pose_stamped, to_transform_stamped)

ROOT = Path(__file__).resolve().parent.parent
HEADER = Header(stamp=Time(sec=1712, nanosec=345678901), frame_id="camera_color_optical_frame")
RGB = np.random.default_rng(0).integers(0, 256, (5, 7, 3), dtype=np.uint8)
ALPHA = np.full((5, 7, 1), 77, np.uint8)
# encoding -> (pixels as the camera sends them, the RGB image they mean)
SENT = {
    "rgb8": (RGB, RGB),
    "bgr8": (RGB[..., ::-1], RGB),
    "rgba8": (np.concatenate([RGB, ALPHA], 2), RGB),
    "bgra8": (np.concatenate([RGB[..., ::-1], ALPHA], 2), RGB),
    "mono8": (RGB[..., :1], np.repeat(RGB[..., :1], 3, axis=2)),
}


def image_msg(pixels: np.ndarray, encoding: str, pad: int = 0) -> Image:
    """A real sensor_msgs/Image of (H, W, C) `pixels`, each row followed by `pad` junk bytes."""
    h, w, c = pixels.shape
    rows = np.concatenate([pixels.reshape(h, w * c), np.full((h, pad), 0xAB, np.uint8)], axis=1)
    msg = Image(header=HEADER, height=h, width=w, encoding=encoding, is_bigendian=0, step=w * c + pad)
    msg.data = rows.tobytes()
    return msg


@pytest.mark.parametrize("pad", [0, 5])
@pytest.mark.parametrize("encoding", list(SENT))
def test_every_encoding_decodes_to_rgb_with_and_without_row_padding(encoding, pad):
    pixels, expected = SENT[encoding]
    out = image_to_rgb(image_msg(pixels, encoding, pad))
    assert out.dtype == np.uint8 and out.shape == (5, 7, 3)
    np.testing.assert_array_equal(out, expected)


def test_rgb8_is_a_read_only_view_of_the_message_bytes():
    msg = image_msg(RGB, "rgb8")
    out = image_to_rgb(msg)
    assert np.shares_memory(out, np.frombuffer(msg.data, np.uint8)) and not out.flags.writeable


def test_rosbags_messages_work_too():
    store = get_typestore(Stores.ROS2_JAZZY)
    types = store.types
    header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=1, nanosec=2), frame_id="c")
    bgr = np.concatenate([RGB[..., ::-1].reshape(5, 21), np.zeros((5, 3), np.uint8)], axis=1)
    msg = types["sensor_msgs/msg/Image"](header=header, height=5, width=7, encoding="bgr8", is_bigendian=0, step=24,
                                         data=bgr.ravel())
    np.testing.assert_array_equal(image_to_rgb(msg), RGB)


@pytest.mark.parametrize("image", [RGB, RGB[..., 0], RGB[:, ::2]])  # colour, grey, a non-contiguous view
def test_array_to_image_round_trip(image):
    msg = rgb_to_image(image, HEADER)
    assert msg.encoding == ("rgb8" if image.ndim == 3 else "mono8") and msg.is_bigendian == 0
    assert msg.step == image.shape[1] * (3 if image.ndim == 3 else 1) and len(msg.data) == msg.step * msg.height
    assert msg.header == HEADER and msg.header is not HEADER
    back = image_to_rgb(msg)
    np.testing.assert_array_equal(back, image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2))


@pytest.mark.parametrize("bad", [RGB.astype(np.float32), np.zeros((5, 7, 4), np.uint8), np.zeros(5, np.uint8)])
def test_array_to_image_rejects_what_it_cannot_encode(bad):
    with pytest.raises(ValueError, match="uint8"):
        rgb_to_image(bad)


def _edited(msg: Image, **fields) -> Image:
    for name, value in fields.items():
        setattr(msg, name, value)
    return msg


@pytest.mark.parametrize("msg, reason", [
    (_edited(image_msg(RGB, "rgb8"), encoding="yuv422"), "unsupported image encoding 'yuv422'"),
    (_edited(image_msg(RGB, "rgb8"), encoding="16UC1"), "supported: rgb8, bgr8, rgba8, bgra8, mono8"),
    (_edited(image_msg(RGB, "rgb8"), step=20), "step 20 bytes is shorter than a rgb8 row: width 7 x 3 bytes = 21"),
    (_edited(image_msg(RGB, "rgb8", pad=3), step=21), "data is 120 bytes; step 21 x height 5 needs 105"),
    (_edited(image_msg(RGB, "rgb8"), data=bytes(100)), "data is 100 bytes; step 21 x height 5 needs 105"),
    (_edited(image_msg(RGB, "rgb8"), height=0), "empty image: 7 x 0 px"),
    (Image(encoding="rgb8"), "empty image: 0 x 0 px"),
    (_edited(image_msg(RGB, "rgb8"), is_bigendian=2), "is_bigendian must be 0 or 1, got 2"),
])
def test_bad_images_are_rejected_with_the_reason(msg, reason):
    with pytest.raises(ImageConversionError, match=reason.replace("(", r"\(")):
        image_to_rgb(msg)


def test_huge_images_are_rejected_before_their_data_is_touched():
    side = 4097
    huge = image_msg(np.zeros((side, side, 1), np.uint8), "mono8")
    assert side * side > DEFAULT_MAX_PIXELS
    with pytest.raises(ImageConversionError, match=f"image 4097 x 4097 = {side * side} px exceeds the limit"):
        image_to_rgb(huge)
    with pytest.raises(ImageConversionError, match="exceeds the limit of 34 px"):
        image_to_rgb(image_msg(RGB, "rgb8"), max_pixels=34)
    assert issubclass(ImageConversionError, ValueError)


def camera_info(**fields) -> CameraInfo:
    msg = CameraInfo(header=HEADER, width=640, height=480)
    msg.k = [600.0, 0.0, 320.0, 0.0, 610.0, 240.0, 0.0, 0.0, 1.0]
    msg.p = [590.0, 0.0, 318.0, 0.0, 0.0, 595.0, 236.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    return _edited(msg, **fields)


def test_camera_info_gives_K_from_k_or_from_p():
    np.testing.assert_array_equal(camera_info_to_K(camera_info()), [[600, 0, 320], [0, 610, 240], [0, 0, 1]])
    np.testing.assert_array_equal(camera_info_to_K(camera_info(), use_rectified_p=True),
                                  [[590, 0, 318], [0, 595, 236], [0, 0, 1]])
    assert camera_info_to_K(camera_info()).dtype == np.float64


@pytest.mark.parametrize("fields, rectified, reason", [
    (dict(k=[0.0] * 9), False, r"CameraInfo.k is all zeros \(is the camera calibrated\?\)"),
    (dict(p=[0.0] * 12), True, "CameraInfo.p is all zeros"),
    (dict(k=[float("nan")] * 9), False, "CameraInfo.k is not finite"),
    (dict(p=[590.0, 0, 318, 0, 0, float("inf"), 236, 0, 0, 0, 1, 0]), True, "CameraInfo.p is not finite"),
    (dict(k=[600.0, 0, 320, 0, -610, 240, 0, 0, 1]), False, "fy = -610.0; both must be > 0"),
    (dict(k=[0.0, 0, 320, 0, 610, 240, 0, 0, 1]), False, "fx = 0.0"),
    (dict(k=[600.0, 0, 320, 0, 610, 240, 0, 0, 0]), False, r"last row \[0.0, 0.0, 0.0\], expected \[0, 0, 1\]"),
])
def test_bad_camera_info_is_rejected_with_the_reason(fields, rectified, reason):
    with pytest.raises(CameraInfoError, match=reason):
        camera_info_to_K(camera_info(**fields), use_rectified_p=rectified)


def test_camera_info_size_must_match_the_image_when_stated():
    check_image_size(camera_info(), 640, 480)
    check_image_size(camera_info(width=0, height=0), 320, 240)  # size not stated
    with pytest.raises(CameraInfoError, match="CameraInfo is for 640 x 480 px but the image is 320 x 240 px"):
        check_image_size(camera_info(), 320, 240)


@pytest.fixture
def estimate() -> Estimate:
    rng = np.random.default_rng(3)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -2.9, 0.4]).as_matrix()  # near a half turn: not the trace branch
    T[:3, 3] = [0.1, -0.2, 1.5]
    return Estimate(True, 0.9, [f"j{i}" for i in range(3)], [f"k{i}" for i in range(4)],
                    joints=np.array([0.5, -1.0, 0.02]), T_cam_base=T, keypoints_3d=rng.normal(size=(4, 3)) + [0, 0, 2],
                    keypoints_2d=rng.uniform(0, 640, (4, 2)), keypoint_confidence=np.array([0.1, 0.5, 0.9, 1.0]))


def test_joint_state_pose_and_transform_carry_the_header_and_the_numbers(estimate):
    joints = to_joint_state(estimate, HEADER)
    assert joints.header == HEADER and joints.name == ["j0", "j1", "j2"]
    np.testing.assert_array_equal(joints.position, estimate.joints)
    assert len(joints.velocity) == len(joints.effort) == 0

    pose = to_pose_stamped(estimate, HEADER)
    p, o = pose.pose.position, pose.pose.orientation
    assert pose.header == HEADER
    np.testing.assert_allclose([p.x, p.y, p.z], estimate.T_cam_base[:3, 3])
    q = np.array([o.x, o.y, o.z, o.w])
    assert np.isclose(np.linalg.norm(q), 1.0) and q[3] >= 0
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), estimate.T_cam_base[:3, :3], atol=1e-12)

    tf = to_transform_stamped(estimate, HEADER, "estimated/panda_link0")
    t, r = tf.transform.translation, tf.transform.rotation
    assert tf.header == HEADER and tf.child_frame_id == "estimated/panda_link0"
    np.testing.assert_allclose([t.x, t.y, t.z], estimate.T_cam_base[:3, 3])
    np.testing.assert_allclose([r.x, r.y, r.z, r.w], q)


def test_keypoint_messages(estimate):
    array = to_keypoints_3d(estimate, HEADER)
    assert array.header == HEADER and len(array.poses) == 4
    np.testing.assert_allclose([[p.position.x, p.position.y, p.position.z] for p in array.poses], estimate.keypoints_3d)
    assert all((p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w) == (0, 0, 0, 1) for p in array.poses)

    cloud = to_keypoints_2d(estimate, HEADER)
    assert cloud.header == HEADER and [f.name for f in cloud.fields] == ["u", "v", "confidence"]
    assert (cloud.height, cloud.width, cloud.point_step, cloud.is_dense) == (1, 4, 12, True)
    expected = np.hstack([estimate.keypoints_2d, estimate.keypoint_confidence[:, None]]).astype(np.float32)
    np.testing.assert_array_equal(keypoints_2d_from_msg(cloud), expected)


def test_markers_draw_the_skeleton_in_the_camera_frame(estimate):
    parents = [-1, 0, 1, 1]
    markers = to_markers(estimate, HEADER, parents).markers
    lines, spheres = markers
    assert all(m.header == HEADER for m in markers) and [m.id for m in markers] == [0, 1]
    assert (lines.type, spheres.type) == (Marker.LINE_LIST, Marker.SPHERE_LIST)
    assert all((m.lifetime.sec, m.lifetime.nanosec) == (0, 500_000_000) for m in markers)
    xyz = lambda points: np.array([[p.x, p.y, p.z] for p in points])  # noqa: E731
    kp = estimate.keypoints_3d
    np.testing.assert_allclose(xyz(lines.points), np.stack([kp[0], kp[1], kp[1], kp[2], kp[1], kp[3]]))
    np.testing.assert_allclose(xyz(spheres.points), kp)
    np.testing.assert_allclose([c.g for c in spheres.colors], estimate.keypoint_confidence, atol=1e-6)


def test_an_estimate_without_a_robot_converts_to_nothing(estimate):
    lost = Estimate(False, 0.1, estimate.joint_names, estimate.keypoint_names)
    for convert in (to_joint_state, to_pose_stamped, to_keypoints_3d, to_keypoints_2d):
        with pytest.raises(ValueError, match="robot not found"):
            convert(lost, HEADER)


def test_pose_and_keypoint_readers_invert_the_converters(estimate):
    T = pose_to_matrix(to_pose_stamped(estimate, HEADER).pose)
    np.testing.assert_allclose(T, estimate.T_cam_base, atol=1e-12)
    np.testing.assert_allclose(pose_array_points(to_keypoints_3d(estimate, HEADER)), estimate.keypoints_3d, atol=1e-12)
    names = list(reversed(estimate.joint_names))
    np.testing.assert_allclose(joint_positions(to_joint_state(estimate, HEADER), names), estimate.joints[::-1])
    assert joint_positions(to_joint_state(estimate, HEADER), names + ["missing"]) is None


def test_msg_adapters_import_neither_torch_nor_the_estimator():
    # numpy and yaml only: the joint-state name matching of holo_pose_ros.monitoring and the robot YAML readers
    allowed = ("('holo_pose_ros', 'holo_pose_ros.geometry', 'holo_pose_ros.geometry.alignment', 'holo_pose_ros.resources', "
               "'holo_pose_ros.robots', 'holo_pose_ros.robots.spec', 'holo_pose_ros.robots.description')")
    code = ("import sys, msg_adapters; bad = [m for m in sys.modules if m.split('.')[0] in ('torch', 'cv2') or "
            f"(m.startswith('holo_pose_ros') and m not in {allowed} and not m.startswith('holo_pose_ros.monitoring'))];"
            "print(bad); sys.exit(bool(bad))")
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr
