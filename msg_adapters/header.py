"""Header propagation: every output gets its own copy of the input image's header (stamp, frame_id)."""

from __future__ import annotations

from builtin_interfaces.msg import Time
from std_msgs.msg import Header


def copy_header(header) -> Header:
    """A new std_msgs/Header with `header`'s stamp and frame_id (duck-typed: rclpy or rosbags messages)."""
    return Header(stamp=Time(sec=int(header.stamp.sec), nanosec=int(header.stamp.nanosec)),
                  frame_id=str(header.frame_id))


def stamp_ns(stamp) -> int:
    """Nanoseconds of a builtin_interfaces/Time (rclpy or rosbags message)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def make_header(t_ns: int, frame_id: str) -> Header:
    """A std_msgs/Header stamped `t_ns` nanoseconds."""
    return Header(stamp=Time(sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000)), frame_id=frame_id)
