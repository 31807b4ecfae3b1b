"""`holo-pose-monitor --config config/monitor/example.yaml`: several robots (of any types) watched by one or more
cameras, from one YAML. For each robot and each camera that watches it, an estimator node and a joint-state monitor
node, each its own process with the shared-memory profile, both under the robot's namespace; Ctrl-C (or SIGTERM)
stops them all and exits 0; a node that dies is named, the others are stopped, and the exit status is 1.

The launch file one would write is not possible here (ros2 launch is not on PyPI), so this is its equivalent, and
it prints the `ros2 run` line of every node it starts (`--dry-run`: only the lines). Two halves: the config (read
and checked without ROS: `load_monitor_config`, a ConfigError naming the file and the field) and a thin process
supervisor (`run`, on nodes/processes.py). The config's fields and defaults: config/monitor/defaults.yaml."""

from __future__ import annotations

import argparse
import math
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from holo_pose_ros.nodes.processes import PROFILE_VARIABLES, ros2_run_line, shared_memory_env, shm_profile, \
    start_node, stop_nodes
from holo_pose_ros.resources import config_dir

PROG = "holo-pose-monitor"
DEFAULTS_FILE = "monitor/defaults.yaml"  # under config/
ESTIMATOR_MODULE, MONITOR_MODULE = "estimator_node", "joint_state_monitor_node"  # = their `ros2 run` executables
ESTIMATOR_YAML, MONITOR_YAML = "estimator.yaml", "joint_state_monitor.yaml"
THRESHOLD_KEYS = ("threshold_factor", "error_factor", "default_threshold_rad", "default_threshold_m",
                  "card_test_set", "threshold_overrides")
# node parameters the launcher sets itself, from other fields (the field that sets each)
ESTIMATOR_OWN = {"robot": "model", "model": "model", "image_topic": "cameras", "camera_info_topic": "cameras",
                 "base_frame_id": "base_frame_id"}
MONITOR_OWN = {"robot": "model", "model": "model", "estimate_topic": "the estimator's namespace",
               "reported_topic": "reported_topic", **{k: "thresholds" for k in THRESHOLD_KEYS}}
POLL_S = 0.2  # how often the children are looked at
LOG_TAIL_LINES = 15  # lines of a dead node's log printed
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class ConfigError(ValueError):
    """A monitor config that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class NodeLaunch:
    """One node process: module (= its `ros2 run` executable), namespace, parameters, remappings."""

    name: str          # fully qualified node name, e.g. /panda_left/holo_pose_estimator
    robot: str         # the config's robot name
    module: str
    namespace: str
    params: dict
    remap: dict = field(default_factory=dict)

    def ros2_run(self) -> str:
        return ros2_run_line(self.module, self.params, self.namespace, self.remap)

    def log_name(self) -> str:
        return self.name.strip("/").replace("/", ".") + ".log"


@dataclass(frozen=True)
class MonitorPlan:
    """What a config asks for: the nodes, in start order, and how to run them."""

    config: Path
    nodes: tuple[NodeLaunch, ...]
    shared_memory: bool
    log_dir: Path | None
    stop_timeout_s: float

    @property
    def robots(self) -> list[str]:
        return list(dict.fromkeys(n.robot for n in self.nodes))


# -- the config, without ROS -----------------------------------------------------------------------------------

def _read_yaml(path: Path, what: str):
    try:
        with open(path) as f:
            return yaml.safe_load(f)
    except OSError as e:
        raise ConfigError(f"{what} {path}: cannot read: {e.strerror or e}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML: {e}") from None


def _node_defaults(file_name: str) -> tuple[str, dict]:
    """(node name, {parameter: default}) of a node's YAML in config/ (its only section)."""
    data = yaml.safe_load((config_dir() / file_name).read_text())
    [(name, section)] = data.items()
    return name, section["ros__parameters"]


def resolve_config_path(config: str | Path) -> Path:
    """A config by path, or by name of a shipped one (config/monitor/<name>.yaml)."""
    path = Path(config)
    if not path.is_file() and not path.suffix and path.name == str(config):
        shipped = config_dir() / "monitor" / f"{config}.yaml"
        if shipped.is_file():
            return shipped
    return path


