"""Joint-state monitoring, no ROS: the estimate compared with what the robot reports. Joints by name (joints.py),
matching by stamp (stamps.py), per-joint windows and debounced alarms (discrepancy.py), thresholds from the model
card (thresholds.py) and the monitor that ties them together (monitor.py); nodes/joint_state_monitor_node.py is
its thin ROS 2 node."""

from holo_pose_ros.monitoring.discrepancy import ERROR, LEVEL_NAMES, OK, WARN, JointWatch, frame_level
from holo_pose_ros.monitoring.joints import (JointNameMap, Selection, joint_difference, parse_pairs, select_by_name,
                                             wrap_angle, wrap_to_period)
from holo_pose_ros.monitoring.monitor import Counters, Discrepancy, EstimateUpdate, JointStateMonitor, Status
from holo_pose_ros.monitoring.stamps import Match, StampBuffer, StampMatcher
from holo_pose_ros.monitoring.thresholds import (JointThreshold, MeasuredError, card_joint_errors, joint_kinds,
                                                 joint_thresholds, node_thresholds, parse_overrides)

__all__ = [
    "ERROR", "LEVEL_NAMES", "OK", "WARN", "JointWatch", "frame_level",
    "JointNameMap", "Selection", "joint_difference", "parse_pairs", "select_by_name", "wrap_angle",
    "wrap_to_period",
    "Counters", "Discrepancy", "EstimateUpdate", "JointStateMonitor", "Status",
    "Match", "StampBuffer", "StampMatcher",
    "JointThreshold", "MeasuredError", "card_joint_errors", "joint_kinds", "joint_thresholds", "node_thresholds",
    "parse_overrides",
]
