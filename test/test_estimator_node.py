"""The estimator node in a real rclpy graph, no mocks: its own Context and domain id per test, the shared-memory
Fast DDS profile and localhost discovery (conftest.py), a small untrained network saved as a model card, and a
rendered Panda frame. Outputs carry the image's header and match the core; bad messages are survived; a
publisher in another process reaches the node."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray, PoseStamped, TransformStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, JointState, PointCloud2
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import generate
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.model.cards import read_card
from holo_pose_ros.nodes.estimator_node import EstimatorNode, main
from graph_helpers import domain_ids, spin_until
from msg_adapters import image_to_rgb, keypoints_2d_from_msg, rgb_to_image

ROOT = Path(__file__).resolve().parent.parent
OUTPUTS = {"joint_states": JointState, "pose": PoseStamped, "transform": TransformStamped, "keypoints": PoseArray,
           "keypoints_2d": PointCloud2, "markers": MarkerArray, "annotated": Image}
FRAME_ID = "camera_color_optical_frame"
_DOMAINS = domain_ids(1, 49)  # a block of our own (test_joint_state_monitor: 50..99, test_monitor_launcher: 201..232)


def header_of(msg) -> Header:
    """A message's header; a MarkerArray's is its first marker's."""
    return msg.markers[0].header if isinstance(msg, MarkerArray) else msg.header


def header(sec: int) -> Header:
    return Header(stamp=Time(sec=sec, nanosec=123), frame_id=FRAME_ID)


def camera_info_msg(K: np.ndarray, width: int, height: int, stamp: Header) -> CameraInfo:
    msg = CameraInfo(header=stamp, width=width, height=height)
    msg.k = K.ravel().tolist()
    return msg


class Graph:
    """One context: the estimator node, a probe node publishing inputs and recording every output."""

    def __init__(self, card: Path, **params):
        self.context = Context()
        self.domain_id = next(_DOMAINS)
        rclpy.init(context=self.context, domain_id=self.domain_id)
        overrides = [Parameter("model", value=str(card)), Parameter("min_confidence", value=0.0)]
        self.node = EstimatorNode(context=self.context,
                                  parameter_overrides=overrides + [Parameter(k, value=v) for k, v in params.items()])
        self.probe = rclpy.create_node("probe", context=self.context)
        self.received: dict[str, list] = {name: [] for name in [*OUTPUTS, "diagnostics"]}
        for name, kind in OUTPUTS.items():
            self.probe.create_subscription(kind, f"/holo_pose_estimator/{name}", self.received[name].append, 10)
        self.probe.create_subscription(DiagnosticArray, "/diagnostics", self.received["diagnostics"].append, 10)
        self.image_pub = self.probe.create_publisher(Image, "image", 10)
        self.info_pub = self.probe.create_publisher(CameraInfo, "camera_info", 10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.probe)

    def spin_until(self, predicate, timeout: float = 20.0, image: Image | None = None,
                   info: CameraInfo | None = None) -> bool:
        """Spin until `predicate()`, publishing `info` and `image` (when given) at 10 Hz meanwhile."""
        def publish():
            if info is not None:
                self.info_pub.publish(info)
            if image is not None:
                self.image_pub.publish(image)
        return spin_until(self.executor, predicate, timeout, publish)

    def stamped(self, name: str, sec: int) -> list:
        """Messages received on output `name` whose stamp has seconds `sec`."""
        return [m for m in self.received[name] if header_of(m).stamp.sec == sec]

    def diagnostics(self) -> dict[str, str]:
        """The latest diagnostics of the node, as key -> value (empty before the first)."""
        if not self.received["diagnostics"]:
            return {}
        status = self.received["diagnostics"][-1].status[0]
        return {"level": status.level, "message": status.message, **{kv.key: kv.value for kv in status.values}}

    def close(self) -> None:
        self.node.destroy_node()
        self.probe.destroy_node()
        self.executor.shutdown()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture(scope="module")
def card(small_model_card) -> Path:
    return small_model_card


@pytest.fixture(scope="module")
def frame(tmp_path_factory) -> tuple[np.ndarray, np.ndarray]:
    """A rendered 320x240 Panda frame: (RGB image, K)."""
    folder = tmp_path_factory.mktemp("frames")
    generate("panda", 1, folder, seed=11, workers=1, width=320, height=240, progress=False)
    reader = DreamReader(folder, "panda")
    return reader.load_image(reader[0]), np.array(reader[0].K)


