"""The main job (`make demo`, console script `holo-pose-demo`): a real ROS 2 graph of separate processes on a
small generated sample. The DREAM replay node publishes Image + CameraInfo in lockstep, the estimator node
(shipped weights) answers, the evaluation node scores it live, and the joint-state monitor compares the estimate
with the replay's ground-truth joints standing in for the robot's reported ones; this process watches the graph,
prints each frame's result, saves the annotated frames, and ends with the summary (ADD/AUC, frames per second,
latency) and the monitor's status line."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import Image, JointState

from holo_pose_ros.bags import ESTIMATOR_NS, GROUND_TRUTH_NS
from holo_pose_ros.nodes.processes import private_graph_env, start_node, stop_nodes
from msg_adapters import image_to_rgb, stamp_ns


MONITOR_NAME = "joint_state_monitor"
LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}


class Watcher(Node):
    """Prints every estimate, saves the annotated images, and collects the estimator's latency diagnostics."""

    def __init__(self, annotated_dir: Path):
        super().__init__("holo_pose_demo_watcher")
        self.annotated_dir, self.arrivals, self.latency_ms, self.inference_ms = annotated_dir, [], [], []
        annotated_dir.mkdir(parents=True, exist_ok=True)
        self.create_subscription(JointState, f"{ESTIMATOR_NS}/joint_states", self._on_joints, 10)
        self.create_subscription(Image, f"{ESTIMATOR_NS}/annotated", self._on_annotated, 10)
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)
        self.monitor_status: tuple[int, str] | None = None  # the joint-state monitor's last (level, message)
        self.monitor_levels: list[int] = []
        self.discrepancies: list[np.ndarray] = []  # the monitor's estimate - reported, per frame
        self.create_subscription(JointState, f"/{MONITOR_NAME}/discrepancy",
                                 lambda m: self.discrepancies.append(np.asarray(m.position, float)), 10)

    def _on_joints(self, msg: JointState) -> None:
        self.arrivals.append(time.monotonic())
        degrees = " ".join(f"{np.degrees(p):7.1f}" for p in msg.position[:7])
        print(f"frame at {stamp_ns(msg.header.stamp) * 1e-9:6.2f} s: joints (deg) {degrees}", flush=True)

    def _on_annotated(self, msg: Image) -> None:
        path = self.annotated_dir / f"{stamp_ns(msg.header.stamp):019d}.png"
        cv2.imwrite(str(path), cv2.cvtColor(np.ascontiguousarray(image_to_rgb(msg)), cv2.COLOR_RGB2BGR))

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if status.name.startswith(MONITOR_NAME):
                self.monitor_status = (int.from_bytes(status.level, "little") if isinstance(status.level, bytes)
                                       else int(status.level), status.message)
                self.monitor_levels.append(self.monitor_status[0])
                continue
            if "latency_ms" in values and values["latency_ms"] != "nan" and float(values.get("rate_hz", 0)) > 0:
                self.latency_ms.append(float(values["latency_ms"]))
                self.inference_ms.append(float(values["inference_ms"]))


