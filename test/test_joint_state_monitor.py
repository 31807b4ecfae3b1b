"""The joint-state monitor node in real rclpy graphs, no mocks: its own Context and domain id per test, rendered
DREAM Panda frames whose ground-truth joints play both the estimate and the robot's reported state (published by
a probe node, any order, the robot's own names), and one end-to-end chain DREAM replay -> estimator node (the small
untrained network) -> monitor, with the replay's ground truth as the robot's reported joints."""

from __future__ import annotations

import math
import os
import time

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import generate
from holo_pose_ros.monitoring import ERROR, OK, JointNameMap, wrap_angle, wrap_to_period
from holo_pose_ros.nodes.dream_replay_node import DreamReplayNode
from holo_pose_ros.nodes.estimator_node import EstimatorNode
from holo_pose_ros.nodes.joint_state_monitor_node import JointStateMonitorNode, main
from graph_helpers import domain_ids, spin_until
from msg_adapters import (joint_positions_by_name, joint_state_arrays, joint_state_from_arrays, make_header,
                          stamp_ns, to_diagnostic_status)

N_FRAMES = 3
MONITOR = "/joint_state_monitor"
ESTIMATE_TOPIC = "/holo_pose_estimator/joint_states"
PREFIX = "robot1/"  # the robot's joint names: robot1/<name>, and its gripper is robot1/gripper
GRIPPER = "robot1/gripper"
_DOMAINS = domain_ids(50, 99)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    folder = tmp_path_factory.mktemp("monitor_frames")
    generate("panda", N_FRAMES, folder, seed=11, workers=1, width=320, height=240, progress=False)
    return folder


@pytest.fixture(scope="module")
def joints(data) -> tuple[list[str], list[np.ndarray]]:
    """(joint names, ground-truth joints of each rendered frame)."""
    reader = DreamReader(data, "panda")
    return reader.robot.joint_names, [np.asarray(frame.joints, float) for frame in reader]


def test_joint_state_adapters_round_trip_and_pick_by_the_robots_names():
    header = make_header(12_345_000_000_123, "cam")
    msg = joint_state_from_arrays(["b/j2", "b/j1", "x"], [0.2, 0.1, 9.0], header)
    assert msg.header == header and msg.header is not header
    names, positions, stamp = joint_state_arrays(msg)
    assert names == ["b/j2", "b/j1", "x"] and positions.tolist() == [0.2, 0.1, 9.0] and stamp == 12_345_000_000_123
    selection, stamp = joint_positions_by_name(msg, ["j1", "j2", "j3"], JointNameMap(prefix="b/"))
    assert selection.values[:2].tolist() == [0.1, 0.2] and selection.missing == ("b/j3",) and selection.extra == 1
    assert selection.reordered and stamp == 12_345_000_000_123
    with pytest.raises(ValueError):
        joint_state_from_arrays(["a"], [1.0, 2.0], header)
    status = to_diagnostic_status(2, "n", "m", "hw", {"k": 1})
    assert status.level == DiagnosticStatus.ERROR and status.values[0].key == "k" and status.values[0].value == "1"


def monitor_statuses(messages: list[DiagnosticArray]) -> list[dict]:
    """The monitor's statuses on /diagnostics, each as {'level', 'message', **values}."""
    out = []
    for array in messages:
        for s in array.status:
            if s.name.startswith("joint_state_monitor:"):
                out.append({"level": s.level[0], "message": s.message, **{kv.key: kv.value for kv in s.values}})
    return out


class Graph:
    """One context: the monitor node(s) under test, other nodes, and a probe that publishes and records."""

    def __init__(self):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=next(_DOMAINS))
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes = []
        self.probe = self.add(rclpy.create_node("probe", context=self.context))
        self.received: dict[str, list] = {}

    def add(self, node):
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def record(self, name: str, kind, topic: str) -> list:
        self.received[name] = []
        self.probe.create_subscription(kind, topic, self.received[name].append, 50)
        return self.received[name]

    def spin_until(self, predicate, timeout: float = 10.0, action=None) -> bool:
        return spin_until(self.executor, predicate, timeout, action, period=0.05)

    def close(self) -> None:
        for node in reversed(self.nodes):
            node.destroy_node()
        self.executor.shutdown()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def graph():
    g = Graph()
    yield g
    g.close()


