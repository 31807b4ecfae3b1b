"""`holo-pose dream-to-bag` -> `holo-pose bag-eval` round trip in both rosbag2 storages (mcap, sqlite3), without
DDS: real rendered frames, a real (untrained) network, real bag files read back with rosbags."""

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from holo_pose_ros.bags import (CAMERA_INFO_TOPIC, DEFAULT_FRAME_ID, ESTIMATOR_NS, GROUND_TRUTH_NS, IMAGE_TOPIC,
                                MSGTYPES, bag_eval, frame_stamp_ns, ground_truth_from_messages)
from holo_pose_ros.cli import main
from msg_adapters import stamp_ns
from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import generate
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.evaluation.run import evaluate_folder
from msg_adapters import camera_info_to_K, image_to_rgb

N_FRAMES = 3


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bag_data")
    generate("panda", N_FRAMES, folder, seed=5, workers=1, width=320, height=240, progress=False)
    return folder


@pytest.fixture(scope="module")
def model(small_model_card):
    return small_model_card


@pytest.fixture(scope="module")
def expected(data, model):
    estimator = Estimator.from_model(model, min_confidence=0.0)
    report, _, _ = evaluate_folder(estimator, DreamReader(data, estimator.robot), progress=False)
    return report


def read_bag(path: Path) -> dict[str, list[tuple[int, object]]]:
    """topic -> [(log time ns, message)] in log-time order."""
    messages: dict[str, list] = {}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for conn, t_ns, raw in reader.messages():
            messages.setdefault(conn.topic, []).append((t_ns, reader.deserialize(raw, conn.msgtype)))
    return messages


@pytest.fixture(scope="module", params=["mcap", "sqlite3"])
def bags(request, data, model, tmp_path_factory):
    """(storage, input bag, estimate bag) made by the two CLI sub-commands."""
    storage, root = request.param, tmp_path_factory.mktemp(f"bags_{request.param}")
    assert main(["dream-to-bag", str(data), str(root / "in"), "--storage", storage, "--robot", "panda", "--quiet"]) == 0
    assert main(["bag-eval", "--bag", str(root / "in"), "--model", str(model), "--out", str(root / "out"),
                 "--min-confidence", "0", "--storage", storage, "--quiet"]) == 0
    return storage, root / "in", root / "out"


def test_dream_to_bag_holds_the_exact_images_camera_and_ground_truth(bags, data):
    storage, bag_in, _ = bags
    metadata = yaml.safe_load((bag_in / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["storage_identifier"] == storage and metadata["version"] == 9
    messages = read_bag(bag_in)
    assert set(messages) == {IMAGE_TOPIC, CAMERA_INFO_TOPIC} | {f"{GROUND_TRUTH_NS}/{n}" for n in MSGTYPES}
    assert all(len(m) == N_FRAMES for m in messages.values())
    reader = DreamReader(data, "panda")
    robot = reader.robot
    stamps = [frame_stamp_ns(i) for i in range(N_FRAMES)]
    for i, frame in enumerate(reader):
        t_ns, image = messages[IMAGE_TOPIC][i]
        assert t_ns == stamps[i] == stamp_ns(image.header.stamp) and image.header.frame_id == DEFAULT_FRAME_ID
        assert image.encoding == "rgb8"
        np.testing.assert_array_equal(image_to_rgb(image), reader.load_image(frame))  # the decoded JPEG, exactly
        info = messages[CAMERA_INFO_TOPIC][i][1]
        assert stamp_ns(info.header.stamp) == stamps[i] and (info.width, info.height) == (frame.width, frame.height)
        np.testing.assert_array_equal(camera_info_to_K(info), frame.K)
        gt = {n: messages[f"{GROUND_TRUTH_NS}/{n}"][i][1] for n in MSGTYPES}
        assert all(stamp_ns(m.header.stamp) == stamps[i] for m in gt.values())
        truth = ground_truth_from_messages(frame.name, gt["keypoints"], gt["keypoints_2d"], gt["joint_states"],
                                           gt["pose"], robot.joint_names, robot.keypoint_names)
        np.testing.assert_array_equal(truth.keypoints_3d, frame.keypoints_3d)  # float64 end to end
        np.testing.assert_array_equal(truth.joints, frame.joints)
        np.testing.assert_allclose(truth.T_cam_base, frame.T_cam_base, atol=1e-12)
        np.testing.assert_allclose(truth.keypoints_2d, frame.keypoints_2d, atol=1e-3)  # float32 pixels
        np.testing.assert_array_equal(truth.in_image, frame.in_image)


def test_bag_eval_writes_one_estimate_per_image_and_topic_and_the_report(bags, expected):
    storage, bag_in, bag_out = bags
    metadata = yaml.safe_load((bag_out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["storage_identifier"] == storage
    images = read_bag(bag_in)[IMAGE_TOPIC]
    estimates = read_bag(bag_out)
    assert set(estimates) == {f"{ESTIMATOR_NS}/{n}" for n in MSGTYPES}
    for topic, messages in estimates.items():
        assert [t for t, _ in messages] == [t for t, _ in images], topic  # the images' log times
        for (_, msg), (_, image) in zip(messages, images):
            assert stamp_ns(msg.header.stamp) == stamp_ns(image.header.stamp)
            assert msg.header.frame_id == image.header.frame_id
    report = json.loads((bag_out / "report.json").read_text())
    assert report["n_frames"] == N_FRAMES and report["n_not_found"] == 0
    # the same estimator on the same pixels and intrinsics: the report of `holo-pose evaluate`
    for key in ("add_mean_mm", "add_median_mm", "add_auc"):
        assert report[key] == pytest.approx(expected[key], abs=1e-3)
    assert report["joint_error_deg"]["mean"] == pytest.approx(expected["joint_error_deg"]["mean"], abs=1e-4)
    assert report["rotation_error_deg"]["mean"] == pytest.approx(expected["rotation_error_deg"]["mean"], abs=1e-4)


def test_bag_eval_without_ground_truth_writes_estimates_only(bags, model, tmp_path):
    _, bag_in, _ = bags
    summary = bag_eval(bag_in, model, tmp_path / "out", min_confidence=0.0, ground_truth_ns="/no_ground_truth",
                       progress=False)
    assert (summary.n_images, summary.n_found, summary.report) == (N_FRAMES, N_FRAMES, None)
    assert not (tmp_path / "out" / "report.json").exists()
    with pytest.raises(ValueError, match="already exists"):
        bag_eval(bag_in, model, tmp_path / "out", progress=False)