@pytest.fixture
def graphs(card):
    made: list[Graph] = []

    def make(**params) -> Graph:
        made.append(Graph(card, **params))
        return made[-1]

    yield make
    for graph in made:
        graph.close()


def test_outputs_carry_the_image_header_and_match_the_core(graphs, card, frame):
    image, K = frame
    g = graphs()
    stamp = header(1001)
    image_msg, info_msg = rgb_to_image(image, stamp), camera_info_msg(K, 320, 240, stamp)
    everything = lambda: all(g.stamped(name, 1001) for name in OUTPUTS) and g.diagnostics()  # noqa: E731
    assert g.spin_until(everything, image=image_msg, info=info_msg), {k: len(v) for k, v in g.received.items()}

    for name in OUTPUTS:
        assert all(header_of(m) == stamp for m in g.received[name]), name
    assert all(marker.header == stamp for marker in g.received["markers"][0].markers)
    robot = g.node.estimator.robot
    assert g.node.estimator.backend == "onnxruntime"  # config/estimator.yaml's default
    reference = Estimator.from_model(card, "cpu", backend="onnxruntime", min_confidence=0.0).estimate(image, K)
    joints = g.received["joint_states"][0]
    assert list(joints.name) == robot.joint_names
    np.testing.assert_allclose(joints.position, reference.joints, atol=1e-4)
    position = g.received["pose"][0].pose.position
    np.testing.assert_allclose([position.x, position.y, position.z], reference.T_cam_base[:3, 3], atol=1e-4)
    transform = g.received["transform"][0]
    assert transform.child_frame_id == "panda_base_link"
    assert len(g.received["keypoints"][0].poses) == robot.n_keypoints
    uvc = keypoints_2d_from_msg(g.received["keypoints_2d"][0])
    np.testing.assert_allclose(uvc[:, :2], reference.keypoints_2d, atol=0.05)
    annotated = image_to_rgb(g.received["annotated"][0])
    assert annotated.shape == image.shape and (annotated != image).any()  # the skeleton is drawn

    assert g.spin_until(lambda: int(g.diagnostics().get("frames_processed", 0)) >= 1)
    diagnostics = g.diagnostics()
    assert diagnostics["level"] == DiagnosticStatus.OK and diagnostics["errors_image"] == "0", diagnostics
    assert {"rate_hz", "latency_ms", "frames_dropped", "confidence", "robot_not_found"} <= set(diagnostics)
    assert g.node.get_parameter("joint_names").value == robot.joint_names

    # live parameters: a robot that is never confident enough is "not found", and nothing is published for it
    assert not g.node.set_parameters([Parameter("model", value="other")])[0].successful  # read-only
    assert not g.node.set_parameters([Parameter("parts", value="sometimes")])[0].successful  # not a mode
    assert g.node.set_parameters([Parameter("parts", value="true")])[0].successful and g.node.estimator.parts
    assert g.node.set_parameters([Parameter("parts", value="auto")])[0].successful
    assert g.node.estimator.parts == bool((read_card(g.node.model)[1].get("estimator") or {}).get("parts", False))
    assert g.node.set_parameters([Parameter("close_ups", value="true")])[0].successful and g.node.estimator.close_ups
    assert g.node.set_parameters([Parameter("close_ups", value="auto")])[0].successful
    assert g.node.estimator.close_ups == bool((read_card(g.node.model)[1].get("estimator") or {}).get("close_ups", False))
    assert not g.node.set_parameters([Parameter("close_ups", value="often")])[0].successful
    assert g.node.set_parameters([Parameter("static_camera", value=True)])[0].successful
    assert g.node.estimator.static_camera is not None and g.node.estimator.static_camera.prior() is None
    assert g.spin_until(lambda: "static_camera_restarts" in g.diagnostics())
    assert g.node.set_parameters([Parameter("static_camera", value=False)])[0].successful
    assert g.node.estimator.static_camera is None
    assert g.node.set_parameters([Parameter("min_confidence", value=1.0)])[0].successful
    lost = header(1002)
    assert g.spin_until(lambda: g.node.stats.not_found >= 1, image=rgb_to_image(image, lost),
                        info=camera_info_msg(K, 320, 240, lost))
    g.spin_until(lambda: False, timeout=0.5)
    assert not any(g.stamped(name, 1002) for name in OUTPUTS)
    assert g.spin_until(lambda: int(g.diagnostics().get("robot_not_found", 0)) >= 1)