class _Checker:
    """Field checks of one config file; every error names the file and the field."""

    def __init__(self, path: Path):
        self.path = path

    def error(self, where: str, message: str) -> ConfigError:
        return ConfigError(f"{self.path}: {where}: {message}")

    def mapping(self, value, where: str) -> dict:
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise self.error(where, f"expected a mapping (key: value), got {_shown(value)}")
        return value

    def known(self, entry: dict, allowed, where: str) -> None:
        for key in entry:
            if key not in allowed:
                raise self.error(f"{where}{key}" if where.endswith(".") or not where else f"{where}.{key}",
                                 f"unknown field; known: {', '.join(allowed)}")

    def entries(self, value, where: str) -> list:
        if value is None:
            raise self.error(where, "required (a list of at least one entry)")
        if not isinstance(value, list) or not value:
            raise self.error(where, f"expected a list of at least one entry, got {_shown(value)}")
        return value

    def required(self, entry: dict, key: str, where: str):
        if entry.get(key) in (None, ""):
            raise self.error(f"{where}.{key}", "required")
        return entry[key]

    def name(self, value, where: str) -> str:
        if not isinstance(value, str) or not _NAME.fullmatch(value):
            raise self.error(where, f"{_shown(value)} is not a ROS name (letters, digits and _, not starting with a "
                             "digit)")
        return value

    def string(self, value, where: str) -> str:
        if not isinstance(value, str):
            raise self.error(where, f"expected a string, got {_shown(value)}")
        return value

    def topic(self, value, where: str, relative_to: str | None = None) -> str:
        """An absolute topic name; a relative one is put under `relative_to` (a namespace), when allowed."""
        text = self.string(value, where)
        tokens = text[1:].split("/") if text.startswith("/") else text.split("/")
        if not text or not all(_NAME.fullmatch(t) for t in tokens):
            raise self.error(where, f"{text!r} is not a topic name (e.g. /camera/color/image_raw)")
        if text.startswith("/"):
            return text
        if relative_to is None:
            raise self.error(where, f"{text!r}: give the absolute name (starting with /)")
        return f"{relative_to.rstrip('/')}/{text}"

    def namespace(self, value, where: str) -> str:
        text = self.string(value, where)
        tokens = text.strip("/").split("/")
        if not text.strip("/") or not all(_NAME.fullmatch(t) for t in tokens):
            raise self.error(where, f"{text!r} is not a ROS namespace (e.g. /panda_left)")
        return "/" + "/".join(tokens)

    def parameter(self, value, default, where: str):
        """`value` as the type of the node's default (an integer is a float where a float is expected; a boolean
        or number is its text where a string is)."""
        if isinstance(default, bool):
            if isinstance(value, bool):
                return value
            raise self.error(where, f"expected true or false, got {_shown(value)}")
        if isinstance(default, int):
            if isinstance(value, int) and not isinstance(value, bool):
                return value
            raise self.error(where, f"expected an integer, got {_shown(value)}")
        if isinstance(default, float):
            if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
                return float(value)
            raise self.error(where, f"expected a number, got {_shown(value)}")
        if isinstance(default, str):
            if isinstance(value, bool):
                return "true" if value else "false"
            if isinstance(value, (str, int, float)):
                return str(value)
            raise self.error(where, f"expected a string, got {_shown(value)}")
        return value

    def parameters(self, values: dict, defaults: dict, own: dict, node: str, where: str) -> dict:
        """Node parameters checked against the node's YAML (names and types)."""
        out = {}
        for key, value in values.items():
            if key in own:
                raise self.error(f"{where}.{key}", f"set by the launcher from {own[key]}, not here")
            if key not in defaults:
                raise self.error(f"{where}.{key}", f"not a parameter of the {node} node (config/{node}.yaml names "
                                 "them)")
            out[key] = self.parameter(value, defaults[key], f"{where}.{key}")
        return out


def _shown(value) -> str:
    return "nothing" if value is None else repr(value)[:60]


def _camera_info_beside(image_topic: str) -> str:
    parent = image_topic.rsplit("/", 1)[0]
    return f"{parent}/camera_info"


