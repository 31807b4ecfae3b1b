"""Several robots: `holo-pose-monitor --config` (holo_pose_ros/nodes/monitor_launcher.py) and the two-robot scenes
of the generator. The config is checked without ROS (errors name the field); the printed `ros2 run` lines are
parsed by rcl itself (the node they start has that namespace and those parameters); a rendered Panda + Kuka scene
has each robot's ground truth for its own DREAM reader; and the launcher, started as a real process on two small
untrained models, runs an estimator and a monitor per robot under its namespace, each pair answering on its own
topics when the two-robot images are published, stops on SIGINT with exit 0, and on a child's death names it and
exits 1, with no node process left behind in any case (checked by pid)."""

from __future__ import annotations

import itertools
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
import torch
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import CameraInfo, Image, JointState

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import DISTRACTOR_LABEL, generate
from holo_pose_ros.monitoring import joint_kinds, wrap_to_period
from holo_pose_ros.nodes.monitor_launcher import ConfigError, load_monitor_config, main
from holo_pose_ros.nodes.processes import parameter_value
from holo_pose_ros.robots.kinematics import RobotModel
from graph_helpers import domain_ids, spin_until
from msg_adapters import camera_info_from_K, make_header, rgb_to_image, stamp_ns
from small_model import save_small_model

ROOT = Path(__file__).resolve().parent.parent
_DOMAINS = domain_ids(201, 232)
ROBOTS = {"panda_left": "panda", "kuka_right": "kuka"}  # config name -> robot type
# An estimator's exit after SIGTERM is its interpreter's final garbage collection: 1 s here when idle, up to 10 s
# with four node processes at nice 19 beside a training run; past this the launcher SIGKILLs it (also under test).
STOP_TIMEOUT_S = 4.0
ESTIMATOR_TEST_PARAMS = {"device": "cpu", "backend": "torch", "threads": 1, "min_confidence": 0.0,
                         "publish_annotated": False, "publish_tf": False}


# -- config ------------------------------------------------------------------------------------------------------

