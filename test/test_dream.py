"""DREAM folder reader/writer and rigid alignment: real files in tmp_path, real URDF forward kinematics."""

from __future__ import annotations

import json
import logging
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from holo_pose_ros.data.dream import DreamFormatError, DreamReader, DreamWriter
from holo_pose_ros.geometry.alignment import (
    UE_TO_OPENCV,
    matrix_to_quaternion_xyzw,
    quaternion_xyzw_to_matrix,
    rigid_align,
)
from holo_pose_ros.robots.kinematics import RobotModel

W, H = 64, 48
K = np.array([[110.0, 0.0, 31.5], [0.0, 112.0, 23.5], [0.0, 0.0, 1.0]])
LOGGER = "holo_pose_ros.data.dream"


@pytest.fixture(scope="module")
def models() -> dict[str, RobotModel]:
    return {name: RobotModel(name, dtype=torch.float64) for name in ("panda", "kuka", "baxter")}


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A random proper rotation from the QR decomposition of a Gaussian matrix."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def camera_pose(model: RobotModel, joints: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A random T_cam<-base putting the robot's keypoint centroid 2-3 m ahead, off-centre by up to 0.6 m."""
    T = np.eye(4)
    T[:3, :3] = random_rotation(rng)
    centroid = model.keypoints(torch.from_numpy(joints)).numpy()[0].mean(axis=0)
    target = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.4, 0.4), rng.uniform(2.0, 3.0)])
    T[:3, 3] = target - T[:3, :3] @ centroid
    return T


def random_image(rng: np.random.Generator) -> np.ndarray:
    """An (H, W, 3) uint8 image of random 16-pixel colour blocks (JPEG keeps it close; channel swaps show)."""
    blocks = rng.integers(0, 256, size=(H // 16, W // 16, 3), dtype=np.uint8)
    return np.repeat(np.repeat(blocks, 16, axis=0), 16, axis=1)


def write_folder(folder: Path, model: RobotModel, n: int, seed: int, units: str = "m", image_ext: str = "jpg",
                 with_mask: bool = False) -> list[dict]:
    """n random frames written with DreamWriter; returns what was written (joints, pose, image, mask)."""
    rng = np.random.default_rng(seed)
    writer = DreamWriter(folder, model, K, W, H, units=units, image_ext=image_ext)
    truth = []
    for i in range(n):
        joints = model.sample_uniform(1, torch.Generator().manual_seed(seed * 100 + i))[0].numpy()
        T = camera_pose(model, joints, rng)
        rgb = random_image(rng)
        mask = rng.integers(0, 256, size=(H, W), dtype=np.uint8) if with_mask else None
        writer.write(i, rgb, joints, T, mask=mask)
        truth.append({"joints": joints, "T": T, "rgb": rgb, "mask": mask})
    return truth


def edit_json(path: Path, change) -> None:
    """Rewrite a frame JSON after change(data) edited it in place."""
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


# -- geometry -----------------------------------------------------------------------------------------------------

def test_rigid_align_recovers_a_random_pose_exactly():
    rng = np.random.default_rng(1)
    R, t = random_rotation(rng), rng.normal(size=3)
    src = rng.normal(size=(12, 3))
    T, residual = rigid_align(src, src @ R.T + t)
    assert residual < 1e-9
    assert np.allclose(T[:3, :3], R, atol=1e-12) and np.allclose(T[:3, 3], t, atol=1e-12)
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)


def test_rigid_align_gives_a_proper_rotation_for_mirrored_points_and_honours_weights():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(8, 3))
    T, residual = rigid_align(src, src * [1, 1, -1])
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0) and residual > 0.1
    dst = src + 0.5
    dst[0] += 10.0  # an outlier with zero weight must not move the fit
    weights = np.ones(8)
    weights[0] = 0.0
    T, residual = rigid_align(src, dst, weights)
    assert residual < 1e-9 and np.allclose(T[:3, 3], 0.5)


