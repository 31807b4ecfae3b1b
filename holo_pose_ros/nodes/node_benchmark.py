"""The node-level speed figure: the estimator node runs as its own process (as `ros2 run` starts it); a probe node
here publishes CameraInfo + Image at a camera's rate and times each image from `publish()` to the arrival of the
JointState carrying its stamp. Frames the node drops (it always takes the newest) are counted, not timed."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, JointState
from std_msgs.msg import Header

from holo_pose_ros.bags import ESTIMATOR_NS
from holo_pose_ros.benchmark import stream_frames
from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.nodes.processes import private_graph_env, start_node, stop_nodes
from msg_adapters import camera_info_from_K, rgb_to_image, stamp_ns


class LatencyProbe(Node):
    """Publishes the pool of frames on a timer with unique stamps; records publish and answer times (monotonic s)."""

    def __init__(self, frames: list[tuple[np.ndarray, np.ndarray]], hold: int = 1, frame_id: str = "camera"):
        super().__init__("holo_pose_latency_probe")
        self.pool, self.hold = frames, hold
        self.frame_id = frame_id
        self.image_pub = self.create_publisher(Image, "image", 10)
        self.info_pub = self.create_publisher(CameraInfo, "camera_info", 10)
        self.create_subscription(JointState, f"{ESTIMATOR_NS}/joint_states", self._on_answer, 10)
        self.sent: dict[int, float] = {}
        self.answered: dict[int, float] = {}
        self.count = 0

    def send(self) -> int:
        """Publish the next frame (stamp = count + 1 seconds); returns its stamp in nanoseconds."""
        image, K = self.pool[(self.count // self.hold) % len(self.pool)]
        self.count += 1
        header = Header(stamp=Time(sec=self.count), frame_id=self.frame_id)
        info = camera_info_from_K(K, image.shape[1], image.shape[0], header)
        msg = rgb_to_image(image, header)
        self.info_pub.publish(info)
        key = stamp_ns(header.stamp)
        self.sent[key] = time.monotonic()
        self.image_pub.publish(msg)
        return key

    def _on_answer(self, msg: JointState) -> None:
        self.answered.setdefault(stamp_ns(msg.header.stamp), time.monotonic())


def node_latency(model: str, data: str | Path, frames: int = 100, rate_hz: float = 30.0, backend: str = "onnxruntime",
                 tracking: bool = False, threads: int = 0, startup_timeout_s: float = 300.0, pipeline: bool = True) -> dict:
    """Run the estimator node on `model` and time `frames` images published at `rate_hz` (after a warm-up);
    `pipeline` is the node's parameter (network and fit on two threads, or one)."""
    from holo_pose_ros.model.cards import read_card

    robot = read_card(model)[1]["robot"]  # the node loads the weights; here only the robot's name is needed
    reader = DreamReader(data, robot)
    chosen, hold = stream_frames(reader, frames + 30, tracking, cap=20)  # 30: more than the warm-up takes
    pool = [(reader.load_image(f), f.K) for f in chosen]
    env = private_graph_env(base_domain=60)
    log = Path(tempfile.mkdtemp(prefix="holo_pose_node_bench_")) / "estimator.log"
    params = {"robot": robot, "model": str(model), "backend": backend, "threads": threads, "tracking": tracking,
              "pipeline": pipeline, "min_confidence": 0.0, "publish_annotated": False, "publish_tf": False}
    process = start_node("estimator_node", params, log, env)
    rclpy.init()
    probe = LatencyProbe(pool, hold=hold)
    try:
        # warm-up: one frame at a time until the node answers (it loads the model, maybe exports it), then 5 more
        deadline, warm = time.monotonic() + startup_timeout_s, 0
        while warm < 6:
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the estimator node did not answer; its log: {log}\n{log.read_text()[-2000:]}")
            key = probe.send()
            t_end = time.monotonic() + 2.0
            while key not in probe.answered and time.monotonic() < t_end:
                rclpy.spin_once(probe, timeout_sec=0.01)
            warm += key in probe.answered
        probe.sent.clear()
        probe.answered.clear()
        period, start = 1.0 / rate_hz, time.monotonic()
        for i in range(frames):
            while time.monotonic() < start + i * period:
                rclpy.spin_once(probe, timeout_sec=max(0.0, min(0.005, start + i * period - time.monotonic())))
            probe.send()
        sending_s = time.monotonic() - start
        t_end = time.monotonic() + 2.0
        while len(probe.answered) < len(probe.sent) and time.monotonic() < t_end:
            rclpy.spin_once(probe, timeout_sec=0.01)
    finally:
        probe.destroy_node()
        rclpy.try_shutdown()
        stop_nodes([process])
    latencies = np.array([(probe.answered[k] - probe.sent[k]) * 1e3 for k in probe.answered if k in probe.sent])
    if latencies.size == 0:
        raise RuntimeError(f"no frame was answered during the timed run; estimator log: {log}")
    return {"rate_hz": rate_hz, "sent": len(probe.sent), "answered": int(latencies.size),
            "dropped": len(probe.sent) - int(latencies.size), "fps": latencies.size / sending_s,
            "latency_ms_p50": float(np.percentile(latencies, 50)), "latency_ms_p95": float(np.percentile(latencies, 95)),
            "latency_ms_max": float(latencies.max()), "backend": backend, "tracking": tracking, "pipeline": pipeline}


def format_node_latency(result: dict) -> str:
    return (f"node (image published -> JointState received, {result['backend']}, "
            f"{'tracking' if result['tracking'] else 'localize + crop'}, "
            f"{'pipelined' if result.get('pipeline', True) else 'one thread'}): {result['sent']} images at "
            f"{result['rate_hz']:.0f} Hz, {result['answered']} answered ({result['fps']:.1f} frames/s), "
            f"{result['dropped']} dropped; latency p50 {result['latency_ms_p50']:.1f} / p95 "
            f"{result['latency_ms_p95']:.1f} / max {result['latency_ms_max']:.1f} ms")