def write_config(tmp_path: Path, text: str, name: str = "monitor.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


GOOD = """
cameras:
  - {name: front, image_topic: /cam/image_raw}
robots:
  - {name: panda_left, model: panda}
  - {name: kuka_right, model: kuka, reported_topic: /iiwa/joint_states}
"""
BAD = [
    ("robots: [{name: a, model: panda}]", "cameras: required"),
    ("cameras: []\nrobots: [{name: a, model: panda}]", "cameras: expected a list of at least one entry"),
    ("cameras: [{name: f, image_topic: /i}]\nrobot: []", "robot: unknown field; known: shared_memory"),
    ("cameras: [{name: f}]\nrobots: [{name: a, model: panda}]", "cameras[0].image_topic: required"),
    ("cameras: [{name: f, image_topic: 'cam image'}]\nrobots: [{name: a, model: panda}]",
     "cameras[0].image_topic: 'cam image' is not a topic name"),
    ("cameras: [{name: f, image_topic: image}]\nrobots: [{name: a, model: panda}]",
     "cameras[0].image_topic: 'image': give the absolute name"),
    ("cameras: [{name: f, image_topic: /i}, {name: f, image_topic: /j}]\nrobots: [{name: a, model: panda}]",
     "cameras[1].name: camera 'f' is named twice"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: panda-left, model: panda}]",
     "robots[0].name: 'panda-left' is not a ROS name"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: a}]", "robots[0].model: required"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: a, model: panda}, {name: b, model: nope}]",
     "robots[1].model: no shipped model 'nope'; shipped: baxter"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: a, model: cards/none.yaml}]",
     "robots[0].model: model card not found"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: a, model: panda, robot: kuka}]",
     "robots[0].robot: 'kuka', but model 'panda' is a model of robot 'panda'"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: a, model: panda}, {name: a, model: kuka}]",
     "robots[1].name: robot 'a' is named twice"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: a, model: panda, namespace: /x},"
     " {name: b, model: kuka, namespace: x}]", "robots 'a' and 'b' would both start /x/holo_pose_estimator"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: a, model: panda, cameras: [side]}]",
     "robots[0].cameras[0]: no camera 'side' in cameras: (f)"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: a, model: panda, colour: red}]",
     "robots[0].colour: unknown field; known: name, model"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: a, model: panda, estimator: {threads: two}}]",
     "robots[0].estimator.threads: expected an integer, got 'two'"),
    ("cameras: [{name: f, image_topic: /i}]\nestimator: {tracking: 1}\nrobots: [{name: a, model: panda}]",
     "robots[0].estimator.tracking: expected true or false, got 1"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: a, model: panda, estimator: {image_topic: /i}}]",
     "robots[0].estimator.image_topic: set by the launcher from cameras, not here"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: a, model: panda, monitor: {windw: 3}}]",
     "robots[0].monitor.windw: not a parameter of the joint_state_monitor node"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: a, model: panda, monitor: {threshold_factor: 2}}]",
     "robots[0].monitor.threshold_factor: set by the launcher from thresholds, not here"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: a, model: panda, thresholds: {factor: 2}}]",
     "robots[0].thresholds.factor: unknown threshold; known: threshold_factor"),
    ("cameras: [{name: f, image_topic: /i}]\n"
     "robots: [{name: a, model: panda, thresholds: {threshold_overrides: {panda_joint9: 0.2}}}]",
     "robots[0].thresholds.threshold_overrides.panda_joint9: not a joint of robot 'panda'"),
    ("cameras: [{name: f, image_topic: /i}]\n"
     "robots: [{name: a, model: panda, thresholds: {threshold_overrides: 'panda_joint1=fast'}}]",
     "robots[0].thresholds.threshold_overrides: threshold_overrides: panda_joint1=fast is not a number"),
    ("cameras: [{name: f, image_topic: /i}]\nrobots: [{name: a, model: panda, reported_topic: '~/js'}]",
     "robots[0].reported_topic: '~/js' is not a topic name"),
    ("cameras: [{name: f, image_topic: /i}]\nstop_timeout_s: 0\nrobots: [{name: a, model: panda}]",
     "stop_timeout_s: must be positive"),
    ("cameras: [{name: f, image_topic: /i}\nrobots: []", "not valid YAML"),
]


@pytest.mark.parametrize("text, message", BAD, ids=[f"bad{i}" for i in range(len(BAD))])
def test_config_errors_name_the_field(tmp_path, text, message):
    path = write_config(tmp_path, text)
    with pytest.raises(ConfigError) as error:
        load_monitor_config(path)
    assert str(error.value).startswith(f"{path}: ") and message in str(error.value), str(error.value)


def test_bad_config_exits_2_with_the_reason(tmp_path, capsys):
    assert main(["--config", str(tmp_path / "missing.yaml")]) == 2
    assert f"holo-pose-monitor: bad config: config {tmp_path / 'missing.yaml'}: cannot read" in capsys.readouterr().err


