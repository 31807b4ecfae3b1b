"""ROS 2 node `joint_state_monitor`: compares the estimator's joint states with the joints the robot reports, by
stamp, and says on /diagnostics when they disagree, per joint, with thresholds from the loaded model's card. Thin:
msg_adapters convert the messages, holo_pose_ros.monitoring does the work (matching, windows, alarms, status).

Run: `ros2 run holo_pose_ros joint_state_monitor_node --ros-args -p robot:=panda -p model:=panda
-r joint_states:=/panda/joint_states` (defaults and their meaning: config/joint_state_monitor.yaml).

In:  `estimate_topic` (sensor_msgs/JointState, the estimator's ~/joint_states, stamped with the image),
     `reported_topic` (sensor_msgs/JointState, the robot's own names; optional). Best effort, so that reliable and
     best-effort publishers both connect.
Out: ~/discrepancy             sensor_msgs/JointState: position = estimate - reported per joint (radians wrapped to
                               (-pi, pi], or to half the period of a joint that looks the same after part of a turn:
                               the robot YAML's joint_symmetry_deg, e.g. the Panda hand's roll, (-pi/2, pi/2];
                               metres for prismatic joints; NaN where either side has no position), the
                               robot's joint names, the image's header; one per matched estimate;
     ~/joint_states_estimated  sensor_msgs/JointState: the estimate with the robot's joint names and the image's
                               header, so that a robot that shares nothing can be used like a joint_state_publisher;
     /diagnostics              one DiagnosticStatus a second, "<node>: <robot_id> joint states": OK / WARN / ERROR,
                               the joints at fault, "robot not reporting", "robot not seen", and counters."""

from __future__ import annotations

import math
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import FloatingPointRange, IntegerRange
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from holo_pose_ros.monitoring import JointNameMap, JointStateMonitor, node_thresholds
from holo_pose_ros.model.cards import read_card
from holo_pose_ros.nodes.parameters import ParameterSpecs, declare_parameters
from holo_pose_ros.nodes.runner import run_node
from holo_pose_ros.robots.spec import load_robot_spec
from msg_adapters import joint_state_arrays, joint_state_from_arrays, to_diagnostic_status

NODE_NAME = "joint_state_monitor"
POLL_PERIOD_S = 0.1  # how often estimates waiting for a reported state are looked at


def _input_qos(depth: int) -> QoSProfile:
    return QoSProfile(reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE,
                      history=HistoryPolicy.KEEP_LAST, depth=depth)


def _range(low: float, high: float = 1e9) -> dict:
    return dict(floating_point_range=[FloatingPointRange(from_value=low, to_value=high)])


_COUNT = dict(integer_range=[IntegerRange(from_value=1, to_value=100_000)])
# name -> (description, read_only, ranges); defaults (and longer explanations) live in config/joint_state_monitor.yaml
PARAMETERS: ParameterSpecs = {
    "robot": ("Robot YAML name or path: the estimator's joint names, and their kinds from its URDF.", True, {}),
    "robot_id": ("Names this robot in /diagnostics (status name, hardware_id); empty: the robot YAML's name.", True,
                 {}),
    "model": ("The loaded model (shipped name, card or weights path) whose card's held-out per-joint errors set the "
              "thresholds; empty: defaults and overrides only.", True, {}),
    "card_test_set": ("The card's test set the errors come from; empty: per joint the largest over all.", True, {}),
    "estimate_topic": ("The estimator's sensor_msgs/JointState (its ~/joint_states).", True, {}),
    "reported_topic": ("The robot's own sensor_msgs/JointState; empty: none (relay only, no comparison).", True, {}),
    "joint_name_prefix": ("The robot's name of joint J is this prefix + J, unless joint_name_map names it.", True, {}),
    "joint_name_map": ("'estimator_name=robot_name, ...': the robot's names of joints that are not prefix + name.",
                       True, {}),
    "threshold_factor": ("WARN threshold = this x the card's held-out mean error of the joint.", True, _range(1e-6)),
    "error_factor": ("ERROR threshold = this x the WARN threshold.", True, _range(1.0)),
    "threshold_overrides": ("'joint=value, ...': explicit WARN thresholds (estimator joint names; rad, or m).", True,
                            {}),
    "default_threshold_rad": ("WARN threshold (rad) of a revolute joint the card does not measure.", True,
                              _range(1e-9)),
    "default_threshold_m": ("WARN threshold (m) of a prismatic joint the card does not measure.", True, _range(1e-9)),
    "persistence": ("Consecutive frames that raise or clear a joint's alarm (one bad frame raises nothing).", True,
                    _COUNT),
    "window": ("Frames per joint behind the diagnostics' mean_abs and max_abs.", True, _COUNT),
    "match_tolerance_s": ("An estimate matches the reported state nearest its image stamp within this (s).", True,
                          _range(0.0, 60.0)),
    "match_wait_s": ("An estimate waits this long (s) for a reported state stamped at or after its own.", True,
                     _range(0.0, 60.0)),
    "reported_history_s": ("Reported states kept this long (s) behind the newest (covers the estimator's latency).",
                           True, _range(1e-3, 3600.0)),
    "report_timeout_s": ("No reported state for this long (s): 'robot not reporting'.", True, _range(1e-3)),
    "estimate_timeout_s": ("No estimate for this long (s): 'robot not seen'.", True, _range(1e-3)),
}


