"""Graphs of node processes on this machine, as users run them (`ros2 run` = one process a node): a private DDS
domain on localhost with the package's shared-memory transport (or only that transport, in the user's domain),
node processes started with `--ros-args` (parameters, namespace, remappings), the equivalent `ros2 run` line, and
their clean shutdown. Used by the demo, the node-level benchmark and the multi-robot launcher."""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

from holo_pose_ros.resources import config_dir

GRAPH_VARIABLES = ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "FASTRTPS_DEFAULT_PROFILES_FILE",
                   "FASTDDS_DEFAULT_PROFILES_FILE")
PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")  # Fast DDS reads either
PACKAGE = "holo_pose_ros"
# A string parameter value passed bare (`-p model:=panda`) only when no YAML reading could take it for anything
# but that string; otherwise JSON-quoted (`-p robot_id:="true"`, `-p joint_name_prefix:=""`).
_PLAIN_STRING = re.compile(r"[A-Za-z_/][A-Za-z0-9_./-]*")
_YAML_WORDS = {"y", "n", "yes", "no", "true", "false", "on", "off", "null", "nan", "inf", "infinity"}


def shm_profile() -> Path:
    """The package's Fast DDS profile: shared memory plus UDP on the loopback (config/fastdds_shm.xml)."""
    return config_dir() / "fastdds_shm.xml"


def shared_memory_env(env: dict[str, str] | None = None) -> dict[str, str]:
    """`env` (default: os.environ) with the shared-memory profile set, everything else (the domain id, the
    discovery range) as it is: for nodes that join the user's own graph on this machine."""
    return {**(os.environ if env is None else env), **{k: str(shm_profile()) for k in PROFILE_VARIABLES}}


def private_graph_env(base_domain: int = 150) -> dict[str, str]:
    """An environment for a graph of our own: a domain picked from this process id, discovery on localhost only,
    Fast DDS over shared memory. This process joins it too (its rclpy.init reads os.environ)."""
    profile = str(shm_profile())
    env = {**os.environ, "ROS_DOMAIN_ID": str(base_domain + os.getpid() % 80),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "FASTRTPS_DEFAULT_PROFILES_FILE": profile, "FASTDDS_DEFAULT_PROFILES_FILE": profile}
    env.pop("ROS_LOCALHOST_ONLY", None)  # it would override the discovery range (Jazzy)
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    os.environ.update({k: env[k] for k in GRAPH_VARIABLES})
    return env


def parameter_value(value) -> str:
    """A parameter value as `-p name:=<value>` takes it (YAML): strings bare when unambiguous, else JSON-quoted;
    booleans true/false; lists as JSON; numbers as Python prints them."""
    if isinstance(value, str):
        plain = _PLAIN_STRING.fullmatch(value) and value.lower() not in _YAML_WORDS
        return value if plain else json.dumps(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return json.dumps(list(value))
    return str(value)


def ros_arguments(params: dict, namespace: str = "", remap: dict[str, str] | None = None) -> list[str]:
    """`--ros-args [-r __ns:=<namespace>] [-p k:=v ...] [-r from:=to ...]` of a node process."""
    args = ["--ros-args"] + (["-r", f"__ns:={namespace}"] if namespace else [])
    for key, value in params.items():
        args += ["-p", f"{key}:={parameter_value(value)}"]
    for source, target in (remap or {}).items():
        args += ["-r", f"{source}:={target}"]
    return args


def ros2_run_line(module: str, params: dict, namespace: str = "", remap: dict[str, str] | None = None) -> str:
    """The shell line `ros2 run holo_pose_ros <module> --ros-args ...` that starts the same node as start_node
    (the package's executables are named after their modules)."""
    return shlex.join(["ros2", "run", PACKAGE, module, *ros_arguments(params, namespace, remap)])


def _stop_with_parent(parent: int) -> None:
    """In the child, before exec: SIGTERM when the parent dies (Linux prctl PR_SET_PDEATHSIG), so that no node
    outlives a launcher that was killed; exit at once when the parent is already gone."""
    import ctypes

    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM, 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
    if os.getppid() != parent:
        os._exit(1)


def start_node(module: str, params: dict, log: Path | None, env: dict, namespace: str = "",
               remap: dict[str, str] | None = None, supervised: bool = False) -> subprocess.Popen:
    """Start `python -m holo_pose_ros.nodes.<module> --ros-args [-r __ns:=ns] -p k:=v ... -r from:=to ...` as its
    own process, output to the file `log` (None: this process's stdout and stderr). `supervised`: in a process
    group of its own (a Ctrl-C at the terminal reaches only this process, which stops the node in order) and
    SIGTERMed if this process dies (Linux), so that it never outlives it; needs a process without threads."""
    args = [sys.executable, "-m", f"holo_pose_ros.nodes.{module}", *ros_arguments(params, namespace, remap)]
    output = open(log, "w") if log is not None else None
    extra = {}
    if supervised:
        extra = dict(process_group=0, stdin=subprocess.DEVNULL)
        if sys.platform.startswith("linux"):
            parent = os.getpid()
            extra["preexec_fn"] = lambda: _stop_with_parent(parent)
    try:
        return subprocess.Popen(args, stdout=output, stderr=subprocess.STDOUT if output else None, env=env, **extra)
    finally:
        if output is not None:
            output.close()  # the child has its own descriptor


def stop_nodes(processes: dict[str, subprocess.Popen] | list[subprocess.Popen], timeout_s: float = 10.0) -> None:
    """SIGTERM every process still running, then SIGKILL whichever has not exited `timeout_s` later; all reaped."""
    procs = list(processes.values()) if isinstance(processes, dict) else list(processes)
    for p in procs:
        if p.poll() is None:
            p.terminate()
    deadline = time.monotonic() + timeout_s
    for p in procs:
        try:
            p.wait(timeout=max(deadline - time.monotonic(), 0.0))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()  # reaped: no zombie left behind