def monitor_node(graph: Graph, **params) -> JointStateMonitorNode:
    defaults = dict(estimate_topic=ESTIMATE_TOPIC, reported_topic="/robot1/joint_states", joint_name_prefix=PREFIX,
                    joint_name_map=f"panda_finger_joint1={GRIPPER}", persistence=3, report_timeout_s=1.0,
                    estimate_timeout_s=1.0, match_wait_s=0.3)
    overrides = [Parameter(k, value=v) for k, v in {**defaults, **params}.items()]
    return graph.add(JointStateMonitorNode(context=graph.context, parameter_overrides=overrides))


class Robot:
    """The probe's two streams of frame k (stamp 10 s + k x 100 ms): the "estimate" (the frame's ground truth, the
    estimator's names and order) and the robot's report (its own names, shuffled, with an extra joint)."""

    def __init__(self, graph: Graph, names: list[str], frames: list[np.ndarray]):
        self.names, self.frames, self.k = names, frames, 0
        self.estimates = graph.probe.create_publisher(JointState, ESTIMATE_TOPIC, 10)
        self.reports = graph.probe.create_publisher(JointState, "/robot1/joint_states", 10)
        self.robot_names = [GRIPPER if n == "panda_finger_joint1" else PREFIX + n for n in names]
        self.rng = np.random.default_rng(0)
        self.estimate_on, self.report_on, self.offset = True, True, {}  # offset: joint index -> radians

    def header(self, k: int):
        return make_header(10_000_000_000 + k * 100_000_000, "camera_color_optical_frame")

    def report(self, k: int, names=None, positions=None, stamp=None) -> None:
        q = self.frames[k % len(self.frames)].copy()
        for i, delta in self.offset.items():
            q[i] += delta
        names = names if names is not None else self.robot_names + [PREFIX + "panda_finger_joint2"]
        positions = positions if positions is not None else [*q, q[-1]]
        order = self.rng.permutation(len(names)) if len(names) == len(positions) else range(len(names))
        msg = JointState(header=stamp or self.header(k), name=[names[i] for i in order])
        msg.position = [float(positions[i]) for i in order] if len(names) == len(positions) else \
            [float(p) for p in positions]
        self.reports.publish(msg)

    def estimate(self, k: int, names=None, positions=None, stamp=None) -> None:
        q = self.frames[k % len(self.frames)]
        msg = JointState(header=stamp or self.header(k), name=list(names or self.names))
        msg.position = [float(p) for p in (q if positions is None else positions)]
        self.estimates.publish(msg)

    def step(self) -> None:
        """The next frame on the streams that are on (the report first, as a robot at a high rate sends it)."""
        if self.report_on:
            self.report(self.k)
        if self.estimate_on:
            self.estimate(self.k)
        self.k += 1


