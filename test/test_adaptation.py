"""`holo-pose adapt` on real components: the shipped Panda model adapted on a small folder of the unseen look whose
labels were deleted first (so they cannot reach the adaptation), from a bag with the robot's joint states, its
weights changed where adaptation trains and nowhere else, the adapted model loaded by the estimator node in a
real rclpy graph; every bad input is one message, exit 1 and no model; an interrupted run leaves nothing."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml
from safetensors.torch import load_file
from sensor_msgs.msg import JointState
from std_msgs.msg import Header

from holo_pose_ros.adaptation.adapt import load_adapt_config
from holo_pose_ros.adaptation.finetune import LOSS_NAMES, finetune, render_synthetic
from holo_pose_ros.adaptation.pseudo_labels import PseudoLabel
from holo_pose_ros.adaptation.silhouettes import SilhouetteRenderer
from holo_pose_ros.adaptation.sources import AdaptationInputError, SourceFrame, read_camera_info_yaml, read_source
from holo_pose_ros.bags import (CAMERA_INFO_MSGTYPE, IMAGE_MSGTYPE, _BagOut, _writer, dream_to_bag, frame_stamp_ns,
                                jazzy_typestore)
from holo_pose_ros.cli import main as cli_main
from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import generate
from holo_pose_ros.data.render import DISTRACTOR_LABEL, robot_foreground
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.geometry.camera import in_image, project
from holo_pose_ros.geometry.crop import crop_affine, crop_box_from_keypoints, crop_image
from holo_pose_ros.model.network import HolisticNet, load_model_config
from holo_pose_ros.robots.kinematics import RobotModel
from holo_pose_ros.resources import weights_dir
from msg_adapters import camera_info_from_K, make_header, rgb_to_image
from test_estimator_node import Graph, camera_info_msg, header
from test_localizer import PYRAMID_SMALL

ROOT = Path(__file__).resolve().parent.parent
JOINTS_TOPIC = "/dream_replay/ground_truth/joint_states"  # dream-to-bag's ground truth: the robot's joint states


def small_config(tmp: Path, **pseudo_labels) -> Path:
    """An adaptation config sized for a test: a few rendered views and fine-tuning steps."""
    path = tmp / f"adapt_{len(list(tmp.glob('adapt_*.yaml')))}.yaml"
    path.write_text(yaml.safe_dump({"pseudo_labels": {"min_labels": 2, "max_disagreement": 0.05, **pseudo_labels},
                                    "finetune": {"steps": 3, "synthetic_views": 4, "batch_size": 2,
                                                 "synthetic_batch_size": 2}}))
    return path


@pytest.fixture(scope="module")
def unlabelled(tmp_path_factory) -> tuple[Path, Path]:
    """(folder of 8 unseen-look Panda frames with every label file deleted, the same frames labelled)."""
    labelled = tmp_path_factory.mktemp("unseen") / "labelled"
    generate("panda", 8, labelled, seed=77, workers=1, config="unseen", progress=False)
    folder = labelled.parent / "unlabelled"
    folder.mkdir()
    for p in labelled.iterdir():
        if p.name == "_camera_settings.json" or p.name.endswith(".rgb.jpg") or p.name.endswith(".rgb.png"):
            (folder / p.name).write_bytes(p.read_bytes())
    assert not [p for p in folder.iterdir() if p.suffix == ".json" and p.name != "_camera_settings.json"]
    return folder, labelled


@pytest.fixture(scope="module")
def adapted(unlabelled, tmp_path_factory) -> Path:
    folder, _ = unlabelled
    tmp = tmp_path_factory.mktemp("adapted")
    out = tmp / "model_dir"
    assert cli_main(["adapt", "--model", "panda", "--images", str(folder), "--out", str(out), "--quiet",
                     "--config", str(small_config(tmp)), "--plots", str(tmp / "plots")]) == 0
    assert (tmp / "plots" / "before_after.png").stat().st_size > 0 and (tmp / "plots" / "losses.png").is_file()
    return out / "model.yaml"


def test_images_alone_adapt_a_model_that_changes_only_what_adaptation_trains(adapted, unlabelled):
    card = yaml.safe_load(adapted.read_text())
    a = card["adaptation"]
    assert a["source_kind"] == "dream" and a["n_images"] == 8 and not a["joint_states"]
    assert a["n_pseudo_labels"] >= 2 and a["finetune_steps"] == 3 and "source_figures" not in a  # no labels to score
    # the shipped Panda (pyramid224) predicts a robot mask: mask consistency joins the other two terms
    assert set(a["losses"]) == {"keypoint consistency", "mask consistency", "rendered views"}
    parent = load_file(str(weights_dir() / "panda.safetensors"))
    assert a["parent_sha256"] == yaml.safe_load((weights_dir() / "panda.yaml").read_text())["weights_sha256"]
    child = load_file(str(adapted.with_suffix(".safetensors")))
    assert set(child) == set(parent)
    changed = {k for k in parent if not np.array_equal(parent[k].numpy(), child[k].numpy())}
    assert any(k.endswith("running_mean") for k in changed)  # BatchNorm statistics of the user's images
    assert any(k.startswith("keypoint_head.") and k.endswith("weight") and "bn" not in k for k in changed)
    learned = {k for k in changed if not k.endswith(("running_mean", "running_var", "num_batches_tracked"))}
    assert learned and all(k.startswith("keypoint_head.") for k in learned), sorted(learned - {
        k for k in learned if k.startswith("keypoint_head.")})[:5]
    assert (adapted.parent / card["lifter"]).is_file()  # the model folder is whole: its lifter beside it


def test_the_adapted_model_estimates_and_runs_in_the_node(adapted, unlabelled):
    _, labelled = unlabelled
    reader = DreamReader(labelled, "panda")
    image, K = reader.load_image(reader[0]), np.array(reader[0].K)
    estimate = Estimator.from_model(adapted).estimate(image, K)
    assert estimate.found and np.isfinite(estimate.T_cam_base).all()
    g = Graph(adapted)
    try:
        stamp = header(7)
        assert g.spin_until(lambda: g.stamped("joint_states", 7), timeout=60.0, image=rgb_to_image(image, stamp),
                            info=camera_info_msg(K, image.shape[1], image.shape[0], stamp))
        assert list(g.received["joint_states"][0].name) == g.node.estimator.robot.joint_names
    finally:
        g.close()


@pytest.fixture(scope="module")
def bag(unlabelled, tmp_path_factory) -> Path:
    """The labelled frames as a bag: images, CameraInfo and the robot's joint states (dream-to-bag's truth)."""
    out = tmp_path_factory.mktemp("bag") / "bag"
    dream_to_bag(unlabelled[1], out, progress=False)
    return out


def test_a_bag_with_joint_states_gives_each_image_its_joints_and_adapts(bag, unlabelled, tmp_path):
    source = read_source(bag, Estimator.from_model("panda").robot.joint_names, JOINTS_TOPIC)
    truth = DreamReader(unlabelled[1], "panda")
    assert source.kind == "bag" and source.has_joints and len(source.frames) == len(truth)
    for frame, labelled in zip(source.frames, truth):
        np.testing.assert_allclose(frame.joints, labelled.joints, atol=1e-6)
    out = tmp_path / "with_joints"
    assert cli_main(["adapt", "--model", "panda", "--images", str(bag), "--joint-states-topic", JOINTS_TOPIC,
                     "--out", str(out), "--quiet", "--config", str(small_config(tmp_path))]) == 0
    card = yaml.safe_load((out / "model.yaml").read_text())["adaptation"]
    assert card["joint_states"] and card["joint_states_topic"] == JOINTS_TOPIC and card["source_kind"] == "bag"


def test_the_camera_info_yaml_of_camera_calibration_is_read_and_checked(tmp_path):
    doc = {"image_width": 640, "image_height": 480, "camera_name": "cam",
           "camera_matrix": {"rows": 3, "cols": 3, "data": [600.0, 0, 320, 0, 610, 240, 0, 0, 1]},
           "distortion_model": "plumb_bob", "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0] * 5}}
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump(doc))
    K, width, height = read_camera_info_yaml(path)
    assert (width, height) == (640, 480) and K[0, 0] == 600 and K[1, 1] == 610 and K[1, 2] == 240
    del doc["camera_matrix"]
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(AdaptationInputError, match="camera_matrix.data"):
        read_camera_info_yaml(path)


def _camera_yaml(folder: Path, width: int, height: int) -> None:
    (folder / "camera_info.yaml").write_text(yaml.safe_dump({
        "image_width": width, "image_height": height,
        "camera_matrix": {"rows": 3, "cols": 3, "data": [500.0, 0, width / 2, 0, 500, height / 2, 0, 0, 1]}}))


def _blank_folder(tmp: Path) -> Path:
    folder = tmp / "blank"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:03d}.png"), np.full((240, 320, 3), 40 + 50 * i, np.uint8))
    _camera_yaml(folder, 320, 240)
    return folder


def _wrong_size_folder(tmp: Path, unlabelled) -> Path:
    folder = tmp / "wrong_size"
    folder.mkdir()
    image = next(p for p in unlabelled[0].iterdir() if p.name.endswith(".rgb.jpg"))
    (folder / image.name).write_bytes(image.read_bytes())
    _camera_yaml(folder, 320, 240)
    return folder


def _bag_lacking_joints(tmp: Path, unlabelled) -> Path:
    reader = DreamReader(unlabelled[1], "panda")
    out = tmp / "lacking"
    writer = _writer(out, "mcap")
    bag = _BagOut(writer, jazzy_typestore())
    try:
        for i, frame in enumerate(reader):
            t = frame_stamp_ns(i)
            h = make_header(t, "camera")
            bag.write("/camera_info", CAMERA_INFO_MSGTYPE, camera_info_from_K(frame.K, frame.width, frame.height, h), t)
            bag.write("/image", IMAGE_MSGTYPE, rgb_to_image(reader.load_image(frame), h), t)
            bag.write("/joint_states", "sensor_msgs/msg/JointState",
                      JointState(header=Header(stamp=h.stamp), name=["panda_joint1"], position=[0.1]), t)
    finally:
        writer.close()
    return out


BAD_INPUTS = {
    "no robot in any image": (lambda tmp, u, b: ["--images", str(_blank_folder(tmp))], "no panda robot found in any"),
    "images of another size than the camera file": (
        lambda tmp, u, b: ["--images", str(_wrong_size_folder(tmp, u))], "but .*camera_info.yaml is for 320 x 240 px"),
    "too few usable pseudo-labels": (
        lambda tmp, u, b: ["--images", str(u[0]), "--config", str(small_config(tmp, min_labels=1000))],
        "usable pseudo-labels of 8 images"),
    "a bag without the image topic": (lambda tmp, u, b: ["--images", str(b), "--image-topic", "/camera/nope"],
                                      "no topic /camera/nope in the bag"),
    "a bag without the joint-state topic": (lambda tmp, u, b: ["--images", str(b), "--joint-states-topic", "/robot/js"],
                                            "no topic /robot/js in the bag"),
    "a joint-state topic that lacks joints": (
        lambda tmp, u, b: ["--images", str(_bag_lacking_joints(tmp, u)), "--joint-states-topic", "/joint_states"],
        "no message on /joint_states holds every joint of the robot \\(lacking panda_finger_joint1, panda_joint2"),
    "joint states asked of a folder": (lambda tmp, u, b: ["--images", str(u[0]), "--joint-states-topic", "/js"],
                                       "joint states come from a bag"),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_is_one_message_exit_1_and_no_model(case, unlabelled, bag, tmp_path, capsys):
    arguments, message = BAD_INPUTS[case]
    out = tmp_path / "out" / "adapted"
    rc = cli_main(["adapt", "--model", "panda", "--out", str(out), "--quiet", *arguments(tmp_path, unlabelled, bag)])
    err = capsys.readouterr().err
    assert rc == 1 and err.startswith("holo-pose adapt: error: ") and len(err.strip().splitlines()) == 1, err
    assert re.search(message, err), err
    assert not out.exists() and not (out.parent.exists() and list(out.parent.iterdir()))


def test_an_existing_output_folder_is_never_overwritten(unlabelled, tmp_path, capsys):
    (tmp_path / "taken").mkdir()
    assert cli_main(["adapt", "--model", "panda", "--images", str(unlabelled[0]), "--out", str(tmp_path / "taken"),
                     "--quiet"]) == 1
    assert "exists" in capsys.readouterr().err and not list((tmp_path / "taken").iterdir())


def test_an_interrupted_adaptation_leaves_no_model(unlabelled, tmp_path):
    config = tmp_path / "long.yaml"
    config.write_text(yaml.safe_dump({"pseudo_labels": {"min_labels": 2, "max_disagreement": 0.05},
                                      "finetune": {"steps": 100000, "synthetic_views": 4, "batch_size": 2,
                                                   "synthetic_batch_size": 2}}))
    out = tmp_path / "adapted"
    process = subprocess.Popen([sys.executable, "-m", "holo_pose_ros.cli", "adapt", "--model", "panda", "--images",
                                str(unlabelled[0]), "--out", str(out), "--config", str(config), "--minutes", "10"],
                               stderr=subprocess.PIPE, text=True, cwd=ROOT, env={**os.environ, "COLUMNS": "200"})
    seen = ""
    while "adapt:" not in seen:  # the fine-tuning's progress bar: the run is mid-way
        chunk = process.stderr.read(64)
        assert chunk, f"the run ended before fine-tuning: {seen[-2000:]}"
        seen += chunk
    process.send_signal(signal.SIGINT)
    process.communicate(timeout=120)
    assert process.returncode != 0
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["long.yaml"]


def test_by_default_only_the_batchnorm_statistics_change(unlabelled, tmp_path):
    out = tmp_path / "default"
    assert cli_main(["adapt", "--model", "panda", "--images", str(unlabelled[0]), "--out", str(out), "--quiet"]) == 0
    card = yaml.safe_load((out / "model.yaml").read_text())["adaptation"]
    assert card["finetune_steps"] == 0 and card["n_pseudo_labels"] == 0 and card["config"]["batchnorm"]["keep"] == 0.5
    parent = load_file(str(weights_dir() / "panda.safetensors"))
    child = load_file(str(out / "model.safetensors"))
    changed = {k for k in parent if not np.array_equal(parent[k].numpy(), child[k].numpy())}
    assert changed and all(k.endswith(("running_mean", "running_var")) for k in changed), sorted(changed)[:5]


def test_a_labelled_source_is_scored_after_adaptation_unless_told_not_to(unlabelled, tmp_path):
    """A DREAM folder with labels: the card gets the parent's and the adapted model's figures on its frames (read
    after adaptation); `--no-score` skips them, for sweeps."""
    labelled = unlabelled[1]
    for name, flags in (("scored", []), ("unscored", ["--no-score"])):
        assert cli_main(["adapt", "--model", "panda", "--images", str(labelled), "--out", str(tmp_path / name),
                         "--quiet", *flags]) == 0
    scored = yaml.safe_load((tmp_path / "scored" / "model.yaml").read_text())["adaptation"]
    assert set(scored["source_figures"]) >= {"parent", "adapted"}, scored["source_figures"]
    assert "source_figures" not in yaml.safe_load((tmp_path / "unscored" / "model.yaml").read_text())["adaptation"]


def test_the_mask_targets_are_the_silhouette_the_generator_drew(unlabelled):
    reader = DreamReader(unlabelled[1], "panda")
    silhouettes = SilhouetteRenderer("panda", 224)
    for frame in list(reader)[:3]:
        labels = cv2.imread(str(frame.mask_path), cv2.IMREAD_UNCHANGED)
        centre = np.round(frame.keypoints_2d[frame.in_image].mean(0))
        box = np.array([centre[0] - 112, centre[1] - 112, 224.0])  # a 1:1 crop: the generator's mask only shifts
        target = silhouettes(frame.joints, frame.T_cam_base, crop_affine(box, 224) @ frame.K, box, frame.width,
                             frame.height)
        drawn = crop_image(robot_foreground(labels).astype(np.uint8) * 255, box, 224) > 127
        seen = crop_image((labels != DISTRACTOR_LABEL).astype(np.uint8) * 255, box, 224) > 127  # not occluded
        iou = (target & drawn & seen).sum() / ((target | drawn) & seen).sum()
        assert drawn.sum() > 500 and iou > 0.97, (frame.name, iou)


def _true_pseudo_labels(folder: Path, robot: RobotModel, n: int) -> tuple[list[SourceFrame], list[PseudoLabel]]:
    """The first `n` labelled frames as source frames and pseudo-labels of their true pose (a perfect fit)."""
    reader = DreamReader(folder, robot.name)
    frames, labels = [], []
    for i, f in enumerate(list(reader)[:n]):
        frames.append(SourceFrame(f.name, reader.load_image(f), f.K))
        with torch.inference_mode():
            points = robot.fit_keypoints_in_camera(torch.tensor(f.joints[None], dtype=robot.dtype),
                                                   torch.tensor(f.T_cam_base[None], dtype=robot.dtype))[0]
        uv = project(points.double().numpy(), f.K)
        box = crop_box_from_keypoints(f.keypoints_2d[f.in_image], f.width, f.height)
        labels.append(PseudoLabel(i, f.joints, f.T_cam_base, uv, in_image(uv, f.width, f.height),
                                  float(f.keypoints_3d[0, 2]), box, 1.0, 0.0))
    return frames, labels


def test_mask_consistency_trains_a_segmentation_head_towards_the_fitted_silhouette(unlabelled):
    robot = RobotModel("panda")
    frames, labels = _true_pseudo_labels(unlabelled[1], robot, 2)
    synthetic = render_synthetic("panda", PYRAMID_SMALL["input_size"], "randomized", 2, seed=3, progress=False)
    cfg = {**load_adapt_config()["finetune"], "steps": 15, "lr": 1.0e-2, "batch_size": 2, "synthetic_batch_size": 2}
    assert cfg["mask_consistency_weight"] > 0  # on by default whenever fine-tuning runs on a network with a mask
    torch.manual_seed(0)
    net = HolisticNet(load_model_config(PYRAMID_SMALL), robot).eval()
    before = net.keypoint_head.mask_out.weight.detach().clone()
    result = finetune(net, robot, frames, labels, synthetic, cfg, seconds=600.0, progress=False)
    assert set(result.history) == set(LOSS_NAMES) and result.steps == 15
    mask = result.history["mask consistency"]
    assert np.isfinite(mask).all() and mask[-3:].mean() < mask[:3].mean()  # it learns the rendered silhouettes
    assert not torch.equal(before, net.keypoint_head.mask_out.weight)
    off = finetune(net, robot, frames, labels, synthetic, {**cfg, "steps": 1, "mask_consistency_weight": 0.0},
                   seconds=600.0, progress=False)
    assert set(off.history) == {"keypoint consistency", "rendered views"}


def test_a_swallowed_ctrl_c_still_stops_the_fine_tuning_loop():
    from holo_pose_ros.adaptation.interrupts import sigint_latch

    before = signal.getsignal(signal.SIGINT)
    with sigint_latch() as check_interrupt:
        check_interrupt()  # nothing latched yet
        try:  # a finalizer that swallows the KeyboardInterrupt raised inside it
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        with pytest.raises(KeyboardInterrupt):
            check_interrupt()
    assert signal.getsignal(signal.SIGINT) is before  # the previous handler is back
