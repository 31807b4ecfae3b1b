"""ROS 2 node `holo_pose_evaluation`: scores a live estimator against the ground truth the DREAM replay node
publishes, and writes the same report.json as `holo-pose evaluate` when the replay ends.

Run (next to `holo-pose-replay` and the estimator): `ros2 run holo_pose_ros evaluation_node --ros-args
-p report_path:=report.json` (or the console script `holo-pose-live-eval --ros-args ...`).

Inputs (all matched by exact header stamp, by the in-house StampSync below; message_filters is not on PyPI):
  <ground_truth>/{keypoints,keypoints_2d,joint_states,pose}   the replay's ground truth (reliable, transient local)
  <estimator>/{keypoints,keypoints_2d,joint_states,pose}      the estimates (reliable, volatile)
  <done_topic>                                                std_msgs/UInt32: frames sent (transient local)
A frame is known once its ground-truth keypoints and keypoints_2d have arrived; it is answered once all four
estimate messages with its stamp have. It logs each answered frame's ADD and the running ADD AUC.

The report is written when `done` has arrived and every frame sent is known and answered, or `done_grace_s`
after `done` (frames still unanswered then are not found: the estimator publishes nothing for them), or after
`idle_timeout_s` without any message (no `done`). `fps` in the live report is 1 / mean end-to-end latency (ground
truth received -> last estimate message received) of the found frames; the other fields mean what they mean in
`holo-pose evaluate`. The report also goes out as JSON on `~/report` (std_msgs/String, transient local).
"""

from __future__ import annotations

import json
import sys
import time
from collections import OrderedDict

import numpy as np
from geometry_msgs.msg import PoseArray, PoseStamped
from rcl_interfaces.msg import FloatingPointRange
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState, PointCloud2
from std_msgs.msg import String, UInt32

from holo_pose_ros.nodes.parameters import ParameterSpecs, declare_parameters
from holo_pose_ros.nodes.runner import run_node
from holo_pose_ros.bags import estimate_from_messages, ground_truth_from_messages
from msg_adapters import stamp_ns

NODE_NAME = "holo_pose_evaluation"
TOPIC_TYPES = {"keypoints": PoseArray, "keypoints_2d": PointCloud2, "joint_states": JointState, "pose": PoseStamped}
GROUND_TRUTH_REQUIRED = ("gt/keypoints", "gt/keypoints_2d")
ESTIMATE_REQUIRED = tuple(f"est/{name}" for name in TOPIC_TYPES)
GROUND_TRUTH_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                              history=HistoryPolicy.KEEP_LAST, depth=100)
ESTIMATE_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
                          history=HistoryPolicy.KEEP_LAST, depth=100)
LATCHED = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                     history=HistoryPolicy.KEEP_LAST, depth=1)

_SECONDS = dict(floating_point_range=[FloatingPointRange(from_value=0.0, to_value=1e6)])
# name -> (description, read_only, ranges); defaults live in config/evaluation.yaml only
PARAMETERS: ParameterSpecs = {
    "robot": ("Robot YAML name or path: joint and keypoint names and order of the report.", True, {}),
    "estimator": ("Namespace of the estimate topics (the estimator node's full name).", True, {}),
    "ground_truth": ("Namespace of the ground-truth topics (the replay's ~/ground_truth).", True, {}),
    "done_topic": ("std_msgs/UInt32 published by the replay when every frame was sent.", True, {}),
    "report_path": ("Where to write report.json ('' : do not write, only publish).", True, {}),
    "done_grace_s": ("Seconds after done to wait for answers still in flight; then unanswered = not found.",
                     True, _SECONDS),
    "idle_timeout_s": ("Write the report after this many seconds without any message when no done came "
                       "(0: never).", True, _SECONDS),
    "max_pending": ("Frames kept in the synchronizer; the oldest are dropped beyond this.", True, {}),
    "exit_when_done": ("main(): exit once the report is written.", True, {}),
}