def test_the_localizer_size_parameter_reaches_the_estimator(graphs, card, frame):
    """`localize_size:=32` runs the whole-image pass 2D-only at 32 px (its own ONNX graph); the outputs are the
    core's with the same setting."""
    image, K = frame
    g = graphs(localize_size=32)
    assert g.node.estimator.localize_size == 32 and g.node.estimator.localizer is not None
    stamp = header(3001)
    assert g.spin_until(lambda: g.stamped("joint_states", 3001), image=rgb_to_image(image, stamp),
                        info=camera_info_msg(K, 320, 240, stamp))
    reference = Estimator.from_model(card, "cpu", backend="onnxruntime", min_confidence=0.0,
                                     localize_size=32).estimate(image, K)
    np.testing.assert_allclose(g.stamped("joint_states", 3001)[0].position, reference.joints, atol=1e-4)
    default = graphs().node.estimator  # -1: the card's choice; it names none, so the crop's size
    assert default.localizer is not None and default.localize_size == default.size
    assert graphs(localize_size=0).node.estimator.localizer is None  # the full pass


def raw_image(height: int, width: int, encoding: str, step: int, data: bytes, stamp: Header) -> Image:
    msg = Image(header=stamp, height=height, width=width, encoding=encoding, is_bigendian=0, step=step)
    msg.data = data
    return msg


def test_bad_messages_are_counted_and_survived(graphs, frame):
    image, K = frame
    g = graphs(max_image_pixels=100_000)
    stats, stamp = g.node.stats, header(2001)
    good = rgb_to_image(image, stamp)

    # no CameraInfo yet: frames are skipped, never estimated without intrinsics
    assert g.spin_until(lambda: stats.no_camera_info >= 1, image=good)
    # NaN intrinsics: rejected, and still no intrinsics to estimate with
    nan_info = camera_info_msg(K * np.nan, 320, 240, stamp)
    assert g.spin_until(lambda: stats.errors["camera_info"] >= 1, info=nan_info)
    skipped = stats.no_camera_info
    assert g.spin_until(lambda: stats.no_camera_info > skipped, image=good)
    assert stats.processed == 0

    info = camera_info_msg(K, 320, 240, stamp)
    bad_images = [
        raw_image(240, 320, "yuv422", 640, bytes(640 * 240), stamp),              # unsupported encoding
        raw_image(240, 320, "rgb8", 900, bytes(900 * 240), stamp),                # step shorter than a row
        raw_image(0, 0, "rgb8", 0, b"", stamp),                                   # zero size
        raw_image(240, 320, "rgb8", 960, bytes(1000), stamp),                     # short data
        raw_image(400, 400, "mono8", 400, bytes(400 * 400), stamp),               # over max_image_pixels
    ]
    for number, bad in enumerate(bad_images, start=1):
        assert g.spin_until(lambda: stats.errors["image"] >= number, image=bad, info=info), bad.encoding
    # a well-formed image of another size than the CameraInfo says, then one too small for the estimator
    tiny = raw_image(4, 4, "rgb8", 12, bytes(48), stamp)
    assert g.spin_until(lambda: stats.errors["camera_info"] >= 2, image=tiny, info=info)
    assert g.spin_until(lambda: stats.errors["estimator"] >= 1, image=tiny, info=camera_info_msg(K, 0, 0, stamp))
    assert stats.processed == 0 and not any(g.received[name] for name in OUTPUTS)

    # still running: the next good frame is estimated and published
    assert g.spin_until(lambda: g.stamped("joint_states", 2001), image=good, info=info)
    assert g.spin_until(lambda: int(g.diagnostics().get("errors_image", 0)) >= 5)
    diagnostics = g.diagnostics()
    assert int(diagnostics["errors_camera_info"]) >= 2 and int(diagnostics["errors_estimator"]) >= 1
    assert int(diagnostics["skipped_no_camera_info"]) >= 2 and diagnostics["errors_internal"] == "0"


PUBLISHER = textwrap.dedent("""
    import sys, time
    import numpy as np, rclpy
    from sensor_msgs.msg import CameraInfo, Image

    image, K = np.load(sys.argv[1]), np.load(sys.argv[2])
    rclpy.init(domain_id=int(sys.argv[3]))
    node = rclpy.create_node("external_camera")
    images = node.create_publisher(Image, "image", 10)
    infos = node.create_publisher(CameraInfo, "camera_info", 10)
    msg = Image(height=image.shape[0], width=image.shape[1], encoding="rgb8", step=image.shape[1] * 3)
    msg.data = image.tobytes()
    info = CameraInfo(height=image.shape[0], width=image.shape[1], k=K.ravel().tolist())
    for m in (msg, info):
        m.header.stamp.sec, m.header.frame_id = 4242, "external_camera_optical_frame"
    while rclpy.ok():
        infos.publish(info)
        images.publish(msg)
        time.sleep(0.1)
""")