def _cameras(check: _Checker, entries, defaults: dict) -> dict[str, dict]:
    cameras = {}
    for i, entry in enumerate(check.entries(entries, "cameras")):
        where = f"cameras[{i}]"
        entry = {**defaults, **check.mapping(entry, where)}
        check.known(entry, defaults, where)
        name = check.name(check.required(entry, "name", where), f"{where}.name")
        if name in cameras:
            raise check.error(f"{where}.name", f"camera '{name}' is named twice")
        image = check.topic(check.required(entry, "image_topic", where), f"{where}.image_topic")
        info = entry["camera_info_topic"]
        info = check.topic(info, f"{where}.camera_info_topic") if info else _camera_info_beside(image)
        cameras[name] = {"image_topic": image, "camera_info_topic": info}
    return cameras


def _model(check: _Checker, model, where: str) -> tuple[str, str]:
    """(model as the nodes take it, the card's robot): a shipped name as it is, a path made absolute (relative to
    the config's folder)."""
    from holo_pose_ros.model.cards import read_card

    text = check.string(model, where)
    if Path(text).suffix or "/" in text:
        path = Path(text).expanduser()
        text = str(path if path.is_absolute() else (check.path.parent / path).resolve())
    try:
        _, card = read_card(text)
    except (ValueError, OSError) as e:
        raise check.error(where, str(e)) from None
    if not isinstance(card.get("robot"), str):
        raise check.error(where, f"the model card of {text!r} names no robot")
    return text, card["robot"]


def _thresholds(check: _Checker, values: dict, robot: str, monitor_defaults: dict, where: str) -> dict:
    """The monitor's threshold parameters; threshold_overrides as the node's 'joint=value, ...' text, its joints
    checked against the robot YAML."""
    from holo_pose_ros.monitoring import parse_overrides, parse_pairs
    from holo_pose_ros.robots.spec import load_robot_spec

    out = {}
    for key, value in values.items():
        if key not in THRESHOLD_KEYS:
            raise check.error(f"{where}.{key}", f"unknown threshold; known: {', '.join(THRESHOLD_KEYS)}")
        if key != "threshold_overrides":
            out[key] = check.parameter(value, monitor_defaults[key], f"{where}.{key}")
            continue
        field_name = f"{where}.threshold_overrides"
        try:
            if isinstance(value, Mapping):
                overrides = parse_overrides({str(k): str(v) for k, v in value.items()})
            else:
                overrides = parse_overrides(parse_pairs(check.string(value, field_name), "threshold_overrides"))
        except ValueError as e:
            raise check.error(field_name, str(e)) from None
        joints = load_robot_spec(robot).joint_names
        for joint, threshold in overrides.items():
            if joint not in joints:
                raise check.error(f"{field_name}.{joint}", f"not a joint of robot '{robot}' ({', '.join(joints)})")
            if not (math.isfinite(threshold) and threshold > 0):
                raise check.error(f"{field_name}.{joint}", f"a threshold must be a positive number, got {threshold}")
        out[key] = ", ".join(f"{joint}={threshold:g}" for joint, threshold in overrides.items())
    return out


