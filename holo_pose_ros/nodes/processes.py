"""Graphs of node processes on this machine, as users run them (`ros2 run` = one process a node): a private DDS
domain on localhost with the package's shared-memory transport, node processes started with `--ros-args -p`,
and their clean shutdown. Used by the demo and the node-level benchmark."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from holo_pose_ros.resources import config_dir

GRAPH_VARIABLES = ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "FASTRTPS_DEFAULT_PROFILES_FILE",
                   "FASTDDS_DEFAULT_PROFILES_FILE")


def private_graph_env(base_domain: int = 150) -> dict[str, str]:
    """An environment for a graph of our own: a domain picked from this process id, discovery on localhost only,
    Fast DDS over shared memory. This process joins it too (its rclpy.init reads os.environ)."""
    profile = str(config_dir() / "fastdds_shm.xml")
    env = {**os.environ, "ROS_DOMAIN_ID": str(base_domain + os.getpid() % 80),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "FASTRTPS_DEFAULT_PROFILES_FILE": profile, "FASTDDS_DEFAULT_PROFILES_FILE": profile}
    env.pop("ROS_LOCALHOST_ONLY", None)  # it would override the discovery range (Jazzy)
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    os.environ.update({k: env[k] for k in GRAPH_VARIABLES})
    return env


def start_node(module: str, params: dict, log: Path, env: dict) -> subprocess.Popen:
    """Start `python -m holo_pose_ros.nodes.<module> --ros-args -p k:=v ...` as its own process, output to `log`."""
    args = [sys.executable, "-m", f"holo_pose_ros.nodes.{module}", "--ros-args"]
    for key, value in params.items():
        args += ["-p", f"{key}:={json.dumps(value) if isinstance(value, str) else value}"]
    return subprocess.Popen(args, stdout=open(log, "w"), stderr=subprocess.STDOUT, env=env)


def stop_nodes(processes: dict[str, subprocess.Popen] | list[subprocess.Popen], timeout_s: float = 10.0) -> None:
    """SIGTERM every process still running, then SIGKILL whichever has not exited after `timeout_s`."""
    procs = list(processes.values()) if isinstance(processes, dict) else list(processes)
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            p.kill()
