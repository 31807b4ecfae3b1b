"""The joint-state monitor's ROS-free core (holo_pose_ros.monitoring): joints by name, wrap-around, matching by
stamp, the persistence of alarms, timeouts, thresholds from the model card, and every malformed input counted."""

import math

import numpy as np
import pytest
import yaml

from holo_pose_ros.model.cards import read_card
from holo_pose_ros.monitoring import (ERROR, OK, WARN, JointNameMap, JointStateMonitor, JointThreshold, JointWatch,
                                      StampBuffer, StampMatcher, card_joint_errors, joint_difference, joint_kinds,
                                      joint_thresholds, parse_overrides, parse_pairs, select_by_name,
                                      wrap_angle, wrap_to_period)
from holo_pose_ros.resources import config_dir
from holo_pose_ros.robots.spec import load_robot_spec

MS = 1_000_000  # ns
NAMES = ["j1", "j2", "j3", "finger"]
KINDS = ["revolute", "revolute", "continuous", "prismatic"]


def thresholds(warn_rad=0.1, warn_m=0.01, error_factor=2.0):
    return [JointThreshold(n, k, warn_m if k == "prismatic" else warn_rad,
                           error_factor * (warn_m if k == "prismatic" else warn_rad), "test")
            for n, k in zip(NAMES, KINDS)]


# -- joints -------------------------------------------------------------------------------------------------------
def test_wrap_angle_is_half_open_and_keeps_nan():
    angles = np.array([0.0, math.pi, -math.pi, 3 * math.pi, -3 * math.pi, 2 * math.pi, 0.5 + 4 * math.pi, np.nan])
    wrapped = wrap_angle(angles)
    np.testing.assert_allclose(wrapped[:7], [0.0, math.pi, math.pi, math.pi, math.pi, 0.0, 0.5], atol=1e-12)
    assert np.isnan(wrapped[7])
    x = np.linspace(-20, 20, 1001)
    w = wrap_angle(x)
    assert np.all(w > -math.pi) and np.all(w <= math.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(x), atol=1e-9)
    np.testing.assert_allclose(np.sin(w), np.sin(x), atol=1e-9)


def test_joint_difference_wraps_angles_only():
    # 179 deg - (-179 deg) is -2 deg, not 358; the finger (metres) never wraps
    a = np.radians([179.0, -170.0, 10.0, 0.0])
    b = np.radians([-179.0, 170.0, 10.0 + 360.0, 0.0])
    a[3], b[3] = 7.0, 0.5
    d = joint_difference(a, b, KINDS)
    np.testing.assert_allclose(d, [math.radians(-2.0), math.radians(20.0), 0.0, 6.5], atol=1e-12)


def test_a_symmetric_joint_is_compared_modulo_its_period():
    # j3 looks the same after half a turn: 190 deg apart is 10 deg; 100 deg apart is -80 deg; j1 still wraps at a turn
    a = np.radians([190.0, 0.0, 190.0, 0.0])
    b = np.radians([0.0, 0.0, 0.0, 0.0])
    periods = [2 * math.pi, 2 * math.pi, math.pi, 2 * math.pi]
    np.testing.assert_allclose(np.degrees(joint_difference(a, b, KINDS, periods)), [-170.0, 0.0, 10.0, 0.0],
                               atol=1e-9)
    a[2] = math.radians(100.0)
    assert math.degrees(joint_difference(a, b, KINDS, periods)[2]) == pytest.approx(-80.0)
    w = wrap_to_period(np.linspace(-10, 10, 401), math.pi / 2)
    assert np.all(w > -math.pi / 4) and np.all(w <= math.pi / 4 + 1e-12)
    np.testing.assert_allclose(wrap_to_period([1.0, np.nan], 2 * math.pi)[:1], wrap_angle([1.0]))
    # the monitor: half a turn off on the symmetric joint raises nothing, a quarter turn (beyond its WARN) does
    joints = [JointThreshold(n, k, 0.1, 0.2, "test", math.pi if n == "j3" else 2 * math.pi)
              for n, k in zip(NAMES, KINDS)]
    assert joints[2].symmetric and not joints[0].symmetric
    mon = JointStateMonitor(joints, persistence=2, now=0.0)
    reported = np.array([0.0, 0.0, 0.5, 0.0])
    for i in range(3):
        mon.add_reported(NAMES, reported, i * 100 * MS, 0.1 * i)
        mon.add_estimate(NAMES, reported + [0.0, 0.0, math.pi, 0.0], i * 100 * MS, 0.1 * i + 0.01)
    assert mon.status(0.3).level == OK
    for i in range(3, 6):
        mon.add_reported(NAMES, reported, i * 100 * MS, 0.1 * i)
        mon.add_estimate(NAMES, reported + [0.0, 0.0, math.pi + 0.15, 0.0], i * 100 * MS, 0.1 * i + 0.01)
    status = mon.status(0.6)
    assert status.level == WARN and status.faults == {"j3": WARN}


