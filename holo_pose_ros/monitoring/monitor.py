"""The joint-state monitor's core, no ROS: estimates (the estimator's joint states, stamped with their image) and
the robot's reported joint states in; per estimate, the discrepancy estimate - reported (the reported state nearest
the image stamp) out; per joint, a window and a debounced alarm level (discrepancy.py); a status that says OK /
WARN / ERROR, names the joints at fault and says when the robot is not reporting or not seen. Every input is
checked and counted, never trusted: joints by name in any order, extra joints ignored, missing joints and NaN
positions skipped, malformed messages and estimates with no reported state near their stamp counted.

Times: stamps in nanoseconds (the messages'), `now` in seconds of the caller's monotonic clock."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import Any, NamedTuple

import numpy as np

from holo_pose_ros.monitoring.discrepancy import ERROR, LEVEL_NAMES, OK, WARN, JointWatch
from holo_pose_ros.monitoring.joints import Selection, joint_difference, select_by_name
from holo_pose_ros.monitoring.stamps import NS, Match, StampMatcher
from holo_pose_ros.monitoring.thresholds import JointThreshold


@dataclass
class Counters:
    """Counts since start (the diagnostics' values). `*_missing` and `*_nonfinite` count joints (a message missing
    two joints adds 2), the others messages."""

    estimates: int = 0
    reported: int = 0
    matched: int = 0
    unmatched: int = 0  # estimates with no reported state within the stamp tolerance
    estimates_malformed: int = 0  # names and positions of different lengths: dropped
    reported_malformed: int = 0
    estimate_missing: int = 0
    estimate_nonfinite: int = 0
    reported_missing: int = 0
    reported_nonfinite: int = 0
    reported_extra: int = 0  # names that are none of the monitored joints (ignored)
    reported_duplicates: int = 0
    reported_reordered: int = 0  # messages whose joints come in another order than the robot YAML's (handled)
    reported_restarts: int = 0  # reported stamps that jumped back past the history (a looping bag, a sim reset)
    pending_dropped: int = 0  # estimates resolved early because too many waited

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class Discrepancy:
    """estimate - reported of one matched estimate: `values` (J,) in the monitor's joint order (radians wrapped to
    (-pi, pi], or to half the period of a symmetric joint; metres for prismatic joints; NaN where either side has no
    finite position), `tag` what the caller
    gave with the estimate (the node: its header), offset_ns = reported stamp - estimate stamp."""

    stamp_ns: int
    values: np.ndarray
    offset_ns: int
    tag: Any = None


class EstimateUpdate(NamedTuple):
    """What one estimate gives at once: its finite joints with the robot's names (the relay), and the discrepancies
    resolved meanwhile (of this estimate or of earlier ones)."""

    robot_names: list[str]
    positions: np.ndarray
    discrepancies: list[Discrepancy]


@dataclass
class Status:
    """The monitor's verdict: `level` (OK / WARN / ERROR as in diagnostic_msgs), `message`, `faults` (joint ->
    level, only the joints at WARN or ERROR), `values` (str -> str, the diagnostics' key/values)."""

    level: int
    message: str
    faults: dict[str, int] = field(default_factory=dict)
    not_reporting: bool = False
    not_seen: bool = False
    values: dict[str, str] = field(default_factory=dict)


def _fmt(x: float, digits: int = 4) -> str:
    return f"{x:.{digits}f}" if math.isfinite(x) else "nan"


class JointStateMonitor:
    """Compares the estimate with the robot's reported joint states; see the module docstring.

    joints: the monitored joints in the estimator's order (JointThreshold: name, kind, warn, error);
    robot_names: the robot's name of each (the name map); expect_reported: False for a robot that reports nothing
    (the estimate is relayed, nothing compared, no "not reporting")."""

    def __init__(self, joints: Sequence[JointThreshold], robot_names: Sequence[str] | None = None, *,
                 persistence: int = 3, window: int = 30, match_tolerance_s: float = 0.05, match_wait_s: float = 0.5,
                 history_s: float = 5.0, report_timeout_s: float = 1.0, estimate_timeout_s: float = 2.0,
                 expect_reported: bool = True, now: float = 0.0):
        self.joints = list(joints)
        self.names = [j.name for j in self.joints]
        self.kinds = [j.kind for j in self.joints]
        self.periods = [j.period for j in self.joints]
        self.robot_names = list(robot_names) if robot_names is not None else list(self.names)
        if len(self.robot_names) != len(self.names) or len(set(self.robot_names)) != len(self.names):
            raise ValueError("robot_names needs one distinct name per joint")
        if report_timeout_s <= 0 or estimate_timeout_s <= 0:
            raise ValueError("report_timeout_s and estimate_timeout_s must be > 0")
        self.watches = [JointWatch(j.name, j.warn, j.error, window, persistence) for j in self.joints]
        self.matcher = StampMatcher(match_tolerance_s, match_wait_s, history_s)
        self.report_timeout_s, self.estimate_timeout_s = float(report_timeout_s), float(estimate_timeout_s)
        self.expect_reported = expect_reported
        self.counters = Counters()
        self.started = now
        self.last_estimate: float | None = None  # arrival times (the caller's clock)
        self.last_reported: float | None = None
        self.persistence = int(persistence)
        self.unmatched_in_a_row = 0  # estimates resolved without a reported state since the last match
        self.last_offset_ns: int | None = None

    # -- inputs ---------------------------------------------------------------------------------------------------
    def add_estimate(self, names: Sequence[str], positions: Sequence[float], stamp_ns: int, now: float,
                     tag: Any = None) -> EstimateUpdate:
        """One estimate (the estimator's joint names). Returns the relay and the discrepancies resolved now."""
        try:
            sel = select_by_name(names, positions, self.names)
        except ValueError:
            self.counters.estimates_malformed += 1
            return EstimateUpdate([], np.zeros(0), self.poll(now))
        self.counters.estimates += 1
        self.counters.estimate_missing += len(sel.missing)
        self.counters.estimate_nonfinite += len(sel.nonfinite)
        self.last_estimate = now
        valid = sel.valid
        relay = EstimateUpdate([n for n, ok in zip(self.robot_names, valid) if ok], sel.values[valid], [])
        if not self.expect_reported:
            return relay
        return relay._replace(discrepancies=self._discrepancies(
            self.matcher.add_estimate(stamp_ns, (sel.values, tag), now), now))

    def add_reported(self, names: Sequence[str], positions: Sequence[float], stamp_ns: int,
                     now: float) -> list[Discrepancy]:
        """One reported joint state (the robot's joint names). Returns the discrepancies resolved now."""
        if not self.expect_reported:
            return []
        try:
            sel = select_by_name(names, positions, self.robot_names)
        except ValueError:
            self.counters.reported_malformed += 1
            return self.poll(now)
        c = self.counters
        c.reported += 1
        c.reported_missing += len(sel.missing)
        c.reported_nonfinite += len(sel.nonfinite)
        c.reported_extra += sel.extra
        c.reported_duplicates += sel.duplicates
        c.reported_reordered += int(sel.reordered)
        self.last_reported = now
        restarts = self.matcher.reported.resets
        matches = self.matcher.add_reported(stamp_ns, sel.values, now)
        c.reported_restarts += self.matcher.reported.resets - restarts
        return self._discrepancies(matches, now)

    def poll(self, now: float) -> list[Discrepancy]:
        """Resolve the estimates that have waited long enough for a reported state (call it periodically)."""
        return self._discrepancies(self.matcher.poll(now), now) if self.expect_reported else []

    def _discrepancies(self, matches: list[Match], now: float) -> list[Discrepancy]:
        self.counters.pending_dropped = self.matcher.dropped
        out = []
        for m in matches:
            if not m.matched:
                self.counters.unmatched += 1
                self.unmatched_in_a_row += 1
                continue
            estimate, tag = m.estimate
            d = joint_difference(estimate, m.reported, self.kinds, self.periods)
            for watch, value in zip(self.watches, d):
                watch.add(float(value))
            self.counters.matched += 1
            self.unmatched_in_a_row, self.last_offset_ns = 0, m.offset_ns
            out.append(Discrepancy(m.stamp_ns, d, m.offset_ns, tag))
        return out

    # -- verdict --------------------------------------------------------------------------------------------------
    def _age(self, last: float | None, now: float) -> float:
        """Seconds since `last` (since start when never)."""
        return now - (self.started if last is None else last)

    def status(self, now: float) -> Status:
        """The verdict now. When the robot is not reporting or not seen, the joints' frames are forgotten (their
        faults would be stale) and the status says why nothing is compared."""
        not_seen = self._age(self.last_estimate, now) > self.estimate_timeout_s
        not_reporting = self.expect_reported and self._age(self.last_reported, now) > self.report_timeout_s
        # both live, but the last `persistence` estimates found no reported state near their stamps (clocks apart?)
        unmatched = (self.expect_reported and not not_seen and not not_reporting
                     and self.unmatched_in_a_row >= self.persistence)
        problems, level = [], OK
        if not_seen or not_reporting or unmatched:
            for watch in self.watches:
                watch.reset()
        if not_seen:
            level = WARN
            problems.append(f"robot not seen: no estimate for {self._age(self.last_estimate, now):.1f} s")
        if not_reporting:
            level = WARN
            problems.append(f"robot not reporting: no reported joint states for "
                            f"{self._age(self.last_reported, now):.1f} s, the estimate is the only source")
        if unmatched:
            level = WARN
            problems.append(f"no reported state within {self.matcher.tolerance_ns / 1e6:g} ms of the image stamps "
                            f"({self.unmatched_in_a_row} estimates in a row): are the clocks apart?")
        faults = {w.name: w.level for w in self.watches if w.level > OK}
        if faults:
            level = max(level, *faults.values())
            worst_first = sorted(faults, key=lambda n: (-faults[n], self.names.index(n)))
            problems.insert(0, "joints at fault: " + ", ".join(self._fault_text(self.names.index(n))
                                                              for n in worst_first))
        if not problems:
            problems.append(self._ok_text())
        return Status(level, "; ".join(problems), faults, not_reporting, not_seen, self._values(now))

    def _fault_text(self, i: int) -> str:
        w, j = self.watches[i], self.joints[i]
        limit = w.error if w.level == ERROR else w.warn
        return f"{w.name} {LEVEL_NAMES[w.level]} (estimate - reported {w.last:+.3f} {j.unit}, |d| > {limit:.3f})"

    def _ok_text(self) -> str:
        if not self.expect_reported:
            return "estimate only: no reported joint states to compare with"
        if self.counters.matched == 0:
            return "waiting for estimates matched with reported joint states"
        watched = sum(w.window_size > 0 for w in self.watches)
        return f"estimate agrees with the reported joint states ({watched}/{len(self.watches)} joints compared)"

    def _values(self, now: float) -> dict[str, str]:
        values = {k: str(v) for k, v in self.counters.as_dict().items()}
        for key, last in (("estimate_age_s", self.last_estimate), ("reported_age_s", self.last_reported)):
            values[key] = "never" if last is None else _fmt(now - last, 2)
        values["match_offset_ms"] = "nan" if self.last_offset_ns is None else _fmt(self.last_offset_ns / 1e6, 2)
        values["waiting_estimates"] = str(self.matcher.pending)
        for w, j in zip(self.watches, self.joints):
            key = f"{w.name} [{j.unit}]"
            values[key] = (f"{LEVEL_NAMES[w.level]} last {_fmt(w.last)} mean_abs {_fmt(w.mean_abs)} max_abs "
                           f"{_fmt(w.max_abs)} warn {_fmt(w.warn)} error {_fmt(w.error)} skipped {w.skipped}")
        return values
