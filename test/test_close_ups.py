"""Close-ups: the robot YAML's `close_ups` (an arm, a hand: the subtree of a URDF link) name the fit keypoints
that a second network pass sees at the part's own scale. Training draws `close_up` views around them (real renders),
old three-mode configs draw exactly the views they drew before, and the estimator's `close_ups` pass replaces the
crop pass's detections of the part's points only (the shipped Panda network, a rendered frame)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import yaml

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import generate, load_generator_config
from holo_pose_ros.data.training import MODES, RenderedViews, SampleConfig, mode_probabilities
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.resources import config_dir
from holo_pose_ros.robots.kinematics import RobotModel
from holo_pose_ros.robots.spec import load_robot_spec


def test_close_ups_are_the_fit_keypoints_of_a_links_subtree():
    baxter = RobotModel("baxter")
    arms = baxter.close_up_fit_indices()
    assert set(arms) == {"left_arm", "right_arm"} and not set(arms["left_arm"]) & set(arms["right_arm"])
    names = baxter.fit_keypoint_names
    for side in ("left", "right"):
        dream = {n for n in baxter.keypoint_names if n.startswith(side)}
        assert dream <= {names[i] for i in arms[f"{side}_arm"]}
        assert not any(names[i].startswith("torso") or names[i].startswith("head") for i in arms[f"{side}_arm"])
    panda = RobotModel("panda")
    hand = {panda.spec.fit_keypoints[i].link for i in panda.close_up_fit_indices()["hand"]}
    assert {"panda_link6", "panda_link7", "panda_hand", "panda_leftfinger"} <= hand and "panda_link5" not in hand


def robot_yaml(tmp_path, close_ups) -> str:
    """A copy of the Panda YAML with another `close_ups` entry (None: without one)."""
    data = yaml.safe_load((config_dir() / "robots" / "panda.yaml").read_text())
    data.pop("close_ups")
    if close_ups is not None:
        data["close_ups"] = close_ups
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_a_bad_close_up_names_the_yaml(tmp_path):
    with pytest.raises(ValueError, match="robot.yaml: close-up 'hand' starts at link 'no_such_link'"):
        RobotModel(robot_yaml(tmp_path, {"hand": "no_such_link"})).close_up_fit_indices()
    with pytest.raises(ValueError, match="robot.yaml: 'close_ups' must map"):
        load_robot_spec(robot_yaml(tmp_path, ["panda_link6"]))


def test_close_up_views_magnify_the_part_and_old_configs_draw_the_same_views(tmp_path):
    generator = load_generator_config("randomized")
    hand = RobotModel("panda").close_up_fit_indices()["hand"]
    close = RenderedViews("panda", SampleConfig(64, mode_probabilities=(0, 0, 0, 1)), generator, seed=5, length=6)
    crops = RenderedViews("panda", SampleConfig(64, mode_probabilities=(1, 0, 0)), generator, seed=5, length=6)
    ratios = []
    for i in range(6):
        c, w = close[i], crops[i]
        assert MODES[int(c["mode"])] == "close_up" and float(c["presence"]) == 1.0 and c["mask"].any()
        in_crop = ((c["uv_fit"][hand] >= -0.5) & (c["uv_fit"][hand] <= 63.5)).all(1)
        assert in_crop.float().mean() > 0.8  # the part is in its close-up (box jitter may cut a few points)
        spread = lambda s: float(s["uv_fit"][hand].std(0).norm())  # noqa: E731 (crop px)
        ratios.append(spread(c) / spread(w))
    assert np.mean(ratios) > 1.3, ratios  # the hand is larger in its close-up than in the robot's crop
    # a config of three modes draws exactly what it drew before close-ups existed
    three = RenderedViews("panda", SampleConfig(64, mode_probabilities=(0.5, 0.3, 0.2)), generator, seed=9, length=3)
    four = RenderedViews("panda", SampleConfig(64, mode_probabilities=(0.5, 0.3, 0.2, 0.0)), generator, seed=9, length=3)
    for i in range(3):
        a, b = three[i], four[i]
        assert all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(ValueError, match="names no close_ups"):
        RenderedViews(robot_yaml(tmp_path, None), SampleConfig(64, mode_probabilities=(0.5, 0.2, 0.1, 0.2)), generator,
                      seed=1, length=1)
    with pytest.raises(ValueError, match="3 or 4 non-negative numbers"):
        mode_probabilities((0.5, 0.5, 0.5))


def test_the_close_up_pass_replaces_only_the_parts_detections(tmp_path):
    generate("panda", 2, tmp_path / "frames", seed=77, workers=1, progress=False)
    frames = list(DreamReader(tmp_path / "frames", "panda"))
    plain = Estimator.from_model("panda", close_ups=False)
    close = Estimator.from_model("panda", close_ups=True)
    hand = close.robot.close_up_fit_indices()["hand"]
    rest = np.setdiff1d(np.arange(close.robot.n_fit_keypoints), hand)
    for frame in frames:
        image = DreamReader(tmp_path / "frames", "panda").load_image(frame)
        timings: dict[str, float] = {}
        a, b = plain.detect(image, frame.K), close.detect(image, frame.K, timings)
        assert not a.close_up_boxes and set(b.close_up_boxes) == {"hand"} and timings["close_ups"] > 0
        assert b.close_up_boxes["hand"][2] < b.box[2]  # the hand's box is smaller than the robot's
        np.testing.assert_array_equal(a.uv[rest], b.uv[rest])
        np.testing.assert_array_equal(a.confidence[rest], b.confidence[rest])
        assert np.abs(a.uv[hand] - b.uv[hand]).max() > 0.1
        assert close.estimate(image, frame.K).found
    with pytest.raises(ValueError, match="names no close_ups"):
        Estimator(plain.net, RobotModel(robot_yaml(tmp_path, None)), close_ups=True)