def test_select_by_name_any_order_extra_missing_nonfinite_duplicates():
    sel = select_by_name(["finger", "extra", "j2", "j1", "j2"], [0.01, 5.0, np.nan, 0.3, 9.0], NAMES)
    assert np.isnan(sel.values[1]) and np.isnan(sel.values[2])
    np.testing.assert_allclose(sel.values[[0, 3]], [0.3, 0.01])
    assert sel.missing == ("j3",) and sel.nonfinite == ("j2",) and sel.extra == 1 and sel.duplicates == 1
    assert sel.reordered
    assert not select_by_name(NAMES, [0, 0, 0, 0], NAMES).reordered
    assert not select_by_name(["j1", "x", "j3"], [0, 0, np.inf], NAMES).reordered  # gaps are not a reorder
    assert select_by_name(["j1", "x", "j3"], [0, 0, np.inf], NAMES).nonfinite == ("j3",)
    with pytest.raises(ValueError, match="2 joint names but 1 positions"):
        select_by_name(["j1", "j2"], [0.0], NAMES)


def test_name_map_prefix_entries_and_errors():
    m = JointNameMap.parse("j1=shoulder, finger=gripper", prefix="left/")
    assert m.robot_names(NAMES) == ["shoulder", "left/j2", "left/j3", "gripper"]
    assert JointNameMap().robot_names(NAMES) == NAMES
    with pytest.raises(ValueError, match="not joints"):
        JointNameMap.parse("nope=x").robot_names(NAMES)
    with pytest.raises(ValueError, match="several joints map"):
        JointNameMap.parse("j1=j2").robot_names(NAMES)
    with pytest.raises(ValueError, match="not name=value"):
        parse_pairs("j1=a, j2", "joint_name_map")
    with pytest.raises(ValueError, match="twice"):
        parse_pairs("j1=a j1=b", "joint_name_map")
    assert parse_pairs(" , ", "x") == {}
    assert parse_overrides({"j1": "0.25"}) == {"j1": 0.25}
    with pytest.raises(ValueError, match="not a number"):
        parse_overrides({"j1": "abc"})


# -- matching by stamp --------------------------------------------------------------------------------------------
def test_stamp_buffer_nearest_within_tolerance_history_and_restart():
    buf = StampBuffer(history_s=1.0)
    for t in (100, 110, 120, 130):
        buf.add(t * MS, t)
    assert buf.nearest(114 * MS, 5 * MS) == (110 * MS, 110)
    assert buf.nearest(116 * MS, 5 * MS) == (120 * MS, 120)
    assert buf.nearest(115 * MS, 5 * MS) == (110 * MS, 110)  # a tie: the earlier
    assert buf.nearest(200 * MS, 5 * MS) is None and buf.nearest(50 * MS, 5 * MS) is None
    buf.add(105 * MS, 105)  # out of order: kept in stamp order
    assert buf.nearest(104 * MS, 2 * MS) == (105 * MS, 105)
    buf.add(1200 * MS, 1200)  # history: everything older than 200 ms is dropped
    assert len(buf) == 1 and buf.nearest(130 * MS, 5 * MS) is None
    buf.add(10 * MS, 10)  # far back: the stream started over
    assert buf.resets == 1 and len(buf) == 1 and buf.newest_ns == 10 * MS