def test_plan_from_the_example_and_defaults(tmp_path, small_model_card):
    plan = load_monitor_config("example")  # the shipped config/monitor/example.yaml by name
    assert plan.config == ROOT / "config" / "monitor" / "example.yaml" and plan.shared_memory
    assert [n.name for n in plan.nodes] == ["/panda_left/holo_pose_estimator", "/panda_left/joint_state_monitor",
                                            "/kuka_right/holo_pose_estimator", "/kuka_right/joint_state_monitor"]
    estimator, monitor = plan.nodes[0], plan.nodes[1]
    assert estimator.module == "estimator_node" and estimator.namespace == "/panda_left"
    assert estimator.params == {"robot": "panda", "model": "panda", "threads": 1,
                                "base_frame_id": "panda_left_base_link"}
    assert estimator.remap == {"image": "/camera/color/image_raw", "camera_info": "/camera/color/camera_info"}
    assert monitor.params["reported_topic"] == "/panda_left/joint_states"
    assert monitor.params["estimate_topic"] == "/panda_left/holo_pose_estimator/joint_states"
    assert monitor.params["threshold_overrides"] == "panda_joint4=0.3" and monitor.params["robot_id"] == "panda_left"
    assert plan.nodes[3].params["reported_topic"] == "/iiwa/joint_states"

    # several cameras: a pair per camera under /<ns>/<camera>; defaults: camera_info beside the image, every camera,
    # ints as floats where the node wants a float, a card path relative to the config's folder
    (tmp_path / "cfg").mkdir()
    card = os.path.relpath(small_model_card, tmp_path / "cfg")
    plan = load_monitor_config(write_config(tmp_path / "cfg", f"""
cameras: [{{name: front, image_topic: /front/color/image_raw}}, {{name: side, image_topic: /side/image}}]
thresholds: {{threshold_factor: 4}}
robots: [{{name: arm, model: {card}, namespace: /cell1/arm, thresholds: {{error_factor: 3}}}}]
"""))
    assert [n.name for n in plan.nodes] == [f"/cell1/arm/{camera}/{node}" for camera in ("front", "side")
                                            for node in ("holo_pose_estimator", "joint_state_monitor")]
    side, side_monitor = plan.nodes[2], plan.nodes[3]
    assert side.remap == {"image": "/side/image", "camera_info": "/side/camera_info"}
    assert side.params["model"] == str(small_model_card) and side.params["base_frame_id"] == "arm_side_base_link"
    assert side_monitor.params["robot_id"] == "arm/side"
    assert side_monitor.params["reported_topic"] == "/cell1/arm/joint_states"  # the robot's, not the camera's
    assert side_monitor.params["threshold_factor"] == 4.0 and isinstance(side_monitor.params["threshold_factor"], float)
    assert side_monitor.params["error_factor"] == 3.0


def test_string_parameters_are_quoted_only_when_yaml_would_misread_them():
    assert parameter_value("panda") == "panda" and parameter_value("/a/b-c.yaml") == "/a/b-c.yaml"
    for text in ["", "true", "Off", "1e3", "nan", "0x10", "a b", "a: b", "~", "panda_joint4=0.3"]:
        assert yaml.safe_load(parameter_value(text)) == text, text
    assert parameter_value(True) == "true" and parameter_value(3.0) == "3.0" and parameter_value(2) == "2"


def test_the_printed_ros2_run_line_is_what_rcl_reads_and_a_renamed_node_keeps_its_defaults():
    """The monitors of the example, built from their printed `ros2 run` lines' arguments (rcl parses them): the
    namespace and every parameter as planned; `-r __node:=other` (a rename) still finds the YAML defaults."""
    from holo_pose_ros.nodes.joint_state_monitor_node import JointStateMonitorNode

    plan = load_monitor_config("example")
    context = Context()
    rclpy.init(context=context, domain_id=next(_DOMAINS))
    try:
        for launch in (plan.nodes[1], plan.nodes[3]):
            argv = shlex.split(launch.ros2_run())
            assert argv[:4] == ["ros2", "run", "holo_pose_ros", "joint_state_monitor_node"]
            node = JointStateMonitorNode(context=context, cli_args=argv[4:])
            try:
                assert node.get_fully_qualified_name() == launch.name
                for key, value in launch.params.items():
                    assert node.get_parameter(key).value == value, key
            finally:
                node.destroy_node()
        node = JointStateMonitorNode(context=context, cli_args=["--ros-args", "-r", "__node:=left_monitor"])
        assert node.get_fully_qualified_name() == "/left_monitor" and node.get_parameter("window").value == 30
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