class JointStateMonitorNode(Node):
    """Compares estimated and reported joint states; see the module docstring."""

    def __init__(self, **node_kwargs):
        super().__init__(NODE_NAME, **node_kwargs)
        p = declare_parameters(self, "joint_state_monitor.yaml", PARAMETERS)
        spec = load_robot_spec(p["robot"])
        self.robot_id = p["robot_id"] or spec.name
        names_map = JointNameMap.parse(p["joint_name_map"], p["joint_name_prefix"])
        robot_names = names_map.robot_names(spec.joint_names)
        card, self.card_path = None, None
        if p["model"]:
            self.card_path, card = read_card(p["model"])
            if card.get("robot") != spec.name:
                raise ValueError(f"model '{p['model']}' is for robot '{card.get('robot')}', but robot:={p['robot']}")
        self.thresholds = node_thresholds(spec, card, p)
        self.reported_topic = p["reported_topic"]
        self.monitor = JointStateMonitor(
            self.thresholds, robot_names, persistence=p["persistence"], window=p["window"],
            match_tolerance_s=p["match_tolerance_s"], match_wait_s=p["match_wait_s"],
            history_s=p["reported_history_s"], report_timeout_s=p["report_timeout_s"],
            estimate_timeout_s=p["estimate_timeout_s"], expect_reported=bool(self.reported_topic),
            now=time.monotonic())

        self._discrepancy_pub = self.create_publisher(JointState, "~/discrepancy", 10)
        self._relay_pub = self.create_publisher(JointState, "~/joint_states_estimated", 10)
        self._diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._estimate_sub = self.create_subscription(JointState, p["estimate_topic"], self._on_estimate,
                                                      _input_qos(10))
        self._reported_sub = None
        if self.reported_topic:
            self._reported_sub = self.create_subscription(JointState, self.reported_topic, self._on_reported,
                                                          _input_qos(100))
        self.create_timer(POLL_PERIOD_S, self._poll)
        self.create_timer(1.0, self._publish_diagnostics)
        self._log_thresholds()

    def _log_thresholds(self) -> None:
        rows = [f"{t.name} -> {name}: warn {t.warn:.3f} error {t.error:.3f} {t.unit} ({t.source})"
                + (f", compared modulo {math.degrees(t.period):g} deg (it looks the same after that turn)"
                   if t.symmetric else "")
                for t, name in zip(self.thresholds, self.monitor.robot_names)]
        source = f"reported on {self._reported_sub.topic_name}" if self._reported_sub else "no reported joint states"
        self.get_logger().info(f"robot '{self.robot_id}': estimate on {self._estimate_sub.topic_name}, {source}; "
                               f"card {self.card_path or 'none'}; thresholds:\n  " + "\n  ".join(rows))
        blind = [t.name for t in self.thresholds if not t.can_warn]
        if blind:
            self.get_logger().warning(
                f"{', '.join(blind)}: WARN threshold >= half the joint's period (pi; half a symmetric joint's), no "
                "wrapped discrepancy can reach it: the model's error on these joints is too large to tell a fault "
                "from it (set threshold_overrides to watch them anyway)")

    # -- callbacks ---------------------------------------------------------------------------------------------
    def _on_estimate(self, msg: JointState) -> None:
        names, positions, stamp = joint_state_arrays(msg)
        update = self.monitor.add_estimate(names, positions, stamp, time.monotonic(), tag=msg.header)
        if update.robot_names:
            self._relay_pub.publish(joint_state_from_arrays(update.robot_names, update.positions, msg.header))
        self._publish_discrepancies(update.discrepancies)

    def _on_reported(self, msg: JointState) -> None:
        names, positions, stamp = joint_state_arrays(msg)
        self._publish_discrepancies(self.monitor.add_reported(names, positions, stamp, time.monotonic()))

    def _poll(self) -> None:
        self._publish_discrepancies(self.monitor.poll(time.monotonic()))

    def _publish_discrepancies(self, discrepancies) -> None:
        for d in discrepancies:
            self._discrepancy_pub.publish(joint_state_from_arrays(self.monitor.robot_names, d.values, d.tag))

    def _publish_diagnostics(self) -> None:
        status = self.monitor.status(time.monotonic())
        values = {**status.values, "robot": self.robot_id, "card": str(self.card_path or ""),
                  "estimate_topic": self._estimate_sub.topic_name,
                  "reported_topic": self._reported_sub.topic_name if self._reported_sub else ""}
        array = DiagnosticArray(status=[to_diagnostic_status(status.level, f"{self.get_name()}: {self.robot_id} "
                                                             "joint states", status.message, self.robot_id, values)])
        array.header.stamp = self.get_clock().now().to_msg()  # about the node, not about a frame
        self._diagnostics.publish(array)


def main(args: list[str] | None = None) -> int:
    """Console-script entry point: run the node until Ctrl-C; 1 when it cannot start (bad robot, model, map...)."""
    return run_node(JointStateMonitorNode, NODE_NAME, args)


if __name__ == "__main__":
    sys.exit(main())
