"""The console-script life cycle shared by the nodes: init, build (a bad start is logged FATAL and exits 1), spin
until Ctrl-C or until the node says it is done, then clean up."""

from __future__ import annotations

import gc
from collections.abc import Callable

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


def run_node(factory: Callable[[], Node], name: str, args: list[str] | None = None,
             done: Callable[[Node], bool] = lambda node: False,
             exit_code: Callable[[Node], int] = lambda node: 0) -> int:
    """Run the node `factory()` builds; returns the process exit status."""
    rclpy.init(args=args)
    try:
        node = factory()
    except (ValueError, OSError, ParameterException) as e:
        rclpy.logging.get_logger(name).fatal(f"cannot start: {e}")
        rclpy.try_shutdown()
        return 1
    gc.freeze()  # the model and everything built so far live until exit: no collection walks them, exit is fast
    try:
        while rclpy.ok() and not done(node):
            rclpy.spin_once(node, timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return exit_code(node)