# -- the two-robot scene -------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def pair_folder(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("panda_and_kuka")
    generate("panda", 2, folder, seed=4, workers=1, width=320, height=240, progress=False, second_robot="kuka")
    return folder


def test_two_robot_scene_renders_both_and_each_reader_reads_its_own(pair_folder):
    panda, kuka = DreamReader(pair_folder, "panda"), DreamReader(pair_folder, "kuka")
    assert len(panda) == len(kuka) == 2 and not panda.problems and not kuka.problems
    models = {name: RobotModel(name, dtype=torch.float64) for name in ("panda", "kuka")}
    n_panda_labels = len([link for link in models["panda"].urdf.robot.links if link.visuals])
    for p, k in zip(panda, kuka):
        assert p.image_path == k.image_path and not np.allclose(p.T_cam_base, k.T_cam_base)
        for frame, model in ((p, models["panda"]), (k, models["kuka"])):
            assert frame.keypoint_names == tuple(model.keypoint_names) and frame.base_pose_source == "quaternion"
            fk = model.keypoints_in_camera(torch.from_numpy(np.array(frame.joints[None])),
                                           torch.from_numpy(np.array(frame.T_cam_base[None])))[0].numpy()
            np.testing.assert_allclose(frame.keypoints_3d, fk, atol=1e-6)
            assert frame.in_image.mean() >= 0.75  # both framed
        # side by side, never touching: every Panda keypoint well away from every Kuka keypoint
        gaps = np.linalg.norm(p.keypoints_3d[:, None] - k.keypoints_3d[None], axis=-1)
        assert gaps.min() > 0.1, gaps.min()
        # both drawn: the mask numbers the Panda's links first, then the Kuka's
        labels = set(np.unique(panda.load_mask(p)).tolist()) - {0, DISTRACTOR_LABEL}
        assert any(v <= n_panda_labels for v in labels) and any(v > n_panda_labels for v in labels), labels
    settings = json.loads((pair_folder / "_generator_settings.json").read_text())
    assert settings["second_robot"] == "kuka" and "--second-robot kuka" in settings["command"]
    with pytest.raises(ValueError, match="another robot type"):
        generate("panda", 1, pair_folder / "same", second_robot="panda", progress=False)


# -- the launcher as a process ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def kuka_card(tmp_path_factory) -> Path:
    return save_small_model(tmp_path_factory.mktemp("small_kuka"), robot="kuka")


def launcher_config(tmp_path: Path, cards: dict[str, Path]) -> Path:
    robots = [{"name": name, "model": str(cards[robot])} for name, robot in ROBOTS.items() if robot in cards]
    config = {"cameras": [{"name": "cam", "image_topic": "/cam/image_raw"}], "log_dir": str(tmp_path / "logs"),
              "stop_timeout_s": STOP_TIMEOUT_S, "estimator": ESTIMATOR_TEST_PARAMS, "robots": robots}
    return write_config(tmp_path, yaml.safe_dump(config, sort_keys=False), "launcher.yaml")