def load_monitor_config(config: str | Path) -> MonitorPlan:
    """Read and check a monitor config (a path, or the name of a shipped one): the nodes to start. ConfigError
    naming the file and the field (e.g. `robots[1].model`) for anything that cannot be used."""
    path = resolve_config_path(config)
    check = _Checker(path)
    defaults = _read_yaml(config_dir() / DEFAULTS_FILE, "defaults")
    data = _read_yaml(path, "config")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping with cameras: and robots:, got {_shown(data)}")
    top_fields = [k for k in defaults if k not in ("camera", "robot")] + ["cameras", "robots"]
    check.known(data, top_fields, "")
    data = {**{k: v for k, v in defaults.items() if k not in ("camera", "robot")}, **data}
    shared_memory = check.parameter(data["shared_memory"], True, "shared_memory")
    stop_timeout_s = check.parameter(data["stop_timeout_s"], 1.0, "stop_timeout_s")
    if stop_timeout_s <= 0:
        raise check.error("stop_timeout_s", f"must be positive, got {stop_timeout_s}")
    log_dir = check.string(data["log_dir"] or "", "log_dir")
    cameras = _cameras(check, data.get("cameras"), defaults["camera"])
    estimator_name, estimator_defaults = _node_defaults(ESTIMATOR_YAML)
    monitor_name, monitor_defaults = _node_defaults(MONITOR_YAML)
    shared = {key: check.mapping(data[key], key) for key in ("estimator", "monitor", "thresholds")}

    nodes, robot_names = [], set()
    for i, entry in enumerate(check.entries(data.get("robots"), "robots")):
        where = f"robots[{i}]"
        entry = {**defaults["robot"], **check.mapping(entry, where)}
        check.known(entry, defaults["robot"], where)
        name = check.name(check.required(entry, "name", where), f"{where}.name")
        if name in robot_names:
            raise check.error(f"{where}.name", f"robot '{name}' is named twice")
        robot_names.add(name)
        model, card_robot = _model(check, check.required(entry, "model", where), f"{where}.model")
        robot = check.string(entry["robot"] or card_robot, f"{where}.robot")
        if robot != card_robot:
            raise check.error(f"{where}.robot", f"'{robot}', but model {model!r} is a model of robot '{card_robot}'")
        namespace = check.namespace(entry["namespace"] or f"/{name}", f"{where}.namespace")
        watched = entry["cameras"] or list(cameras)
        if not isinstance(watched, list):
            raise check.error(f"{where}.cameras", f"expected a list of camera names, got {_shown(watched)}")
        for j, camera in enumerate(watched):
            if camera not in cameras:
                raise check.error(f"{where}.cameras[{j}]", f"no camera {_shown(camera)} in cameras: "
                                  f"({', '.join(cameras)})")
        if len(set(watched)) < len(watched):
            raise check.error(f"{where}.cameras", "a camera is listed twice")
        reported = entry["reported_topic"]
        reported = check.topic(reported, f"{where}.reported_topic", namespace) if reported else ""
        base_frame = check.string(entry["base_frame_id"] or "", f"{where}.base_frame_id")
        estimator = check.parameters({**shared["estimator"], **check.mapping(entry["estimator"], f"{where}.estimator")},
                                     estimator_defaults, ESTIMATOR_OWN, "estimator", f"{where}.estimator")
        monitor = check.parameters({**shared["monitor"], **check.mapping(entry["monitor"], f"{where}.monitor")},
                                   monitor_defaults, MONITOR_OWN, "joint_state_monitor", f"{where}.monitor")
        thresholds = _thresholds(check, {**shared["thresholds"],
                                         **check.mapping(entry["thresholds"], f"{where}.thresholds")},
                                 robot, monitor_defaults, f"{where}.thresholds")
        for camera in watched:
            several = len(watched) > 1
            ns = f"{namespace}/{camera}" if several else namespace
            estimator_params = {"robot": robot, "model": model, **estimator,
                                "base_frame_id": base_frame or (f"{name}_{camera}_base_link" if several
                                                                else f"{name}_base_link")}
            monitor_params = {"robot": robot, "model": model, "robot_id": f"{name}/{camera}" if several else name,
                              "estimate_topic": f"{ns}/{estimator_name}/joint_states", "reported_topic": reported,
                              **thresholds, **monitor}
            remap = {estimator_defaults["image_topic"]: cameras[camera]["image_topic"],
                     estimator_defaults["camera_info_topic"]: cameras[camera]["camera_info_topic"]}
            nodes.append(NodeLaunch(f"{ns}/{estimator_name}", name, ESTIMATOR_MODULE, ns, estimator_params, remap))
            nodes.append(NodeLaunch(f"{ns}/{monitor_name}", name, MONITOR_MODULE, ns, monitor_params))
    seen: dict[str, str] = {}
    for node in nodes:
        if node.name in seen:
            raise check.error("robots", f"robots '{seen[node.name]}' and '{node.robot}' would both start "
                              f"{node.name}: give them different namespaces")
        seen[node.name] = node.robot
    return MonitorPlan(path, tuple(nodes), shared_memory, Path(log_dir) if log_dir else None, stop_timeout_s)


# -- the processes --------------------------------------------------------------------------------------------

def _say(message: str, stream=None) -> None:
    print(f"{PROG}: {message}", file=stream or sys.stdout, flush=True)


def _exit_reason(code: int) -> str:
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exited with code {code}"


def _tail(path: Path | None) -> str:
    if path is None or not path.is_file():
        return ""
    lines = path.read_text(errors="replace").splitlines()[-LOG_TAIL_LINES:]
    return "".join(f"    | {line}\n" for line in lines)