def test_quaternion_conversions_match_scipy_and_round_trip():
    rng = np.random.default_rng(3)
    for _ in range(20):
        R = random_rotation(rng)
        q = matrix_to_quaternion_xyzw(R)
        ref = Rotation.from_matrix(R).as_quat()  # scipy: [x, y, z, w]
        assert np.allclose(q, ref * np.sign(ref[3]), atol=1e-12) and q[3] >= 0
        assert np.allclose(quaternion_xyzw_to_matrix(q), R, atol=1e-12)
        assert np.allclose(quaternion_xyzw_to_matrix(3.0 * q), R, atol=1e-12)  # normalises
    assert np.allclose(quaternion_xyzw_to_matrix([0, 0, 0, 1]), np.eye(3))
    assert np.allclose(matrix_to_quaternion_xyzw(np.diag([1.0, -1.0, -1.0])), [1, 0, 0, 0])
    noisy = random_rotation(rng) + 1e-4 * rng.normal(size=(3, 3))
    assert np.isclose(np.linalg.norm(matrix_to_quaternion_xyzw(noisy)), 1.0)
    assert np.isclose(np.linalg.det(UE_TO_OPENCV), 1.0) and np.allclose(UE_TO_OPENCV @ UE_TO_OPENCV.T, np.eye(3))


# -- round trip ---------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("robot,image_ext", [("panda", "png"), ("kuka", "jpg"), ("baxter", "jpg")])
def test_write_read_round_trip(tmp_path, models, robot, image_ext):
    model = models[robot]
    truth = write_folder(tmp_path / robot, model, 4, seed=10, image_ext=image_ext, with_mask=robot == "panda")
    reader = DreamReader(tmp_path / robot, robot)
    assert len(reader) == 4 and reader.units == "m" and reader.scale == 1.0 and not reader.problems
    flags_seen = set()
    for frame, t in zip(reader, truth):
        assert frame.keypoint_names == tuple(model.keypoint_names)
        assert (frame.width, frame.height) == (W, H) and np.array_equal(frame.K, K)
        np.testing.assert_allclose(frame.joints, t["joints"], atol=1e-12)
        expected = model.keypoints(torch.from_numpy(t["joints"])).numpy()[0] @ t["T"][:3, :3].T + t["T"][:3, 3]
        np.testing.assert_allclose(frame.keypoints_3d, expected, atol=1e-6)
        u = K[0, 0] * expected[:, 0] / expected[:, 2] + K[0, 2]
        v = K[1, 1] * expected[:, 1] / expected[:, 2] + K[1, 2]
        np.testing.assert_allclose(frame.keypoints_2d, np.stack([u, v], axis=1), atol=0.01)
        np.testing.assert_array_equal(frame.in_image, (u >= 0) & (u <= W) & (v >= 0) & (v <= H))
        flags_seen.update(frame.in_image.tolist())
        np.testing.assert_allclose(frame.T_cam_base, t["T"], atol=1e-6)
        assert frame.base_pose_source == "quaternion" and frame.alignment_residual_m < 1e-6
        rgb = reader.load_image(frame)
        assert rgb.shape == (H, W, 3) and rgb.dtype == np.uint8
        if image_ext == "png":
            np.testing.assert_array_equal(rgb, t["rgb"])
        else:
            assert np.abs(rgb.astype(float) - t["rgb"]).mean() < 8  # lossy, but the RGB order is kept
        if t["mask"] is None:
            assert frame.mask_path is None and reader.load_mask(frame) is None
        else:
            np.testing.assert_array_equal(reader.load_mask(frame), t["mask"])
    assert frame.name == "000003" and frame.image_path.name == f"000003.rgb.{image_ext}"
    assert flags_seen == {True, False}, "the random cameras should leave some keypoints out of the image"


def test_written_files_follow_the_ndds_layout(tmp_path, models):
    write_folder(tmp_path, models["kuka"], 1, seed=4)
    writer = DreamWriter(tmp_path, models["kuka"], K, W, H)
    joints, T = models["kuka"].neutral.numpy(), np.eye(4)
    T[2, 3] = 2.0
    extra = {"camera_data": {"note": "from a test"}}
    assert json.loads(writer.write(1, random_image(np.random.default_rng(0)), joints, T, extra=extra).read_text())[
        "camera_data"] == extra["camera_data"]
    with pytest.raises(ValueError, match="objects"):
        writer.write(2, random_image(np.random.default_rng(0)), joints, T, extra={"objects": []})
    T[2, 3] = -2.0
    with pytest.raises(ValueError, match="z > 0"):
        writer.write(2, random_image(np.random.default_rng(0)), joints, T)
    camera = json.loads((tmp_path / "_camera_settings.json").read_text())["camera_settings"][0]
    assert camera["intrinsic_settings"]["fx"] == K[0, 0] and camera["captured_image_size"] == {"width": W, "height": H}
    assert json.loads((tmp_path / "_object_settings.json").read_text())["exported_object_classes"] == ["kuka"]
    obj = json.loads((tmp_path / "000000.json").read_text())["objects"][0]
    assert obj["class"] == "kuka" and obj["keypoints"][0]["name"] == "iiwa7_link_0"
    np.testing.assert_allclose(obj["keypoints"][0]["location"], obj["location"], atol=1e-9)  # base keypoint
    assert [j["name"] for j in json.loads((tmp_path / "000000.json").read_text())["sim_state"]["joints"]] == \
        models["kuka"].joint_names