def test_matcher_waits_for_a_later_reported_stamp_or_the_wait():
    m = StampMatcher(tolerance_s=0.02, wait_s=0.5, history_s=5.0)
    # the estimate arrives first: it waits, and the reported state of its stamp resolves it
    assert m.add_estimate(100 * MS, "e100", now=0.0) == []
    assert m.add_reported(95 * MS, "r95", now=0.01) == []  # before the stamp: a nearer one may still come
    [match] = m.add_reported(101 * MS, "r101", now=0.02)
    assert (match.estimate, match.reported, match.offset_ns) == ("e100", "r101", MS)
    # the reported state already there: resolved at once
    [match] = m.add_estimate(96 * MS, "e96", now=0.03)
    assert match.reported == "r95" and match.offset_ns == -MS
    # nothing near the stamp: unmatched once the wait is over
    assert m.add_estimate(500 * MS, "e500", now=1.0) == []
    assert m.poll(now=1.2) == []
    [match] = m.poll(now=1.6)
    assert not match.matched and match.offset_ns is None
    # a stamp far before every reported state: resolved at once, unmatched
    [match] = m.add_estimate(10 * MS, "e10", now=2.0)
    assert not match.matched and m.pending == 0


def test_matcher_bounds_its_waiting_estimates():
    m = StampMatcher(tolerance_s=0.01, wait_s=10.0, history_s=5.0, max_pending=3)
    out = [match for k in range(5) for match in m.add_estimate(k * MS, k, now=0.0)]
    assert [o.estimate for o in out] == [0, 1] and m.dropped == 2 and m.pending == 3


# -- persistence --------------------------------------------------------------------------------------------------
def test_one_bad_frame_raises_nothing_k_in_a_row_raise_and_k_good_clear():
    w = JointWatch("j1", warn=0.1, error=0.2, persistence=3)
    for d in (0.0, 0.5, 0.0, 0.5, 0.5, 0.0, 0.15):
        assert w.add(d) == OK
    assert w.add(0.15) == OK and w.add(0.15) == WARN  # three WARN frames in a row (0.15, 0.15, 0.15)
    assert w.add(0.5) == WARN and w.add(0.5) == WARN and w.add(0.5) == ERROR
    assert w.add(0.0) == ERROR and w.add(float("nan")) == ERROR  # NaN: skipped, neither raises nor clears
    assert w.add(0.15) == ERROR and w.add(0.15) == WARN  # (0.0, 0.15, 0.15): all at or below WARN
    assert w.add(0.0) == WARN and w.add(0.0) == WARN and w.add(0.0) == OK
    assert w.skipped == 1 and w.samples == 18
    assert w.max_abs == pytest.approx(0.5) and w.last == 0.0
    w.reset()
    assert w.level == OK and math.isnan(w.mean_abs)
    assert JointWatch("j", 0.1, 0.2, persistence=1).add(0.3) == ERROR
    with pytest.raises(ValueError):
        JointWatch("j", 0.2, 0.1)


def feed(monitor, k, estimate, reported, now, names=NAMES, reported_names=None, offset_ns=0):
    """One frame k: stamp k x 100 ms, the reported state first (as a robot at a high rate does), then the estimate."""
    stamp = k * 100 * MS
    out = monitor.add_reported(reported_names or names, reported, stamp + offset_ns, now)
    return out + monitor.add_estimate(names, estimate, stamp, now + 0.05, tag=k).discrepancies