def equivalent_commands(plan: MonitorPlan) -> list[str]:
    """The shell lines that start the same nodes by hand (one terminal each)."""
    lines = [f"export {var}={shm_profile()}" for var in PROFILE_VARIABLES] if plan.shared_memory else []
    return lines + [node.ros2_run() for node in plan.nodes]


def run(plan: MonitorPlan) -> int:
    """Start every node of `plan`, wait; 0 after SIGINT/SIGTERM (every node stopped), 1 when a node dies (the
    others stopped). A second signal while stopping kills the nodes still running at once."""
    env = shared_memory_env() if plan.shared_memory else dict(os.environ)
    if plan.log_dir is not None:
        plan.log_dir.mkdir(parents=True, exist_ok=True)
    processes: dict[str, subprocess.Popen] = {}
    logs = {node.name: plan.log_dir / node.log_name() if plan.log_dir else None for node in plan.nodes}
    state = {"signal": None, "stopping": False}

    def on_signal(signum, _frame):
        if state["stopping"]:  # asked again: no more waiting
            for process in processes.values():
                if process.poll() is None:
                    process.kill()
        state["signal"] = state["signal"] or signal.Signals(signum).name

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    code = 0
    try:
        transport = (f"shared-memory profile {shm_profile()}" if plan.shared_memory
                     else "the environment's DDS settings")
        _say(f"{plan.config}: {len(plan.robots)} robot(s), {len(plan.nodes)} nodes; ROS_DOMAIN_ID "
             f"{env.get('ROS_DOMAIN_ID', '0 (unset)')}, {transport}"
             + (f"; logs in {plan.log_dir}" if plan.log_dir else ""))
        if plan.shared_memory:
            print("\n".join(f"  export {var}={shm_profile()}" for var in PROFILE_VARIABLES), flush=True)
        for node in plan.nodes:
            if state["signal"]:
                break
            processes[node.name] = start_node(node.module, node.params, logs[node.name], env, node.namespace,
                                              node.remap, supervised=True)
            print(f"started {node.name} (pid {processes[node.name].pid}):\n  {node.ros2_run()}", flush=True)
        if not state["signal"]:
            _say(f"running {len(processes)} nodes; Ctrl-C stops them all")
        while not state["signal"]:
            dead = [(name, p) for name, p in processes.items() if p.poll() is not None]
            if dead:
                for name, p in dead:
                    log = logs[name]
                    _say(f"{name} (pid {p.pid}) {_exit_reason(p.returncode)}"
                         + (f"; its log: {log}" if log else ""), sys.stderr)
                    sys.stderr.write(_tail(log))
                code = 1
                break
            time.sleep(POLL_S)
    finally:
        state["stopping"] = True
        running = [name for name, p in processes.items() if p.poll() is None]
        reason = state["signal"] or ("a node stopped" if code else "error")
        if running:
            _say(f"{reason}: stopping {len(running)} node(s)")
        stopping_since = time.monotonic()
        stop_nodes({name: processes[name] for name in running}, plan.stop_timeout_s)
        stop_s = time.monotonic() - stopping_since
        for s, handler in previous.items():
            signal.signal(s, handler)
    forced = [name for name in running if processes[name].returncode == -signal.SIGKILL]
    if forced:
        _say(f"killed after {plan.stop_timeout_s:g} s: {', '.join(forced)}")
    _say(f"stopped {len(processes)} node(s) in {stop_s:.1f} s; exit {code}")
    return code


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0],
                                     epilog="config fields and defaults: config/monitor/defaults.yaml; example: "
                                            "config/monitor/example.yaml")
    parser.add_argument("--config", required=True, help="monitor config YAML (a path, or a shipped config's name)")
    parser.add_argument("--dry-run", action="store_true", help="check the config, print the equivalent "
                        "`ros2 run` lines, start nothing")
    args = parser.parse_args(argv)
    try:
        plan = load_monitor_config(args.config)
    except ConfigError as e:
        _say(f"bad config: {e}", sys.stderr)
        return 2
    if args.dry_run:
        print("\n".join(equivalent_commands(plan)))
        return 0
    return run(plan)


if __name__ == "__main__":
    sys.exit(main())
