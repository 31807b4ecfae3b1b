"""Joints by name: the map from the estimator's joint names (robot YAML) to a robot's own names, the selection of
a message's positions by name (any order, extra joints ignored, missing ones reported), and angle wrapping. Plain
Python and numpy: the monitor uses it, and so can the estimator's calibration mode (a robot's JointState mapped
onto the robot YAML's joints). Radians; metres for prismatic joints."""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

ANGULAR_KINDS = ("revolute", "continuous")  # URDF joint types whose positions are angles (they wrap)
LINEAR_KINDS = ("prismatic",)


def wrap_to_period(angle, period):
    """`angle` (radians) wrapped to (-period/2, period/2] (`period` radians, scalar or per element); NaN stays NaN."""
    period = np.asarray(period, dtype=np.float64)
    return period / 2.0 - np.mod(period / 2.0 - np.asarray(angle, dtype=np.float64), period)


def wrap_angle(angle):
    """`angle` (radians, scalar or array) wrapped to (-pi, pi]; NaN stays NaN."""
    return wrap_to_period(angle, 2.0 * np.pi)


def joint_difference(a, b, kinds: Sequence[str], periods: Sequence[float] | None = None) -> np.ndarray:
    """(J,) a - b per joint: wrapped to (-pi, pi] for angular joints (`kinds` as URDF joint types), or to
    (-p/2, p/2] for a joint whose `periods` entry p (radians) is less than a turn (a joint that looks the same after
    p: the robot YAML's joint_symmetry_deg); plain for prismatic ones (metres). NaN where either side is NaN."""
    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    angular = np.array([kind in ANGULAR_KINDS for kind in kinds], dtype=bool)
    period = np.full(len(kinds), 2.0 * np.pi) if periods is None else np.asarray(periods, dtype=np.float64)
    d[angular] = wrap_to_period(d[angular], period[angular])
    return d


def parse_pairs(text: str, what: str) -> dict[str, str]:
    """'a=b, c=d' (commas and/or whitespace between the pairs) -> {'a': 'b', 'c': 'd'}; '' -> {}. ValueError for a
    pair without '=' or a key given twice, naming `what` (the parameter)."""
    pairs: dict[str, str] = {}
    for item in re.split(r"[\s,]+", text.strip()):
        if not item:
            continue
        key, sep, value = item.partition("=")
        if not sep or not key or not value:
            raise ValueError(f"{what}: '{item}' is not name=value (expected e.g. 'a=b, c=d')")
        if key in pairs:
            raise ValueError(f"{what}: '{key}' is given twice")
        pairs[key] = value
    return pairs


@dataclass(frozen=True)
class JointNameMap:
    """The estimator's joint name -> the robot's: an explicit entry, else `prefix` + the name (identity by default).

    `JointNameMap.parse("panda_joint1=fr3_joint1", prefix="left_")` maps panda_joint1 to fr3_joint1 and every other
    joint J to left_J."""

    prefix: str = ""
    entries: Mapping[str, str] = field(default_factory=dict)

    @classmethod
    def parse(cls, text: str = "", prefix: str = "", what: str = "joint_name_map") -> "JointNameMap":
        return cls(prefix=prefix, entries=parse_pairs(text, what))

    def robot_name(self, name: str) -> str:
        return self.entries.get(name, self.prefix + name)

    def robot_names(self, names: Sequence[str]) -> list[str]:
        """The robot's name of each of `names` (the estimator's joints); ValueError when an entry names no joint of
        `names` or two joints get one name."""
        unknown = sorted(set(self.entries) - set(names))
        if unknown:
            raise ValueError(f"joint name map: {unknown} are not joints of the robot YAML ({', '.join(names)})")
        mapped = [self.robot_name(n) for n in names]
        if len(set(mapped)) != len(mapped):
            twice = sorted({m for m in mapped if mapped.count(m) > 1})
            raise ValueError(f"joint name map: several joints map to {twice}")
        return mapped


@dataclass(frozen=True)
class Selection:
    """A message's positions picked by name for the `wanted` joints.

    values: (J,) float64 in `wanted`'s order, NaN where the joint is missing or its position is not finite;
    missing / nonfinite: the wanted joints absent from the message / present with a NaN or infinite position;
    extra: names in the message that are not wanted; duplicates: wanted names given more than once (the first
    counts); reordered: the wanted joints present come in another order than `wanted`."""

    values: np.ndarray
    missing: tuple[str, ...] = ()
    nonfinite: tuple[str, ...] = ()
    extra: int = 0
    duplicates: int = 0
    reordered: bool = False

    @property
    def valid(self) -> np.ndarray:
        """(J,) bool: the joints with a finite position."""
        return np.isfinite(self.values)


def select_by_name(names: Sequence[str], positions: Sequence[float], wanted: Sequence[str]) -> Selection:
    """The positions of `wanted` found by name in (`names`, `positions`): any order, extra names ignored, missing
    ones NaN (see Selection). ValueError when names and positions differ in length (a malformed message)."""
    if len(names) != len(positions):
        raise ValueError(f"{len(names)} joint names but {len(positions)} positions")
    index = {name: i for i, name in enumerate(wanted)}
    values = np.full(len(wanted), np.nan)
    seen: set[int] = set()
    order: list[int] = []
    extra = duplicates = 0
    for name, position in zip(names, positions):
        i = index.get(name)
        if i is None:
            extra += 1
        elif i in seen:
            duplicates += 1
        else:
            seen.add(i)
            order.append(i)
            values[i] = float(position) if position is not None else math.nan
    missing = tuple(wanted[i] for i in range(len(wanted)) if i not in seen)
    nonfinite = tuple(wanted[i] for i in sorted(seen) if not math.isfinite(values[i]))
    values[~np.isfinite(values)] = np.nan  # +-inf too: one marker for "no usable position"
    return Selection(values, missing, nonfinite, extra, duplicates, order != sorted(order))
