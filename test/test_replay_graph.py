"""The live graph (DREAM replay -> estimator node -> evaluation node, lockstep) scores a model exactly as
`holo-pose evaluate` does, on real rendered frames, a real (untrained) network and a real in-process rclpy graph
with its own context and domain."""

import json
import os
import time

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import generate
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.evaluation.report import per_frame_add
from holo_pose_ros.evaluation.run import evaluate_folder
from holo_pose_ros.nodes.dream_replay_node import MAX_RESENDS, DreamReplayNode
from holo_pose_ros.nodes.estimator_node import EstimatorNode
from holo_pose_ros.nodes.evaluation_node import EvaluationNode

N_FRAMES = 3
DOMAIN_ID = 101 + os.getpid() % 100  # away from the default domain 0 and from parallel test runs


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    folder = tmp_path_factory.mktemp("replay_data")
    generate("panda", N_FRAMES, folder, seed=11, workers=1, width=320, height=240, progress=False)
    return folder


@pytest.fixture(scope="module")
def model(small_model_card):
    return small_model_card


def run_graph(data, model, report_path, min_confidence: float, timeout_s: float = 40.0, estimator_params=(),
              replay_params=()):
    """Spin replay + estimator + evaluation in one executor until the evaluation node has written its report;
    returns the three nodes (destroyed)."""
    context = Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    nodes = []
    try:
        nodes.append(EstimatorNode(context=context, parameter_overrides=[
            Parameter("model", value=str(model)), Parameter("device", value="cpu"),
            Parameter("min_confidence", value=min_confidence), *estimator_params]))
        nodes.append(DreamReplayNode(context=context, parameter_overrides=[
            Parameter("folder", value=str(data)), Parameter("lockstep", value=True),
            Parameter("lockstep_timeout_s", value=20.0), *replay_params]))
        evaluation = EvaluationNode(context=context, parameter_overrides=[
            Parameter("report_path", value=str(report_path)), Parameter("done_grace_s", value=1.5)])
        nodes.append(evaluation)
        executor = SingleThreadedExecutor(context=context)
        for node in nodes:
            executor.add_node(node)
        deadline = time.monotonic() + timeout_s
        while not evaluation.finished and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        return tuple(nodes)
    finally:
        for node in reversed(nodes):
            node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.mark.parametrize("min_confidence", [0.0, 1.0], ids=["all_found", "none_found"])
def test_live_report_equals_holo_pose_evaluate(data, model, tmp_path, min_confidence):
    # the same backend as the node's default (config/estimator.yaml), so the two must agree to rounding
    estimator = Estimator.from_model(model, backend="onnxruntime", min_confidence=min_confidence)
    expected, expected_results, _ = evaluate_folder(estimator, DreamReader(data, estimator.robot), progress=False)

    _, replay, evaluation = run_graph(data, model, tmp_path / "report.json", min_confidence)

    assert evaluation.finished, "the evaluation node wrote no report in time"
    assert replay.finished and replay.sent == N_FRAMES and replay.unanswered == 0
    assert np.all(np.diff(replay.stamps) > 0)
    report = json.loads((tmp_path / "report.json").read_text())
    assert report == json.loads(json.dumps(evaluation.report))
    assert report["n_frames"] == expected["n_frames"] == N_FRAMES
    assert report["n_not_found"] == expected["n_not_found"] == (0 if min_confidence == 0.0 else N_FRAMES)
    add, found = per_frame_add(evaluation.results)
    expected_add, expected_found = per_frame_add(expected_results)
    np.testing.assert_array_equal(found, expected_found)
    np.testing.assert_allclose(add, expected_add, atol=1e-6, equal_nan=True)  # metres
    assert report["add_auc"] == pytest.approx(expected["add_auc"], abs=1e-6)
    for key in ("add_mean_mm", "add_median_mm"):
        assert report[key] == pytest.approx(expected[key], abs=1e-3, nan_ok=True)
    if min_confidence == 0.0:
        assert report["joint_error_deg"]["mean"] == pytest.approx(expected["joint_error_deg"]["mean"], abs=1e-4)
        assert report["rotation_error_deg"]["mean"] == pytest.approx(expected["rotation_error_deg"]["mean"], abs=1e-4)
        assert report["depth_error_mm"]["mean"] == pytest.approx(expected["depth_error_mm"]["mean"], abs=1e-3)
        assert report["reproj_error_px"]["mean"] == pytest.approx(expected["reproj_error_px"]["mean"], abs=1e-3)
        assert report["truncation"] == expected["truncation"]


def test_lockstep_never_waits_forever_on_an_estimator_that_cannot_answer(data, model, tmp_path):
    # The estimator listens for CameraInfo where nobody publishes: it skips every image. The replay learns it from
    # /diagnostics, sends the frame again (MAX_RESENDS times), then moves on; the frame counts as not found.
    estimator, replay, evaluation = run_graph(
        data, model, tmp_path / "report.json", 0.0, estimator_params=[Parameter("camera_info_topic", value="nowhere")],
        replay_params=[Parameter("limit", value=1)])
    assert evaluation.finished and replay.finished and replay.sent == 1 and replay.unanswered == 0
    assert estimator.stats.no_camera_info == 1 + MAX_RESENDS and estimator.stats.processed == 0
    assert (evaluation.report["n_frames"], evaluation.report["n_not_found"]) == (1, 1)