class Launcher:
    """`holo-pose-monitor --config` as a real process in its own domain; its output in a file."""

    def __init__(self, tmp_path: Path, config: Path):
        self.domain = next(_DOMAINS)
        self.out = tmp_path / "launcher.out"
        env = {**os.environ, "ROS_DOMAIN_ID": str(self.domain), "OMP_NUM_THREADS": "1"}
        self.process = subprocess.Popen([sys.executable, "-m", "holo_pose_ros.nodes.monitor_launcher", "--config",
                                         str(config)], stdout=open(self.out, "w"), stderr=subprocess.STDOUT, env=env)

    def output(self) -> str:
        return self.out.read_text()

    def pids(self) -> dict[str, int]:
        return {name: int(pid) for name, pid in re.findall(r"^started (\S+) \(pid (\d+)\)", self.output(), re.M)}

    def wait_for(self, text: str, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while text not in self.output():
            assert self.process.poll() is None and time.monotonic() < deadline, self.output()
            time.sleep(0.1)

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()
        for pid in self.pids().values():
            if alive(pid):
                os.kill(pid, signal.SIGKILL)


def alive(pid: int) -> bool:
    """Whether process `pid` still runs (a zombie, waiting for a reaper, does not)."""
    try:
        os.kill(pid, 0)
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (ProcessLookupError, FileNotFoundError):
        return False
    return state != "Z"


def all_gone(pids, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while any(alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    return not any(alive(p) for p in pids)


@pytest.fixture
def launchers(tmp_path):
    made = []

    def make(config: Path) -> Launcher:
        made.append(Launcher(tmp_path, config))
        return made[-1]

    yield make
    for launcher in made:
        launcher.close()


def test_two_robots_one_camera_each_pair_under_its_namespace_then_sigint(tmp_path, launchers, pair_folder,
                                                                         small_model_card, kuka_card):
    launcher = launchers(launcher_config(tmp_path, {"panda": small_model_card, "kuka": kuka_card}))
    launcher.wait_for("running 4 nodes")
    pids = launcher.pids()
    assert sorted(pids) == sorted(f"/{name}/{node}" for name in ROBOTS
                                  for node in ("holo_pose_estimator", "joint_state_monitor"))
    assert "ros2 run holo_pose_ros estimator_node --ros-args -r __ns:=/panda_left" in launcher.output()

    readers = {name: DreamReader(pair_folder, robot) for name, robot in ROBOTS.items()}
    frames = list(zip(*readers.values()))
    context = Context()
    rclpy.init(context=context, domain_id=launcher.domain)
    probe = rclpy.create_node("probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(probe)
    received: dict[str, list] = {}

    def record(key: str, kind, topic: str) -> None:
        received[key] = []
        probe.create_subscription(kind, topic, received[key].append, 50)

    for name in ROBOTS:
        record(f"{name}/estimate", JointState, f"/{name}/holo_pose_estimator/joint_states")
        record(f"{name}/discrepancy", JointState, f"/{name}/joint_state_monitor/discrepancy")
    record("diagnostics", DiagnosticArray, "/diagnostics")
    images = probe.create_publisher(Image, "/cam/image_raw", 10)
    infos = probe.create_publisher(CameraInfo, "/cam/camera_info", 10)
    reported = {name: probe.create_publisher(JointState, f"/{name}/joint_states", 10) for name in ROBOTS}
    truth: dict[tuple[str, int], np.ndarray] = {}
    count = itertools.count()

    def publish() -> None:
        """Frame k of the two-robot scene stamped 100 s + k x 0.1 s, each robot's truth as its report."""
        k = next(count)
        pair = frames[k % len(frames)]
        header = make_header(100_000_000_000 + k * 100_000_000, "cam_optical_frame")
        for (name, publisher), frame in zip(reported.items(), pair):
            truth[name, stamp_ns(header.stamp)] = np.asarray(frame.joints)
            publisher.publish(JointState(header=header, name=readers[name].robot.joint_names,
                                         position=[float(v) for v in frame.joints]))
        infos.publish(camera_info_from_K(pair[0].K, pair[0].width, pair[0].height, header))
        images.publish(rgb_to_image(readers["panda_left"].load_image(pair[0]), header))

    def statuses() -> dict[str, dict]:
        out = {}
        for array in received["diagnostics"]:
            for s in array.status:
                if s.name.startswith("joint_state_monitor:"):
                    out[s.name] = {kv.key: kv.value for kv in s.values}
        return out

    def answered() -> bool:
        return all(len(received[f"{name}/discrepancy"]) >= 2 for name in ROBOTS) and len(statuses()) == 2

    try:
        deadline, next_frame = time.monotonic() + 75.0, 0.0
        while not answered() and time.monotonic() < deadline:
            assert launcher.process.poll() is None, launcher.output()
            if time.monotonic() > next_frame:
                publish()
                next_frame = time.monotonic() + 0.25
            executor.spin_once(timeout_sec=0.02)
        assert answered(), ({k: len(v) for k, v in received.items()}, launcher.output())

        def estimates_caught_up() -> bool:
            """The probe has the estimate of every discrepancy it received (two topics, two publishers: the
            discrepancy of a frame can reach the probe before that frame's estimate does)."""
            return all({stamp_ns(d.header.stamp) for d in received[f"{name}/discrepancy"]}
                       <= {stamp_ns(m.header.stamp) for m in received[f"{name}/estimate"]} for name in ROBOTS)

        spin_until(executor, estimates_caught_up, timeout=10.0)
        graph = set(probe.get_node_names_and_namespaces())
        assert {(node, f"/{name}") for name in ROBOTS
                for node in ("holo_pose_estimator", "joint_state_monitor")} <= graph, graph
        # each estimator estimates its own robot, each monitor compares it with its own robot's report
        for name, robot in ROBOTS.items():
            joint_names = readers[name].robot.joint_names
            estimates = {stamp_ns(m.header.stamp): m for m in received[f"{name}/estimate"]}
            assert all(list(m.name) == joint_names for m in estimates.values())
            spec = readers[name].robot.spec
            kinds = joint_kinds(spec)
            for d in received[f"{name}/discrepancy"]:
                stamp = stamp_ns(d.header.stamp)
                assert list(d.name) == joint_names and stamp in estimates
                expected = np.asarray(estimates[stamp].position) - truth[name, stamp]
                angular = np.array([kind != "prismatic" for kind in kinds])
                # a turn, or half of one for a joint that looks the same after it (the robot YAML's symmetry)
                period = np.array([spec.joint_symmetry.get(n, 2 * np.pi) for n in joint_names])
                expected[angular] = wrap_to_period(expected[angular], period[angular])
                np.testing.assert_allclose(d.position, expected, atol=1e-9)
        status = statuses()
        for name in ROBOTS:
            values = status[f"joint_state_monitor: {name} joint states"]
            assert values["robot"] == name and values["reported_topic"] == f"/{name}/joint_states"
            assert values["estimate_topic"] == f"/{name}/holo_pose_estimator/joint_states"
    finally:
        probe.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown(context=context)

    launcher.process.send_signal(signal.SIGINT)
    assert launcher.process.wait(timeout=30) == 0, launcher.output()
    assert "SIGINT: stopping 4 node(s)" in launcher.output() and "exit 0" in launcher.output()
    assert all_gone(pids.values(), timeout=1.0), {n: p for n, p in pids.items() if alive(p)}


def test_a_dead_node_is_named_and_the_others_stopped_exit_1(tmp_path, launchers, small_model_card):
    launcher = launchers(launcher_config(tmp_path, {"panda": small_model_card}))
    launcher.wait_for("running 2 nodes")
    pids = launcher.pids()
    os.kill(pids["/panda_left/joint_state_monitor"], signal.SIGKILL)
    assert launcher.process.wait(timeout=30) == 1, launcher.output()
    assert f"/panda_left/joint_state_monitor (pid {pids['/panda_left/joint_state_monitor']}) killed by SIGKILL" \
        in launcher.output()
    assert "stopping 1 node(s)" in launcher.output()
    assert all_gone(pids.values(), timeout=1.0), {n: p for n, p in pids.items() if alive(p)}


def test_no_node_outlives_a_killed_launcher(tmp_path, launchers, small_model_card):
    launcher = launchers(launcher_config(tmp_path, {"panda": small_model_card}))
    launcher.wait_for("running 2 nodes")
    pids = launcher.pids()
    launcher.process.kill()  # SIGKILL: no chance to stop anything; the nodes get SIGTERM from the kernel
    launcher.process.wait()
    assert all_gone(pids.values(), timeout=15.0), {n: p for n, p in pids.items() if alive(p)}