def test_monitor_ok_then_the_faulty_joint_then_not_reporting_then_not_seen(graph, joints):
    names, frames = joints
    # the shipped Panda card sets every threshold but panda_joint4's, given explicitly
    node = monitor_node(graph, model="panda", threshold_overrides="panda_joint4=0.3")
    by_name = {t.name: t for t in node.thresholds}
    assert by_name["panda_joint4"].warn == 0.3 and by_name["panda_joint4"].error == pytest.approx(0.6)
    assert all(t.source.startswith("card ") for n, t in by_name.items() if n != "panda_joint4")
    discrepancy = graph.record("discrepancy", JointState, f"{MONITOR}/discrepancy")
    relay = graph.record("relay", JointState, f"{MONITOR}/joint_states_estimated")
    diagnostics = graph.record("diagnostics", DiagnosticArray, "/diagnostics")
    robot = Robot(graph, names, frames)
    assert graph.spin_until(lambda: node.count_publishers(ESTIMATE_TOPIC) and
                            graph.probe.count_subscribers(f"{MONITOR}/discrepancy"))

    def lockstep(k: int) -> JointState:
        """Frame k on both streams; its discrepancy (the monitor waits for it and answers once)."""
        robot.k = k
        robot.step()
        stamp = stamp_ns(robot.header(k).stamp)
        assert graph.spin_until(lambda: any(stamp_ns(m.header.stamp) == stamp for m in discrepancy)), k
        return next(m for m in discrepancy if stamp_ns(m.header.stamp) == stamp)

    # reported = estimate (any order, an extra joint, the robot's own names): zero discrepancy, OK
    for k in range(4):
        d = lockstep(k)
        assert d.name == robot.robot_names and d.header.frame_id == "camera_color_optical_frame"
        np.testing.assert_allclose(d.position, 0.0, atol=1e-12)
        assert node.monitor.status(time.monotonic()).level == OK
    assert graph.spin_until(lambda: len(relay) >= 4)
    assert relay[0].name == robot.robot_names and relay[0].header == robot.header(0)
    np.testing.assert_allclose(relay[0].position, frames[0])
    seen = len(diagnostics)
    assert graph.spin_until(lambda: monitor_statuses(diagnostics[seen:]), timeout=3, action=robot.step)
    status = monitor_statuses(diagnostics[seen:])[-1]
    assert status["level"] == DiagnosticStatus.OK[0] and "agrees" in status["message"], status

    # the hand's roll reported half a turn away: it looks the same (the robot YAML's joint_symmetry_deg), so the
    # discrepancy is 0 modulo half a turn and nothing is raised
    assert by_name["panda_joint7"].period == pytest.approx(math.pi) and by_name["panda_joint7"].symmetric
    robot.offset = {6: math.pi}
    for k in range(50, 54):
        np.testing.assert_allclose(lockstep(k).position, 0.0, atol=1e-9)
        assert node.monitor.status(time.monotonic()).level == OK

    # from frame 100 the robot reports panda_joint4 1 rad away: nothing for 2 frames, ERROR at the 3rd, only it
    robot.offset = {3: 1.0}
    faults = []
    for k in range(100, 104):
        d = lockstep(k)
        expected = np.zeros(len(names))
        expected[3] = wrap_angle(-1.0)
        np.testing.assert_allclose(d.position, expected, atol=1e-9)
        faults.append(node.monitor.status(time.monotonic()).faults)
    assert faults == [{}, {}, {"panda_joint4": ERROR}, {"panda_joint4": ERROR}]
    seen = len(diagnostics)
    assert graph.spin_until(lambda: monitor_statuses(diagnostics[seen:]), timeout=3, action=robot.step)
    status = monitor_statuses(diagnostics[seen:])[-1]
    assert status["level"] == DiagnosticStatus.ERROR[0] and "panda_joint4 ERROR" in status["message"], status
    assert all(n not in status["message"] for n in names if n != "panda_joint4")
    assert status["panda_joint4 [rad]"].startswith("ERROR") and status["panda_joint1 [rad]"].startswith("OK")
    assert int(status["reported_extra"]) >= 1 and int(status["reported_reordered"]) >= 1

    # the robot stops reporting: "not reporting", the stale fault dropped, the estimate still relayed
    robot.report_on, robot.offset = False, {}
    seen, relayed = len(diagnostics), len(relay)
    not_reporting = lambda: any("robot not reporting" in s["message"]  # noqa: E731
                                for s in monitor_statuses(diagnostics[seen:]))
    assert graph.spin_until(not_reporting, timeout=4, action=robot.step)
    status = [s for s in monitor_statuses(diagnostics[seen:]) if "robot not reporting" in s["message"]][-1]
    assert status["level"] == DiagnosticStatus.WARN[0] and "panda_joint4" not in status["message"], status
    assert len(relay) > relayed

    # reporting again, but nothing estimated: "not seen"
    robot.report_on, robot.estimate_on = True, False
    seen = len(diagnostics)
    not_seen = lambda: any("robot not seen" in s["message"] for s in monitor_statuses(diagnostics[seen:]))  # noqa
    assert graph.spin_until(not_seen, timeout=4, action=robot.step)
    status = [s for s in monitor_statuses(diagnostics[seen:]) if "robot not seen" in s["message"]][-1]
    assert status["level"] == DiagnosticStatus.WARN[0] and "not reporting" not in status["message"], status


