"""The static camera (static_camera.py): its running robust average, the prior it gives once min_frames poses
are in, single disagreeing frames kept out, a moved camera restarting it, bad configurations refused; and on real
renders, a generated video of two clips (two cameras) estimated with the shipped Panda: the average lands near each
clip's true base pose (nearer than to the other clip's), the move between clips is noticed, and `holo-pose evaluate
--static-camera` runs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from holo_pose_ros.calibration import pose_error
from holo_pose_ros.cli import main as cli_main
from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import generate
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.fitting.residuals import so3_exp
from holo_pose_ros.static_camera import StaticCamera, load_static_camera_config


def pose(rotation_vector, translation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = so3_exp(np.asarray(rotation_vector, float)), translation
    return T


def noisy(T: np.ndarray, rng: np.random.Generator, sigma_m: float = 0.01, sigma_rad: float = 0.01) -> np.ndarray:
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ so3_exp(rng.normal(0, sigma_rad, 3))
    out[:3, 3] += rng.normal(0, sigma_m, 3)
    return out


def test_the_average_becomes_a_prior_after_min_frames_and_a_moved_camera_restarts_it():
    rng = np.random.default_rng(3)
    truth, moved = pose([0.3, -0.2, 1.0], [0.1, -0.2, 1.6]), pose([-0.4, 0.5, 0.2], [0.6, 0.1, 2.2])
    camera = StaticCamera({"min_frames": 5, "jump_frames": 3, "sigma_m": 0.02, "sigma_deg": 2.0})
    for i in range(5):
        assert camera.prior() is None  # fewer than min_frames poses so far
        camera.observe(noisy(truth, rng))
    prior = camera.prior()
    assert prior is not None and prior.sigma_m == 0.02 and prior.sigma_rad == pytest.approx(np.radians(2.0))
    dt, dr = pose_error(prior.T_cam_base, truth)
    assert dt < 0.015 and dr < 1.0
    for _ in range(2):  # two wrong frames (a wrong basin): not averaged, no restart
        camera.observe(moved)
    assert camera.restarts == 0 and len(camera.poses) == 5
    camera.observe(noisy(truth, rng))  # an agreeing frame ends the run of disagreeing ones
    for _ in range(3):
        camera.observe(noisy(moved, rng))
    assert camera.restarts == 1 and len(camera.poses) == 3 and camera.prior() is None
    for _ in range(2):
        camera.observe(noisy(moved, rng))
    assert pose_error(camera.prior().T_cam_base, moved)[0] < 0.015
    camera.reset()
    assert camera.prior() is None and not camera.poses
    with pytest.raises(ValueError, match="finite 4 x 4"):
        camera.observe(np.full((4, 4), np.nan))


def test_bad_configurations_are_refused():
    with pytest.raises(ValueError, match="min_frames <= window"):
        load_static_camera_config({"window": 5, "min_frames": 10})
    with pytest.raises(ValueError, match="positive"):
        load_static_camera_config({"sigma_m": 0.0})
    with pytest.raises(ValueError, match="unknown static camera parameters"):
        load_static_camera_config({"windw": 5})


@pytest.fixture(scope="module")
def two_clips(tmp_path_factory):
    """A generated video of two 8-frame clips: one camera each, the robot moving."""
    folder = tmp_path_factory.mktemp("static")
    config = {"extends": "video", "video": {"clip_frames": 8, "leg_frames": [4, 8], "reach": 0.1}}
    (folder / "clips.yaml").write_text(yaml.safe_dump(config))
    generate("panda", 16, folder / "video", seed=21, workers=1, progress=False, config=folder / "clips.yaml")
    return folder / "video"


def near(average: np.ndarray, truth: np.ndarray, other: np.ndarray) -> bool:
    """Whether an averaged base pose lies within 10 cm and 20 deg of `truth` (a few frames of an untrained-for
    camera: the base's yaw trades off against joint 1) and nearer to it than to `other`, in both."""
    dt, dr = pose_error(average, truth)
    ot, orot = pose_error(average, other)
    return dt < 0.1 and dr < 20.0 and dt < ot and dr < orot


def test_a_video_of_two_cameras_is_averaged_per_camera(two_clips, tmp_path):
    reader = DreamReader(two_clips, "panda")
    frames = list(reader)
    first, second = frames[0].T_cam_base, frames[8].T_cam_base
    dt, dr = pose_error(first, second)
    assert dt > 0.2 or dr > 15.0  # the clips' cameras differ by more than the jump limits
    estimator = Estimator.from_model("panda", static_camera={"min_frames": 4, "jump_frames": 3})
    for i, (frame, image) in enumerate(reader.images(frames)):
        estimate = estimator.estimate(image, frame.K)
        assert estimate.found, frame.name
        if i == 7:  # the end of the first clip: near its camera's pose, nearer than to the next clip's
            assert near(estimator.static_camera.prior().T_cam_base, first, second)
            assert estimator.static_camera.restarts == 0
    assert estimator.static_camera.restarts == 1  # the camera moved once
    assert near(estimator.static_camera.prior().T_cam_base, second, first)
    estimator.reset()
    assert estimator.static_camera.prior() is None

    reports = {}
    for diagnostics in ("--depth-diagnostics", "--no-depth-diagnostics"):
        out = tmp_path / f"report{diagnostics}.json"
        assert cli_main(["evaluate", "--model", "panda", "--data", str(two_clips), "--static-camera", "--quiet",
                         diagnostics, "--out", str(out)]) == 0
        reports[diagnostics] = json.loads(out.read_text())
    report = reports["--depth-diagnostics"]
    assert report["n_frames"] == 16 and report["add_auc"] > 0 and "depth_diagnostics" in report
    # the diagnostics' second fit of each detection neither feeds nor uses the static camera: the same estimates
    assert report["add_auc"] == reports["--no-depth-diagnostics"]["add_auc"]