def test_monitor_raises_only_the_faulty_joint_within_persistence_frames():
    mon = JointStateMonitor(thresholds(), persistence=3, now=0.0)
    q = np.array([0.5, -1.0, 3.1, 0.02])
    for k in range(5):
        [d] = feed(mon, k, q, q, now=k * 0.1)
        assert d.tag == k and np.allclose(d.values, 0.0)
        assert mon.status(k * 0.1 + 0.06).level == OK
    status = mon.status(0.6)
    assert status.level == OK and "agrees" in status.message and status.values["matched"] == "5"
    # from frame 5: j2 reported 0.5 rad away (above the ERROR threshold of 0.2): ERROR after exactly 3 frames
    levels = []
    for k in range(5, 10):
        reported = q.copy()
        reported[1] += 0.5
        [d] = feed(mon, k, q, reported, now=k * 0.1)
        assert d.values[1] == pytest.approx(-0.5) and np.allclose(d.values[[0, 2, 3]], 0.0)
        levels.append(mon.status(k * 0.1 + 0.06).level)
    assert levels == [OK, OK, ERROR, ERROR, ERROR]
    status = mon.status(1.0)
    assert status.faults == {"j2": ERROR} and "j2 ERROR" in status.message
    assert all(name not in status.message for name in ("j1", "j3", "finger"))
    assert status.values["j2 [rad]"].startswith("ERROR")


def test_monitor_wraps_revolute_discrepancies():
    mon = JointStateMonitor(thresholds(), persistence=1, now=0.0)
    estimate = np.array([math.pi - 0.01, -math.pi + 0.01, 0.0, 0.0])
    reported = np.array([-math.pi + 0.01, math.pi - 0.01, 2 * math.pi, 0.0])
    [d] = feed(mon, 0, estimate, reported, now=0.0)
    np.testing.assert_allclose(d.values, [-0.02, 0.02, 0.0, 0.0], atol=1e-9)
    assert mon.status(0.1).level == OK


def test_monitor_timeouts_not_reporting_not_seen_and_clocks_apart():
    mon = JointStateMonitor(thresholds(), persistence=2, report_timeout_s=1.0, estimate_timeout_s=2.0, now=0.0)
    q = np.zeros(4)
    assert mon.status(0.5).level == OK  # nothing yet, within the timeouts
    status = mon.status(2.5)
    assert status.not_reporting and status.not_seen and status.level == WARN
    assert "robot not reporting" in status.message and "robot not seen" in status.message
    # a fault, then the reported stream stops: after report_timeout_s "not reporting", the stale fault is dropped
    for k in range(3):
        reported = q.copy()
        reported[0] = 1.0
        feed(mon, k, q, reported, now=3.0 + 0.1 * k)
    assert mon.status(3.3).faults == {"j1": ERROR}
    for k in range(3, 10):  # estimates go on, nothing reported
        mon.add_estimate(NAMES, q, k * 100 * MS, now=3.0 + 0.1 * k)
    status = mon.status(4.3)  # the last reported state came at 3.2 s
    assert status.not_reporting and not status.not_seen and status.faults == {} and status.level == WARN
    assert "the estimate is the only source" in status.message
    assert mon.poll(10.0) == [] and mon.counters.unmatched == 7 and mon.matcher.pending == 0  # waited: unmatched
    # reported again, estimates stopped: "not seen"
    mon.add_reported(NAMES, q, 2000 * MS, now=6.0)
    status = mon.status(6.1)
    assert status.not_seen and not status.not_reporting and "robot not seen" in status.message
    # both live but 100 s apart: every estimate unmatched -> a WARN that says so
    for k in range(3):
        mon.add_reported(NAMES, q, (100_000 + k * 100) * MS, now=7.0 + 0.1 * k)
        mon.add_estimate(NAMES, q, (k * 100) * MS, now=7.0 + 0.1 * k)
    status = mon.status(7.3)
    assert status.level == WARN and "no reported state within 50 ms" in status.message, status.message
    assert int(status.values["unmatched"]) >= 3