def test_bad_messages_are_handled_and_counted_never_a_crash(graph, joints):
    names, frames = joints
    node = monitor_node(graph, model="", persistence=2)
    discrepancy = graph.record("discrepancy", JointState, f"{MONITOR}/discrepancy")
    relay = graph.record("relay", JointState, f"{MONITOR}/joint_states_estimated")
    diagnostics = graph.record("diagnostics", DiagnosticArray, "/diagnostics")
    robot = Robot(graph, names, frames)
    assert {t.source for t in node.thresholds} == {"default"}  # no card
    assert graph.spin_until(lambda: node.count_publishers(ESTIMATE_TOPIC) and
                            graph.probe.count_subscribers(f"{MONITOR}/discrepancy"))
    q = frames[0]
    nan_q = q.copy()
    nan_q[1] = np.nan
    far_estimate = make_header(500_000_000_000, "camera_color_optical_frame")  # far from every reported stamp
    far_report = make_header(800_000_000_000, "camera_color_optical_frame")
    bad = [
        lambda: robot.report(0, positions=[*nan_q, 0.0]),                       # a NaN position
        lambda: robot.report(0, names=robot.robot_names[:5], positions=q[:5]),  # joints missing
        lambda: robot.report(0, names=robot.robot_names, positions=q[:3]),      # names/positions lengths differ
        lambda: robot.estimate(0, names=names[:2]),                             # malformed estimate
        lambda: robot.estimate(0, positions=nan_q),                             # a NaN in the estimate
        lambda: robot.estimate(2, stamp=far_estimate),                          # no reported state near it
        lambda: robot.report(3, stamp=far_report), lambda: robot.report(4),     # a far stamp, then back
        lambda: robot.estimate(4, names=names[::-1], positions=q[::-1]),        # estimate in reverse order
    ]
    for publish in bad:
        publish()
        graph.spin_until(lambda: False, timeout=0.05)
    counts = lambda: node.monitor.counters  # noqa: E731
    assert graph.spin_until(lambda: counts().unmatched >= 1 and counts().estimates_malformed >= 1
                            and counts().reported_malformed >= 1, timeout=3)
    c = counts()
    assert c.reported_nonfinite >= 1 and c.reported_missing >= 3 and c.estimate_nonfinite >= 1
    assert c.reported_restarts >= 1
    # still alive: good frames give zero discrepancies and an OK status with the counters
    for k in range(10, 13):
        robot.k = k
        robot.step()
    stamp = stamp_ns(robot.header(12).stamp)
    assert graph.spin_until(lambda: any(stamp_ns(m.header.stamp) == stamp for m in discrepancy))
    good = next(m for m in discrepancy if stamp_ns(m.header.stamp) == stamp)
    np.testing.assert_allclose(good.position, 0.0, atol=1e-12)
    first = stamp_ns(robot.header(0).stamp)
    [nan_frame] = [m for m in discrepancy if stamp_ns(m.header.stamp) == first]
    assert math.isnan(nan_frame.position[1]) and np.isfinite(nan_frame.position[0])
    [nan_relay] = [m for m in relay if stamp_ns(m.header.stamp) == first]
    assert nan_relay.name == robot.robot_names[:1] + robot.robot_names[2:]  # the NaN joint is not relayed
    reversed_frame = [m for m in discrepancy if stamp_ns(m.header.stamp) == stamp_ns(robot.header(4).stamp)]
    assert len(reversed_frame) == 1 and not any(m.header.stamp.sec == 500 for m in discrepancy)
    seen = len(diagnostics)
    assert graph.spin_until(lambda: monitor_statuses(diagnostics[seen:]), timeout=3, action=robot.step)
    status = monitor_statuses(diagnostics[seen:])[-1]
    assert status["level"] == DiagnosticStatus.OK[0], status
    for key in ("reported_nonfinite", "reported_missing", "reported_malformed", "estimates_malformed",
                "estimate_nonfinite", "unmatched", "reported_extra", "reported_reordered", "reported_restarts"):
        assert int(status[key]) >= 1, (key, status)


