"""sensor_msgs/JointState <-> (names, positions, stamp) and the monitor's status -> diagnostic_msgs/DiagnosticStatus.
Name matching and mapping (any order, extra joints ignored, missing ones reported) is the ROS-free
holo_pose_ros.monitoring.joints; `joint_positions_by_name` applies it to a message. Radians (metres for prismatic
joints), stamps in nanoseconds."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from sensor_msgs.msg import JointState

from holo_pose_ros.monitoring.joints import JointNameMap, Selection, select_by_name
from msg_adapters.header import copy_header, stamp_ns


def joint_state_arrays(msg) -> tuple[list[str], np.ndarray, int]:
    """(names, positions (N,) float64, stamp ns) of a JointState (rclpy or rosbags message). Not validated: a
    message whose name and position lengths differ is passed on as it is (select_by_name refuses it)."""
    positions = np.asarray(msg.position, dtype=np.float64).reshape(-1)
    return [str(n) for n in msg.name], positions, stamp_ns(msg.header.stamp)


def joint_state_from_arrays(names: Sequence[str], positions, header) -> JointState:
    """A JointState of `names` and `positions` (positions only) with a copy of `header` (the image's)."""
    values = np.asarray(positions, dtype=np.float64).reshape(-1)
    if len(values) != len(names):
        raise ValueError(f"{len(names)} joint names but {len(values)} positions")
    return JointState(header=copy_header(header), name=list(names), position=[float(v) for v in values])


def joint_positions_by_name(msg, joint_names: Sequence[str], name_map: JointNameMap | None = None
                            ) -> tuple[Selection, int]:
    """(Selection, stamp ns): the positions of the robot YAML's `joint_names` picked from a robot's JointState by
    the robot's names (`name_map`: the YAML name -> the robot's, identity by default). ValueError for a malformed
    message (names and positions of different lengths)."""
    names, positions, stamp = joint_state_arrays(msg)
    wanted = (name_map or JointNameMap()).robot_names(joint_names)
    return select_by_name(names, positions, wanted), stamp


def to_diagnostic_status(level: int, name: str, message: str, hardware_id: str = "",
                         values: Mapping[str, object] | None = None) -> DiagnosticStatus:
    """A DiagnosticStatus; `level` 0 OK, 1 WARN, 2 ERROR, 3 STALE (as an int), values as strings."""
    return DiagnosticStatus(level=bytes([int(level)]), name=name, message=message, hardware_id=hardware_id,
                            values=[KeyValue(key=str(k), value=str(v)) for k, v in (values or {}).items()])