def test_monitor_counts_nan_missing_extra_reordered_malformed_and_survives():
    names = ["left/j1", "left/j2", "left/j3", "left/finger"]
    mon = JointStateMonitor(thresholds(), names, persistence=1, now=0.0)
    q = np.array([0.1, 0.2, 0.3, 0.01])
    stamp = 100 * MS
    mon.add_reported(["left/finger", "left/j3", "other", "left/j1"], [0.01, np.nan, 9.0, 0.1], stamp, 0.0)
    update = mon.add_estimate(NAMES, q, stamp, 0.01, tag="h")
    assert update.robot_names == names  # the relay: the robot's names
    [d] = update.discrepancies
    assert np.isnan(d.values[1]) and np.isnan(d.values[2]) and np.allclose(d.values[[0, 3]], 0.0)
    assert mon.add_reported(["left/j1"], [0.1, 0.2], stamp, 0.02) == []  # malformed
    update = mon.add_estimate(["j1", "j2"], [0.1], stamp, 0.03)  # malformed
    assert update.robot_names == [] and update.discrepancies == []
    update = mon.add_estimate(["j2", "j1"], [np.nan, 0.1], 200 * MS, 0.04)  # missing and NaN joints
    assert update.robot_names == ["left/j1"] and update.positions.tolist() == [0.1]
    mon.add_reported(names, q, 2 * stamp, 0.05)
    c = mon.counters
    assert (c.reported, c.reported_malformed, c.estimates, c.estimates_malformed) == (2, 1, 2, 1)
    assert (c.reported_missing, c.reported_nonfinite, c.reported_extra, c.reported_reordered) == (1, 1, 1, 1)
    assert (c.estimate_missing, c.estimate_nonfinite, c.matched) == (2, 1, 2)
    status = mon.status(0.1)
    assert status.level == OK and status.values["reported_extra"] == "1"
    assert status.values["j2 [rad]"].endswith("skipped 2")


def test_estimate_only_relays_and_never_warns_about_reporting():
    mon = JointStateMonitor(thresholds(), expect_reported=False, now=0.0)
    update = mon.add_estimate(NAMES, np.zeros(4), 0, 0.1)
    assert update.robot_names == NAMES and update.discrepancies == []
    status = mon.status(1.5)
    assert status.level == OK and not status.not_reporting and "estimate only" in status.message
    assert mon.status(5.0).not_seen


# -- thresholds ---------------------------------------------------------------------------------------------------
def test_thresholds_from_the_shipped_card_overrides_and_defaults():
    spec = load_robot_spec("panda")
    kinds = joint_kinds(spec)
    assert kinds == ["revolute"] * 7 + ["prismatic"]
    _, card = read_card("panda")
    measured = card_joint_errors(card, spec.joint_names)
    for name in spec.joint_names:  # the largest of the card's held-out means, in radians / metres
        tests = card["test"].values()
        scale = 1e-3 if name == "panda_finger_joint1" else math.pi / 180
        assert measured[name].value == pytest.approx(max(t["joint_error_deg"][name] for t in tests) * scale)
    photo = card_joint_errors(card, spec.joint_names, "photo")
    assert photo["panda_joint4"].value == pytest.approx(card["test"]["photo"]["joint_error_deg"]["panda_joint4"]
                                                        * math.pi / 180)
    with pytest.raises(ValueError, match="no test set"):
        card_joint_errors(card, spec.joint_names, "nope")
    t = joint_thresholds(spec.joint_names, kinds, measured, factor=3.0, error_factor=2.0,
                         overrides={"panda_joint1": 0.2})
    by_name = {x.name: x for x in t}
    assert by_name["panda_joint1"].warn == 0.2 and by_name["panda_joint1"].source == "override"
    assert by_name["panda_joint4"].warn == pytest.approx(3 * measured["panda_joint4"].value)
    assert by_name["panda_joint4"].error == pytest.approx(2 * by_name["panda_joint4"].warn)
    assert by_name["panda_finger_joint1"].unit == "m" and by_name["panda_finger_joint1"].can_error
    # no measurement (a card without a test section): the defaults of the joint's kind
    t = joint_thresholds(spec.joint_names, kinds, card_joint_errors({}, spec.joint_names), default_rad=0.3,
                         default_m=0.01)
    assert [x.warn for x in t] == [0.3] * 7 + [0.01] and {x.source for x in t} == {"default"}
    assert not JointThreshold("j", "revolute", 3.2, 6.4, "x").can_warn
    with pytest.raises(ValueError, match="not joints"):
        joint_thresholds(spec.joint_names, kinds, {}, overrides={"nope": 0.1})
    with pytest.raises(ValueError, match="finite and > 0"):
        joint_thresholds(spec.joint_names, kinds, {}, overrides={"panda_joint1": -1.0})