def test_a_publisher_in_another_process_reaches_the_node(graphs, frame, tmp_path):
    image, K = frame
    np.save(tmp_path / "image.npy", image)
    np.save(tmp_path / "K.npy", K)
    (tmp_path / "publisher.py").write_text(PUBLISHER)
    g = graphs()
    process = subprocess.Popen([sys.executable, str(tmp_path / "publisher.py"), str(tmp_path / "image.npy"),
                                str(tmp_path / "K.npy"), str(g.domain_id)], cwd=ROOT, env=dict(os.environ),
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        arrived = g.spin_until(lambda: g.stamped("joint_states", 4242) or process.poll() is not None, timeout=40)
        assert arrived and process.poll() is None, process.stdout.read().decode() if process.poll() is not None else ""
        msg = g.stamped("joint_states", 4242)[0]
        assert msg.header.frame_id == "external_camera_optical_frame"
        assert list(msg.name) == g.node.estimator.robot.joint_names
    finally:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def test_main_exits_1_with_the_reason_when_the_model_cannot_be_loaded(capfd):
    assert main(["--ros-args", "-p", "model:=no_such_model"]) == 1
    assert "cannot start: no shipped model 'no_such_model'" in capfd.readouterr().err


def test_a_found_frame_without_frame_id_after_a_not_found_one_is_published(graphs, frame):
    """Regression: the 'not found' line (info) and the empty frame_id line (warning) came from one rclpy call
    site, whose severity rclpy refuses to change: every later valid frame without a frame_id was lost."""
    image, K = frame
    g = graphs(min_confidence=1.0)
    lost = header(5001)
    assert g.spin_until(lambda: g.node.stats.not_found >= 1, image=rgb_to_image(image, lost),
                        info=camera_info_msg(K, 320, 240, lost))
    assert g.node.set_parameters([Parameter("min_confidence", value=0.0)])[0].successful
    no_frame = Header(stamp=Time(sec=5002, nanosec=0), frame_id="")
    assert g.spin_until(lambda: g.stamped("joint_states", 5002), image=rgb_to_image(image, no_frame),
                        info=camera_info_msg(K, 320, 240, no_frame))
    assert g.node.stats.errors["internal"] == 0


@pytest.mark.parametrize("pipeline", [True, False])
def test_a_burst_of_frames_is_answered_in_order_each_with_its_own_image(graphs, card, frame, pipeline):
    """Two different images alternate at 100 Hz, faster than the node answers: whatever it drops, what it
    publishes comes in stamp order and is the estimate of the image that carried that stamp, whether the network
    and the fit run as two pipelined stages or on one thread."""
    image, K = frame
    images = [image, np.ascontiguousarray(np.roll(image, (9, -14), axis=(0, 1)))]
    reference = Estimator.from_model(card, "cpu", backend="onnxruntime", min_confidence=0.0)
    expected = [reference.estimate(im, K).joints for im in images]
    assert not np.allclose(expected[0], expected[1], atol=1e-3)  # the two frames are told apart by their answers
    g = graphs(pipeline=pipeline)
    assert g.node.get_parameter("pipeline").value is pipeline
    info = camera_info_msg(K, 320, 240, header(7000))
    assert g.spin_until(lambda: g.node.stats.camera_info_received >= 1, info=info)
    sent = iter(range(7001, 7061))

    def publish_next():
        sec = next(sent, None)
        if sec is not None:
            g.image_pub.publish(rgb_to_image(images[sec % 2], header(sec)))
    spin_until(g.executor, lambda: False, timeout=0.6 + 60 * 0.01, action=publish_next, period=0.01)
    assert g.spin_until(lambda: g.node.stats.received >= 20 and g.node.stats.processed + g.node.stats.dropped
                        >= g.node.stats.received, timeout=20)
    g.spin_until(lambda: False, timeout=0.5)

    stamps = [m.header.stamp.sec for m in g.received["joint_states"]]
    assert len(stamps) >= 3 and stamps == sorted(set(stamps)), stamps
    for msg in g.received["joint_states"]:
        np.testing.assert_allclose(msg.position, expected[msg.header.stamp.sec % 2], atol=1e-4)
    assert [m.header.stamp.sec for m in g.received["pose"]] == stamps
    assert g.spin_until(lambda: "pipeline" in g.diagnostics())
    assert g.diagnostics()["pipeline"] == str(pipeline) and g.node.stats.errors["internal"] == 0