class StampSync:
    """Messages of several slots grouped by exact header stamp, oldest first. Bounded: beyond `max_groups`
    stamps, the oldest group is dropped (counted in `evicted`)."""

    def __init__(self, max_groups: int = 10000):
        self.groups: OrderedDict[int, dict] = OrderedDict()
        self.max_groups, self.evicted = max_groups, 0

    def add(self, slot: str, msg, now: float) -> tuple[int, dict]:
        """File `msg` under its stamp; returns (stamp, group). A group maps slots to messages, plus '_first'
        (arrival time of its first message) and '_last' (of its latest)."""
        stamp = stamp_ns(msg.header.stamp)
        group = self.groups.get(stamp)
        if group is None:
            group = self.groups[stamp] = {"_first": now}
            while len(self.groups) > self.max_groups:
                self.groups.popitem(last=False)
                self.evicted += 1
        group[slot] = msg
        group["_last"] = now
        return stamp, group

    @staticmethod
    def complete(group: dict, slots: tuple[str, ...]) -> bool:
        return all(slot in group for slot in slots)


class EvaluationNode(Node):
    """Scores the estimator against the replay's ground truth; see the module docstring."""

    def __init__(self, **node_kwargs):
        super().__init__(NODE_NAME, **node_kwargs)
        p = declare_parameters(self, "evaluation.yaml", PARAMETERS)
        from holo_pose_ros.robots.kinematics import RobotModel

        self.robot = RobotModel(p["robot"])
        self.report_path, self.exit_when_done = p["report_path"], p["exit_when_done"]
        self.done_grace_s, self.idle_timeout_s = p["done_grace_s"], p["idle_timeout_s"]
        self.sync = StampSync(p["max_pending"])
        self.report: dict | None = None
        self.results: list = []  # FrameResult per known frame, in stamp order (after the report)
        self.finished = False
        self._done: tuple[int, float] | None = None  # (frames sent, arrival time)
        self._last_message = None
        self._adds: list[float] = []  # ADD (m) of the answered frames, for the running log
        for name, cls in TOPIC_TYPES.items():
            self.create_subscription(cls, f"{p['ground_truth'].rstrip('/')}/{name}",
                                     lambda msg, slot=f"gt/{name}": self._on_message(slot, msg), GROUND_TRUTH_QOS)
            self.create_subscription(cls, f"{p['estimator'].rstrip('/')}/{name}",
                                     lambda msg, slot=f"est/{name}": self._on_message(slot, msg), ESTIMATE_QOS)
        self.create_subscription(UInt32, p["done_topic"], self._on_done, LATCHED)
        self._report_pub = self.create_publisher(String, "~/report", LATCHED)
        self._timer = self.create_timer(0.1, self._tick)
        self.get_logger().info(f"scoring {p['estimator']} against {p['ground_truth']} ({self.robot.name}); report "
                               f"when {p['done_topic']} arrives")

    # -- callbacks -----------------------------------------------------------------------------------------------
    def _on_message(self, slot: str, msg) -> None:
        if self.finished:
            return
        now = time.monotonic()
        self._last_message = now
        stamp, group = self.sync.add(slot, msg, now)
        if "_answered_at" not in group and StampSync.complete(group, ESTIMATE_REQUIRED):
            group["_answered_at"] = now
        if "_logged" not in group and "_answered_at" in group and StampSync.complete(group, GROUND_TRUTH_REQUIRED):
            group["_logged"] = True
            self._log_frame(stamp, group)
        if self._done is not None:
            self._maybe_finish(now)

    def _on_done(self, msg: UInt32) -> None:
        if self._done is None:
            self._done = (int(msg.data), time.monotonic())
            self.get_logger().info(f"replay done: {msg.data} frames sent")

    def _tick(self) -> None:
        if self.finished:
            return
        now = time.monotonic()
        if self._done is not None:
            self._maybe_finish(now)
        elif (self.idle_timeout_s > 0 and self._last_message is not None
              and now - self._last_message > self.idle_timeout_s):
            self.get_logger().warning(f"no done and no message for {self.idle_timeout_s:g} s: writing the report")
            self._finish()

    def _maybe_finish(self, now: float) -> None:
        n_sent, done_at = self._done
        known = [g for g in self.sync.groups.values() if StampSync.complete(g, GROUND_TRUTH_REQUIRED)]
        if (len(known) >= n_sent and all("_answered_at" in g for g in known)) or now - done_at >= self.done_grace_s:
            self._finish()

    # -- scoring ---------------------------------------------------------------------------------------------------
    def _truth(self, stamp: int, group: dict):
        return ground_truth_from_messages(str(stamp), group["gt/keypoints"], group["gt/keypoints_2d"],
                                          group.get("gt/joint_states"), group.get("gt/pose"), self.robot.joint_names,
                                          self.robot.keypoint_names)

    def _estimate(self, group: dict):
        return estimate_from_messages(group["est/keypoints"], group["est/keypoints_2d"], group["est/joint_states"],
                                      group["est/pose"], self.robot.joint_names, self.robot.keypoint_names)

    def _log_frame(self, stamp: int, group: dict) -> None:
        """Log the ADD of a newly answered frame and the running ADD AUC over the answered frames."""
        from holo_pose_ros.evaluation import metrics

        try:
            add = float(metrics.add_per_frame(self._estimate(group).keypoints_3d[None],
                                              self._truth(stamp, group).keypoints_3d[None])[0])
        except ValueError as e:
            self.get_logger().warning(f"frame {stamp}: {e}")
            return
        self._adds.append(add)
        adds = np.array(self._adds)
        self.get_logger().info(f"frame {stamp * 1e-9:.3f} s: ADD {add * 1e3:.1f} mm; {len(adds)} answered, ADD AUC "
                               f"{metrics.add_auc(adds):.2f}, mean ADD {adds.mean() * 1e3:.1f} mm")

    def _results(self) -> list:
        """FrameResults of every known frame (stamp order); unanswered frames are not found."""
        from holo_pose_ros.estimator import Estimate
        from holo_pose_ros.evaluation.run import frame_result

        robot, results, partial = self.robot, [], 0
        for stamp, group in sorted(self.sync.groups.items()):
            if not StampSync.complete(group, GROUND_TRUTH_REQUIRED):
                continue
            truth, estimate, seconds = self._truth(stamp, group), None, 0.0
            if "_answered_at" in group:
                try:
                    estimate = self._estimate(group)
                    seconds = group["_answered_at"] - group["_first"]
                except ValueError as e:
                    self.get_logger().warning(f"frame {stamp}: unusable estimate ({e}): not found")
            elif any(slot.startswith("est/") for slot in group):
                partial += 1
            if estimate is None:
                estimate = Estimate(False, 0.0, joint_names=robot.joint_names, keypoint_names=robot.keypoint_names)
            results.append(frame_result(truth, estimate, seconds, robot))
        if partial:
            self.get_logger().warning(f"{partial} frame(s) got only some of the estimate messages: not found")
        return results

    def _finish(self) -> None:
        from holo_pose_ros.evaluation.report import build_report, format_report, write_report

        self.finished = True
        self._timer.cancel()
        self.results = self._results()
        n_sent = self._done[0] if self._done else None
        if n_sent is not None and len(self.results) != n_sent:
            self.get_logger().warning(f"{n_sent} frames sent but ground truth for {len(self.results)} received")
        if self.sync.evicted:
            self.get_logger().warning(f"{self.sync.evicted} frame(s) dropped from the synchronizer (max_pending)")
        if not self.results:
            self.get_logger().error("no ground truth received: no report")
            return
        self.report = build_report(self.results, self.robot.spec.joint_names, self.robot.joint_types,
                                   self.robot.spec.keypoint_names, self.robot.spec.joint_symmetry)
        if self.report_path:
            write_report(self.report, self.report_path)
        self._report_pub.publish(String(data=json.dumps(self.report)))
        self.get_logger().info("\n" + format_report(self.report)
                               + (f"\nreport: {self.report_path}" if self.report_path else ""))


def main(args: list[str] | None = None) -> int:
    """Console-script entry point: evaluate until the report is written (exit_when_done) or Ctrl-C."""
    return run_node(EvaluationNode, NODE_NAME, args, done=lambda node: node.finished and node.exit_when_done,
                    exit_code=lambda node: 0 if node.report is not None or not node.finished else 1)


if __name__ == "__main__":
    sys.exit(main())