def test_a_symmetric_joints_threshold_comes_from_its_error_modulo_the_symmetry():
    """The Panda hand's roll (joint_symmetry_deg in the robot YAML): its threshold is 3 x the card's error modulo half a
    turn where the card measures it, and it can warn only below a quarter turn."""
    spec = load_robot_spec("panda")
    assert spec.joint_symmetry == {"panda_joint7": pytest.approx(math.pi)}
    kinds = joint_kinds(spec)
    card = {"test": {"unseen": {"joint_error_deg": {"panda_joint7": 70.0, "panda_joint1": 30.0},
                                "joint_error_modulo_symmetry_deg": {"panda_joint7": 20.0,
                                                                    "period_deg": {"panda_joint7": 180.0}}},
                     "photo": {"joint_error_deg": {"panda_joint7": 60.0, "panda_joint1": 10.0}}}}
    measured = card_joint_errors(card, spec.joint_names, "unseen", list(spec.joint_symmetry))
    assert measured["panda_joint7"].value == pytest.approx(math.radians(20.0)) and measured["panda_joint7"].modulo_symmetry
    # every set: the modulo measure of the sets that have it wins over a plain one, however large
    assert card_joint_errors(card, spec.joint_names, "", list(spec.joint_symmetry))["panda_joint7"].value == \
        pytest.approx(math.radians(20.0))
    assert card_joint_errors(card, spec.joint_names)["panda_joint7"].value == pytest.approx(math.radians(70.0))
    # a card without the modulo measure (the photo set here): the plain error
    photo = card_joint_errors(card, spec.joint_names, "photo", list(spec.joint_symmetry))
    assert photo["panda_joint7"].value == pytest.approx(math.radians(60.0)) and not photo["panda_joint7"].modulo_symmetry
    t = {x.name: x for x in joint_thresholds(spec.joint_names, kinds, measured, factor=3.0,
                                             periods=spec.joint_symmetry)}
    hand = t["panda_joint7"]
    assert hand.warn == pytest.approx(math.radians(60.0)) and hand.period == pytest.approx(math.pi)
    assert hand.can_warn and not hand.can_error and "modulo the symmetry" in hand.source  # ERROR 120 deg > 90
    assert not t["panda_joint1"].symmetric and t["panda_joint1"].period == pytest.approx(2 * math.pi)
    blind = joint_thresholds(spec.joint_names, kinds, photo, factor=3.0, periods=spec.joint_symmetry)
    assert not {x.name: x for x in blind}["panda_joint7"].can_warn  # 3 x 60 deg is beyond a quarter turn
    with pytest.raises(ValueError, match="angular joint"):
        joint_thresholds(spec.joint_names, kinds, {}, periods={"panda_finger_joint1": 1.0})
    with pytest.raises(ValueError, match="not a joint"):
        joint_thresholds(spec.joint_names, kinds, {}, periods={"nope": 1.0})


@pytest.mark.parametrize("entry, message", [({"panda_joint9": 180}, "names 'panda_joint9', which is not one of"),
                                            ({"panda_joint7": 0}, "0 is not in \\(0, 360\\] degrees"),
                                            ({"panda_joint7": "half"}, "'half' is not a number"),
                                            ([180], "must map joint names")])
def test_a_bad_joint_symmetry_names_the_yaml_and_the_joint(tmp_path, entry, message):
    data = yaml.safe_load((config_dir() / "robots" / "panda.yaml").read_text())
    data["joint_symmetry_deg"] = entry
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match="robot.yaml: .*" + message):
        load_robot_spec(path)