# -- units ----------------------------------------------------------------------------------------------------

def test_units_are_detected_from_the_data_and_can_be_overridden(tmp_path, models):
    truth = write_folder(tmp_path / "synthetic_but_metres", models["panda"], 3, seed=5, units="m")
    write_folder(tmp_path / "real_but_cm", models["panda"], 3, seed=5, units="cm")
    metres = DreamReader(tmp_path / "synthetic_but_metres", models["panda"])
    cm = DreamReader(tmp_path / "real_but_cm", "panda")
    assert metres.units == "m" and cm.units == "cm" and cm.scale == 0.01
    for a, b, t in zip(metres, cm, truth):
        np.testing.assert_allclose(b.keypoints_3d, a.keypoints_3d, atol=1e-9)
        np.testing.assert_allclose(b.keypoints_2d, a.keypoints_2d, atol=1e-9)  # pixels are never scaled
        np.testing.assert_allclose(b.T_cam_base, t["T"], atol=1e-6)
    forced = DreamReader(tmp_path / "real_but_cm", "panda", units="m")
    assert forced.units == "m" and forced.scale == 1.0
    np.testing.assert_allclose(forced[0].keypoints_3d, 100 * cm[0].keypoints_3d, atol=1e-7)
    with pytest.raises(ValueError, match="units"):
        DreamReader(tmp_path / "real_but_cm", "panda", units="mm")


def test_units_fall_back_to_depth_when_joints_are_missing(tmp_path, models):
    for units in ("m", "cm"):
        folder = tmp_path / units
        write_folder(folder, models["panda"], 2, seed=6, units=units)
        for path in folder.glob("0*.json"):
            edit_json(path, lambda d: d.pop("sim_state"))
        reader = DreamReader(folder, "panda")
        assert reader.units == units and reader[0].joints is None
        assert reader[0].base_pose_source == "quaternion" and np.isnan(reader[0].alignment_residual_m)


# -- base pose ----------------------------------------------------------------------------------------------------

def test_base_pose_from_alignment_when_the_quaternion_is_absent(tmp_path, models):
    truth = write_folder(tmp_path, models["baxter"], 3, seed=7, units="cm")
    for path in tmp_path.glob("0*.json"):
        edit_json(path, lambda d: d["objects"][0].pop("quaternion_xyzw"))
    reader = DreamReader(tmp_path, "baxter")
    for frame, t in zip(reader, truth):
        assert frame.base_pose_source == "alignment" and frame.alignment_residual_m < 1e-6
        np.testing.assert_allclose(frame.T_cam_base, t["T"], atol=1e-6)


def test_a_wrong_quaternion_gives_way_to_the_alignment_with_one_warning(tmp_path, models, caplog):
    truth = write_folder(tmp_path, models["panda"], 3, seed=8)
    for path in tmp_path.glob("0*.json"):
        edit_json(path, lambda d: d["objects"][0].update(quaternion_xyzw=[0.0, 0.0, 0.0, 1.0]))
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        reader = DreamReader(tmp_path, "panda")
    assert [r.name for r in caplog.records] == [LOGGER] and "quaternion" in caplog.records[0].getMessage()
    for frame, t in zip(reader, truth):
        assert frame.base_pose_source == "alignment" and frame.alignment_residual_m < 1e-6
        np.testing.assert_allclose(frame.T_cam_base, t["T"], atol=1e-6)


# -- malformed data -----------------------------------------------------------------------------------------------