def test_estimate_only_relays_with_the_robots_names(graph, joints):
    names, frames = joints
    node = monitor_node(graph, reported_topic="", model="")
    relay = graph.record("relay", JointState, f"{MONITOR}/joint_states_estimated")
    diagnostics = graph.record("diagnostics", DiagnosticArray, "/diagnostics")
    robot = Robot(graph, names, frames)
    robot.report_on = False
    assert graph.spin_until(lambda: relay and monitor_statuses(diagnostics), timeout=4, action=robot.step)
    assert relay[0].name == robot.robot_names and relay[0].header == robot.header(0)
    status = monitor_statuses(diagnostics)[-1]
    assert status["level"] == DiagnosticStatus.OK[0] and "estimate only" in status["message"], status
    assert node.get_parameter("reported_topic").value == ""


def test_replay_estimator_monitor_end_to_end(graph, data, small_model_card):
    # the robot's report is the replay's ground truth (same header as the image): the discrepancy of each frame is
    # the estimator's joints minus the truth, wrapped
    replay = graph.add(DreamReplayNode(context=graph.context, parameter_overrides=[
        Parameter("folder", value=str(data)), Parameter("lockstep", value=True),
        Parameter("lockstep_timeout_s", value=20.0)]))
    graph.add(EstimatorNode(context=graph.context, parameter_overrides=[
        Parameter("model", value=str(small_model_card)), Parameter("device", value="cpu"),
        Parameter("backend", value="torch"), Parameter("threads", value=1), Parameter("min_confidence", value=0.0),
        Parameter("publish_annotated", value=False)]))
    monitor = monitor_node(graph, model=str(small_model_card), reported_topic="/dream_replay/ground_truth/joint_states",
                           joint_name_prefix="", joint_name_map="", estimate_timeout_s=30.0, report_timeout_s=30.0)
    estimates = graph.record("estimates", JointState, ESTIMATE_TOPIC)
    discrepancy = graph.record("discrepancy", JointState, f"{MONITOR}/discrepancy")
    relay = graph.record("relay", JointState, f"{MONITOR}/joint_states_estimated")
    diagnostics = graph.record("diagnostics", DiagnosticArray, "/diagnostics")
    assert graph.spin_until(lambda: replay.finished and len(discrepancy) >= N_FRAMES and len(relay) >= N_FRAMES,
                            timeout=40), (replay.sent, len(estimates), len(discrepancy))
    assert graph.spin_until(lambda: any(s["matched"] == str(N_FRAMES) for s in monitor_statuses(diagnostics)), 3)

    reader = DreamReader(data, "panda")
    truth = {stamp: np.asarray(frame.joints, float) for stamp, frame in zip(replay.stamps, reader)}
    kinds = monitor.monitor.kinds
    assert sorted(stamp_ns(m.header.stamp) for m in discrepancy) == replay.stamps
    for d in discrepancy:
        stamp = stamp_ns(d.header.stamp)
        [estimate] = [m for m in estimates if stamp_ns(m.header.stamp) == stamp]
        [relayed] = [m for m in relay if stamp_ns(m.header.stamp) == stamp]
        assert d.header == estimate.header == relayed.header and d.name == estimate.name == relayed.name
        expected = np.asarray(estimate.position) - truth[stamp]
        angular = np.array([k != "prismatic" for k in kinds])
        periods = np.array(monitor.monitor.periods)  # a turn; half of one for the hand's roll (its symmetry)
        expected[angular] = wrap_to_period(expected[angular], periods[angular])
        np.testing.assert_allclose(d.position, expected, atol=1e-9)
        np.testing.assert_allclose(relayed.position, estimate.position)


@pytest.mark.parametrize("param, reason", [
    ("joint_name_map:=nope=x", "joint name map: ['nope'] are not joints of the robot YAML"),
    ("threshold_overrides:=panda_joint1=fast", "threshold_overrides: panda_joint1=fast is not a number"),
    ("model:=kuka", "model 'kuka' is for robot 'kuka', but robot:=panda"),
], ids=["name_map", "override", "card_robot"])
def test_main_exits_1_with_the_reason(capfd, param, reason):
    assert main(["--ros-args", "-p", param]) == 1
    assert f"cannot start: {reason}" in capfd.readouterr().err