def run_demo(model: str, robot: str, frames: int, out: Path, seed: int, timeout_s: float) -> int:
    """Generate the sample (if needed), run the graph until the evaluation node reports, print the summary."""
    from holo_pose_ros.data.generator import generate

    data, logs = out / "data", out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    if not (data / f"{frames - 1:06d}.json").exists():
        generate(robot, frames, data, seed=seed, progress=True)
    env = private_graph_env()
    report_path = out / "report.json"
    report_path.unlink(missing_ok=True)
    processes = {
        "estimator": start_node("estimator_node", {"robot": robot, "model": model}, logs / "estimator.log", env),
        "evaluation": start_node("evaluation_node", {"robot": robot, "report_path": str(report_path.resolve())},
                                 logs / "evaluation.log", env),
        # the replay's ground-truth joints play the robot's reported joint states
        "monitor": start_node("joint_state_monitor_node", {"robot": robot, "model": model,
                                                           "reported_topic": f"{GROUND_TRUTH_NS}/joint_states"},
                              logs / "monitor.log", env),
    }
    rclpy.init()
    watcher = Watcher(out / "annotated")
    # Frames start only once the estimator and this watcher see each other: ~/annotated is published only while
    # someone subscribes, so a watcher discovered late would miss the first frames.
    deadline = time.monotonic() + min(timeout_s, 120.0)
    while watcher.count_publishers(f"{ESTIMATOR_NS}/annotated") == 0 and time.monotonic() < deadline \
            and processes["estimator"].poll() is None:
        rclpy.spin_once(watcher, timeout_sec=0.1)
    # ... and the evaluation and monitor nodes subscribe to the estimate (the monitor would miss a short sample)
    while watcher.count_subscribers(f"{ESTIMATOR_NS}/joint_states") < 3 and time.monotonic() < deadline:
        rclpy.spin_once(watcher, timeout_sec=0.1)
    for _ in range(10):  # discovery is not instantaneous in both directions
        rclpy.spin_once(watcher, timeout_sec=0.1)
    processes["replay"] = start_node("dream_replay_node", {"folder": str(data.resolve()), "robot": robot,
                                                          "lockstep": True, "exit_when_done": True,
                                                          "lockstep_timeout_s": 60.0}, logs / "replay.log", env)
    print(f"ROS 2 graph up (domain {env['ROS_DOMAIN_ID']}): replay -> estimator -> evaluation; logs in {logs}")
    start, code = time.monotonic(), 0
    try:
        while processes["evaluation"].poll() is None:
            rclpy.spin_once(watcher, timeout_sec=0.1)
            if time.monotonic() - start > timeout_s:
                print(f"demo: no report after {timeout_s:.0f} s", file=sys.stderr)
                code = 1
                break
            for name in ("estimator", "replay", "monitor"):
                if processes[name].poll() not in (None, 0):
                    print(f"demo: the {name} node stopped; see {logs / (name + '.log')}", file=sys.stderr)
                    code = 1
            if code:
                break
    finally:
        watcher.destroy_node()
        rclpy.try_shutdown()
        stop_nodes(processes)
    if code or not report_path.exists():
        print((logs / "evaluation.log").read_text()[-2000:], file=sys.stderr)
        return code or 1
    report = json.loads(report_path.read_text())
    print((logs / "evaluation.log").read_text().split("\n", 1)[-1][-4000:])
    lat = np.array(watcher.latency_ms) if watcher.latency_ms else np.array([np.nan])
    inf = np.array(watcher.inference_ms) if watcher.inference_ms else np.array([np.nan])
    t = watcher.arrivals
    throughput = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else float("nan")
    print(f"summary: {report['n_frames']} frames, {report['n_frames'] - report['n_not_found']} found, "
          f"ADD AUC {report['add_auc']:.1f}, mean ADD {report['add_mean_mm'] or float('nan'):.1f} mm; "
          f"estimator inference {np.nanmedian(inf):.0f} ms, latency (image received -> published) median "
          f"{np.nanmedian(lat):.0f} ms; lockstep throughput {throughput:.1f} frames/s")
    if watcher.monitor_status is not None:
        level, message = watcher.monitor_status
        compared = ""
        if watcher.discrepancies:
            median = np.degrees(np.nanmedian(np.abs(np.stack(watcher.discrepancies)), axis=0))
            compared = (f"{len(watcher.discrepancies)} frames compared, median |estimate - reported| (deg) "
                        + " ".join(f"{v:.0f}" for v in median[:7]) + "; ")
        print(f"monitor (estimate vs the ground-truth joints as the robot's report): {compared}last status "
              f"{LEVELS.get(level, level)}: {message}")
    else:
        print("monitor: no status received", file=sys.stderr)
    print(f"annotated frames: {out / 'annotated'}; report: {report_path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="holo-pose-demo", description=__doc__)
    parser.add_argument("--model", default="panda", help="shipped model name or model card path")
    parser.add_argument("--robot", default="panda", help="robot of the model")
    parser.add_argument("--frames", type=int, default=12, help="frames to generate and replay")
    parser.add_argument("--out", default="out/demo", help="output folder")
    parser.add_argument("--seed", type=int, default=7, help="generator seed of the sample")
    parser.add_argument("--timeout", type=float, default=600.0, help="give up after this many seconds")
    args = parser.parse_args(argv)
    return run_demo(args.model, args.robot, args.frames, Path(args.out), args.seed, args.timeout)


if __name__ == "__main__":
    sys.exit(main())
