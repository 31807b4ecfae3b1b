"""Per-joint alarm thresholds of the monitor, from the loaded model's card: the held-out mean joint error the card
measured (its `test:` section, `joint_error_deg`: degrees, millimetres for prismatic joints) times a factor is the
WARN threshold, `error_factor` times that the ERROR threshold; a joint the card does not measure gets a default,
and any joint an explicit override. A joint that looks the same after part of a turn (the robot YAML's
joint_symmetry_deg) is compared modulo that period, with the card's error modulo it. Radians and metres out. Reads
the card's YAML only (no torch)."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from holo_pose_ros.monitoring.joints import ANGULAR_KINDS, LINEAR_KINDS, parse_pairs
from holo_pose_ros.robots.description import urdf_text
from holo_pose_ros.robots.spec import RobotSpec

CARD_UNITS = {"deg": math.pi / 180.0, "mm": 1e-3}  # the card's units -> radians, metres


def joint_kinds(spec: RobotSpec) -> list[str]:
    """The URDF joint type ('revolute', 'continuous' or 'prismatic') of each of the robot YAML's joints, read from
    the URDF's XML (light: no mesh or kinematics library)."""
    root = ET.fromstring(urdf_text(spec.urdf))
    types = {j.get("name"): j.get("type") for j in root.iter("joint")}
    kinds = []
    for joint in spec.joints:
        kind = types.get(joint.urdf)
        if kind is None:
            raise ValueError(f"{spec.source_file}: joint '{joint.name}' drives URDF joint '{joint.urdf}', which the "
                             "URDF does not have")
        if kind not in ANGULAR_KINDS + LINEAR_KINDS:
            raise ValueError(f"{spec.source_file}: URDF joint '{joint.urdf}' is {kind}; the monitor handles "
                             f"{', '.join(ANGULAR_KINDS + LINEAR_KINDS)} joints")
        kinds.append(kind)
    return kinds


@dataclass(frozen=True)
class MeasuredError:
    """A card's held-out mean |error| of one joint: `value` in radians (metres for prismatic joints), measured on
    the card's test set `test_set`; `modulo_symmetry`: measured modulo the joint's symmetry period (the card's
    `joint_error_modulo_symmetry_deg`)."""

    value: float
    test_set: str
    modulo_symmetry: bool = False


def card_joint_errors(card: Mapping, joint_names: Sequence[str], test_set: str = "",
                      symmetric: Sequence[str] = ()) -> dict[str, MeasuredError]:
    """The held-out mean error per joint from the card's `test: <set>: joint_error_deg:` (per joint, with `units`);
    for the joints named in `symmetric` (the robot YAML's joint_symmetry_deg) the error modulo the symmetry,
    `joint_error_modulo_symmetry_deg:`, where the card has it. `test_set` '' takes, per joint, the largest over the
    card's test sets, so that an alarm means more than the model's error on any of its held-out looks (for a
    symmetric joint, over the sets that measure it modulo the symmetry, where any does); otherwise that set only
    (ValueError when the card has none of that name). Joints the card does not measure (or measures as NaN / null)
    are left out."""
    tests = card.get("test") or {}
    if not isinstance(tests, Mapping):
        return {}
    if test_set:
        if test_set not in tests:
            raise ValueError(f"the model card has no test set '{test_set}'; it has: {', '.join(tests) or 'none'}")
        tests = {test_set: tests[test_set]}
    errors: dict[str, MeasuredError] = {}
    for set_name, section in tests.items():
        joints = (section or {}).get("joint_error_deg") if isinstance(section, Mapping) else None
        if not isinstance(joints, Mapping):
            continue
        units = joints.get("units") or {}
        modulo = section.get("joint_error_modulo_symmetry_deg") or {}
        for name in joint_names:
            value, unit, is_modulo = joints.get(name), units.get(name, "deg"), False
            if name in symmetric and isinstance(modulo, Mapping) and isinstance(modulo.get(name), (int, float)):
                value, unit, is_modulo = modulo[name], "deg", True
            if not isinstance(value, (int, float)) or not math.isfinite(value) or unit not in CARD_UNITS:
                continue
            measured = MeasuredError(float(value) * CARD_UNITS[unit], str(set_name), is_modulo)
            # the largest; an error modulo the symmetry before any plain one (a card rescored on some looks only)
            if name not in errors or ((measured.modulo_symmetry, measured.value)
                                      > (errors[name].modulo_symmetry, errors[name].value)):
                errors[name] = measured
    return errors


