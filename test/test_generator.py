"""The synthetic generator on real renders: labels agree with geometry, output is deterministic, CLI works."""

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import DISTRACTOR_LABEL, SETTINGS_FILE, generate
from holo_pose_ros.geometry.camera import project
from holo_pose_ros.robots.kinematics import RobotModel


@pytest.fixture(scope="module")
def panda_folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("panda")
    generate("panda", 8, out, seed=3, workers=1, progress=False)
    return out


def check_frames(folder, robot: str, n: int):
    """Every written frame is valid and its labels agree with the robot's geometry."""
    reader = DreamReader(folder, robot)
    assert len(reader) == n and not reader.problems
    model = RobotModel(robot, dtype=torch.float64)
    for frame in reader:
        # projected_location is K P / z of the 3D keypoints
        np.testing.assert_allclose(frame.keypoints_2d, project(frame.keypoints_3d, frame.K), atol=0.01)
        # the 3D keypoints are FK(joints) moved by the base pose
        fk = model.keypoints_in_camera(torch.tensor(frame.joints[None]), torch.tensor(frame.T_cam_base[None]))[0]
        np.testing.assert_allclose(frame.keypoints_3d, fk.numpy(), atol=1e-4)
        # the mask covers every in-image keypoint (within 3 px), unless a distractor hides it
        mask = reader.load_mask(frame)
        assert mask.shape == (frame.height, frame.width)
        for (u, v), inside in zip(frame.keypoints_2d, frame.in_image):
            if not inside:
                continue
            u, v = int(round(min(u, frame.width - 1))), int(round(min(v, frame.height - 1)))
            window = mask[max(v - 3, 0):v + 4, max(u - 3, 0):u + 4]
            robot = (window > 0) & (window < DISTRACTOR_LABEL)
            assert robot.any() or (window == DISTRACTOR_LABEL).any(), f"{frame.name}: keypoint ({u}, {v}) off the mask"
    return reader


def test_panda_frames_are_consistent(panda_folder):
    reader = check_frames(panda_folder, "panda", 8)
    frames = list(reader)
    assert all(f.base_pose_source == "quaternion" for f in frames)
    image = reader.load_image(frames[0])
    assert image.shape == (480, 640, 3) and image.std() > 10  # a real picture, not a blank
    # the camera is drawn once per folder, joints per frame, within the URDF limits
    assert all(np.allclose(f.K, frames[0].K) for f in frames)
    model = RobotModel("panda", dtype=torch.float64)
    q = np.stack([f.joints for f in frames])
    assert (q >= model.lower.numpy() - 1e-9).all() and (q <= model.upper.numpy() + 1e-9).all()
    assert len({tuple(f.joints.round(6)) for f in frames}) == len(frames)
    settings = json.loads((panda_folder / SETTINGS_FILE).read_text())  # how the folder was made
    assert (settings["robot"], settings["n"], settings["seed"]) == ("panda", 8, 3) and "--seed 3" in settings["command"]


@pytest.mark.parametrize("robot", ["kuka", "baxter"])
def test_other_robots(tmp_path, robot):
    generate(robot, 3, tmp_path, seed=1, workers=1, progress=False)
    check_frames(tmp_path, robot, 3)


def test_same_seed_same_frames_any_worker_count(tmp_path, panda_folder):
    generate("panda", 4, tmp_path, seed=3, workers=2, progress=False)
    for name in ["000000", "000003"]:
        assert (tmp_path / f"{name}.json").read_bytes() == (panda_folder / f"{name}.json").read_bytes()
        assert (tmp_path / f"{name}.rgb.jpg").read_bytes() == (panda_folder / f"{name}.rgb.jpg").read_bytes()
        assert (tmp_path / f"{name}.mask.png").read_bytes() == (panda_folder / f"{name}.mask.png").read_bytes()


def test_randomization_covers_truncation_and_occlusion(tmp_path):
    generate("panda", 40, tmp_path, seed=11, workers=2, progress=False)
    reader = DreamReader(tmp_path, "panda")
    frames = list(reader)
    truncated = sum(not f.in_image.all() for f in frames)
    occluded = sum((reader.load_mask(f) == DISTRACTOR_LABEL).any() for f in frames)
    depths = [f.T_cam_base[2, 3] for f in frames]
    assert 0 < truncated < len(frames)
    assert occluded > 0
    assert max(depths) > 1.5 * min(depths)


def test_cli_generate_and_show(tmp_path):
    out = tmp_path / "cli"
    run = subprocess.run([sys.executable, "-m", "holo_pose_ros.cli", "generate", "--robot", "kuka", "--n", "2",
                          "--out", str(out), "--workers", "1", "--quiet"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert "wrote 2 frames" in run.stdout
    run = subprocess.run([sys.executable, "-m", "holo_pose_ros.cli", "show", str(out), "--robot", "kuka"],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert "2 good" in run.stdout and (out / "preview.png").stat().st_size > 10_000
    bad = subprocess.run([sys.executable, "-m", "holo_pose_ros.cli", "show", str(tmp_path / "nothing"), "--robot", "kuka"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "nothing" in bad.stderr