def add_bad_frame(folder: Path, index: int, change=None, raw_text: str | None = None, image: bool = True) -> str:
    """Copy frame 000000 to `index`, then edit its JSON (change), replace its text (raw_text) or drop its image."""
    name = f"{index:06d}"
    if image:
        shutil.copy(folder / "000000.rgb.jpg", folder / f"{name}.rgb.jpg")
    shutil.copy(folder / "000000.json", folder / f"{name}.json")
    if change is not None:
        edit_json(folder / f"{name}.json", change)
    if raw_text is not None:
        (folder / f"{name}.json").write_text(raw_text)
    return f"{name}.json"


def test_malformed_frames_are_reported_once_and_skipped(tmp_path, models, caplog):
    write_folder(tmp_path, models["panda"], 5, seed=9)
    expected = {
        add_bad_frame(tmp_path, 10, lambda d: d["objects"][0].pop("keypoints")): "objects[0].keypoints",
        add_bad_frame(tmp_path, 11, lambda d: d["objects"][0]["keypoints"].pop(3)): "objects[0].keypoints",
        add_bad_frame(tmp_path, 12, lambda d: d["objects"][0]["keypoints"][2]["location"].pop()):
            "objects[0].keypoints[2].location",
        add_bad_frame(tmp_path, 13, lambda d: d["objects"][0]["keypoints"][1].update(location=[0.1, float("nan"), 1.0])):
            "objects[0].keypoints[1].location",
        add_bad_frame(tmp_path, 14, raw_text='{"objects": [ {"class": "panda", '): "<json>",
        add_bad_frame(tmp_path, 15, image=False): "image",
        add_bad_frame(tmp_path, 16, lambda d: d["sim_state"]["joints"][0].update(position="x")):
            "sim_state.joints[0].position",
    }
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        reader = DreamReader(tmp_path, "panda")
        frames = list(reader) + list(reader)  # iterating again must not report again
    assert len(reader) == 5 and [f.name for f in frames[:5]] == [f"{i:06d}" for i in range(5)]
    assert {Path(file).name: field for file, field, _ in reader.problems} == expected
    assert len(reader.problems) == len(expected) == len(caplog.records)
    for file_name, field in expected.items():
        assert sum(file_name in r.getMessage() and f"'{field}'" in r.getMessage() for r in caplog.records) == 1
    assert "missing keypoint 'panda_link4'" in dict((Path(f).name, m) for f, _, m in reader.problems)["000011.json"]


def test_unreadable_images_are_caught_up_front_or_on_load(tmp_path, models):
    write_folder(tmp_path, models["kuka"], 3, seed=11)
    (tmp_path / "000001.rgb.jpg").write_bytes(b"not a jpeg")
    lenient = DreamReader(tmp_path, "kuka")
    assert len(lenient) == 3
    with pytest.raises(DreamFormatError, match=re.escape(str(tmp_path / "000001.rgb.jpg"))):
        lenient.load_image(lenient[1])
    strict = DreamReader(tmp_path, "kuka", check_images=True)
    assert [f.name for f in strict] == ["000000", "000002"]
    assert [(Path(f).name, field) for f, field, _ in strict.problems] == [("000001.json", "image")]


def test_unusable_folders_raise_one_error_naming_the_path(tmp_path, models):
    missing = tmp_path / "nope"
    with pytest.raises(DreamFormatError, match=re.escape(str(missing))):
        DreamReader(missing, "panda")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DreamFormatError, match=re.escape(str(empty))):
        DreamReader(empty, "panda")
    no_camera = tmp_path / "no_camera"
    write_folder(no_camera, models["panda"], 1, seed=12)
    (no_camera / "_camera_settings.json").unlink()
    with pytest.raises(DreamFormatError, match=re.escape(str(no_camera)) + ".*_camera_settings.json"):
        DreamReader(no_camera, "panda")
    wrong_robot = tmp_path / "wrong_robot"
    write_folder(wrong_robot, models["panda"], 1, seed=12)
    with pytest.raises(DreamFormatError, match="no valid frames.*missing keypoint 'iiwa7_link_0'"):
        DreamReader(wrong_robot, "kuka")
    assert issubclass(DreamFormatError, ValueError)


def test_a_doubled_folder_is_accepted(tmp_path, models):
    write_folder(tmp_path / "panda-3cam_azure" / "panda-3cam_azure", models["panda"], 2, seed=13)
    reader = DreamReader(tmp_path / "panda-3cam_azure", "panda")
    assert len(reader) == 2 and reader.folder == tmp_path / "panda-3cam_azure" / "panda-3cam_azure"