@dataclass(frozen=True)
class JointThreshold:
    """A joint's alarm thresholds on |estimate - reported| (radians, metres for prismatic joints) and where the WARN
    threshold came from ('card <set>: 3 x 0.295', 'override', 'default'). `period` (radians): an angular joint's
    discrepancy is wrapped to (-period/2, period/2], a full turn unless the joint looks the same after less
    (the robot YAML's joint_symmetry_deg: the hand's roll, half a turn)."""

    name: str
    kind: str
    warn: float
    error: float
    source: str
    period: float = 2.0 * math.pi

    @property
    def unit(self) -> str:
        return "m" if self.kind in LINEAR_KINDS else "rad"

    @property
    def symmetric(self) -> bool:
        """True for an angular joint compared modulo less than a turn."""
        return self.kind not in LINEAR_KINDS and self.period < 2.0 * math.pi

    @property
    def can_warn(self) -> bool:
        """False for an angular joint whose WARN threshold is half its period (pi) or more: a wrapped discrepancy
        never exceeds it."""
        return self.kind in LINEAR_KINDS or self.warn < self.period / 2.0

    @property
    def can_error(self) -> bool:
        return self.kind in LINEAR_KINDS or self.error < self.period / 2.0


def joint_thresholds(joint_names: Sequence[str], kinds: Sequence[str], measured: Mapping[str, MeasuredError],
                     factor: float = 3.0, error_factor: float = 2.0, default_rad: float = 0.35,
                     default_m: float = 0.02, overrides: Mapping[str, float] | None = None,
                     periods: Mapping[str, float] | None = None) -> list[JointThreshold]:
    """WARN = an override, else `factor` x the card's measured error, else the default of the joint's kind;
    ERROR = `error_factor` x WARN. `periods` (joint -> radians, the robot YAML's joint_symmetry): the joints compared
    modulo less than a turn. ValueError for an override or period naming no joint, a period on a prismatic joint,
    or a threshold that is not > 0."""
    overrides, periods = dict(overrides or {}), dict(periods or {})
    for name, period in periods.items():
        if name not in joint_names:
            raise ValueError(f"joint symmetry: '{name}' is not a joint of the robot YAML ({', '.join(joint_names)})")
        if kinds[list(joint_names).index(name)] in LINEAR_KINDS or not 0.0 < period <= 2.0 * math.pi:
            raise ValueError(f"joint symmetry: '{name}' needs an angular joint and a period in (0, 2 pi] rad")
    unknown = sorted(set(overrides) - set(joint_names))
    if unknown:
        raise ValueError(f"threshold overrides: {unknown} are not joints of the robot YAML ({', '.join(joint_names)})")
    if not (factor > 0 and error_factor >= 1 and default_rad > 0 and default_m > 0):
        raise ValueError("threshold_factor and the defaults must be > 0, error_factor >= 1")
    out = []
    for name, kind in zip(joint_names, kinds, strict=True):
        if name in overrides:
            warn, source = float(overrides[name]), "override"
        elif name in measured:
            warn = factor * measured[name].value
            source = (f"card {measured[name].test_set}: {factor:g} x {measured[name].value:.4g}"
                      + (" modulo the symmetry" if measured[name].modulo_symmetry else ""))
        else:
            warn, source = (default_m if kind in LINEAR_KINDS else default_rad), "default"
        if not (math.isfinite(warn) and warn > 0):
            raise ValueError(f"{name}: threshold {warn} ({source}) must be finite and > 0")
        out.append(JointThreshold(name, kind, warn, error_factor * warn, source, periods.get(name, 2.0 * math.pi)))
    return out


def node_thresholds(spec: RobotSpec, card: Mapping | None, params: Mapping) -> list[JointThreshold]:
    """The thresholds as the joint-state monitor node makes them from its parameters (`params`: card_test_set,
    threshold_factor, error_factor, default_threshold_rad, default_threshold_m and the threshold_overrides text) and
    the loaded model's card (None: no card, defaults and overrides only); symmetric joints (the robot YAML's
    joint_symmetry_deg) with the card's error modulo their period, compared modulo it."""
    symmetric = list(spec.joint_symmetry)
    measured = card_joint_errors(card, spec.joint_names, params["card_test_set"], symmetric) if card else {}
    return joint_thresholds(spec.joint_names, joint_kinds(spec), measured, params["threshold_factor"],
                            params["error_factor"], params["default_threshold_rad"], params["default_threshold_m"],
                            parse_overrides(parse_pairs(params["threshold_overrides"], "threshold_overrides")),
                            spec.joint_symmetry)


def parse_overrides(pairs: Mapping[str, str]) -> dict[str, float]:
    """{'joint': '0.3'} -> {'joint': 0.3}; ValueError naming the joint for a value that is not a number."""
    out = {}
    for name, text in pairs.items():
        try:
            out[name] = float(text)
        except ValueError:
            raise ValueError(f"threshold_overrides: {name}={text} is not a number") from None
    return out
