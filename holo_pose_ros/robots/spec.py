"""The robot YAML (config/robots/<name>.yaml): the single source of truth for a robot's keypoints, estimated
joints, root keypoint, neutral pose and URDF source. Loaded into plain dataclasses; nothing here imports torch."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from holo_pose_ros.resources import config_dir


@dataclass(frozen=True)
class UrdfSource:
    """Where the URDF comes from: exactly one of (package + path), file, or string."""

    package: str | None = None
    path: str | None = None
    file: str | None = None
    string: str | None = None


@dataclass(frozen=True)
class KeypointSpec:
    """A keypoint: the origin of URDF link `link`, named as in DREAM files."""

    name: str
    link: str


@dataclass(frozen=True)
class FitKeypointSpec:
    """A point fixed in URDF link `link` at `xyz` (metres, link frame): one of the points the heatmap network
    detects and the kinematic fit explains. DREAM's keypoints come first (xyz = 0), then the YAML's extra points."""

    name: str
    link: str
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class JointSpec:
    """An estimated joint: `name` in DREAM files and outputs, `urdf` the URDF joint it drives."""

    name: str
    urdf: str


@dataclass(frozen=True)
class RobotSpec:
    """Everything the package knows about one robot, as written in its YAML."""

    name: str
    urdf: UrdfSource
    base_link: str
    keypoints: tuple[KeypointSpec, ...]
    root_keypoint: str
    joints: tuple[JointSpec, ...]
    neutral: tuple[float, ...]
    fixed_joints: dict[str, float] = field(default_factory=dict)
    constants: dict[str, float] = field(default_factory=dict)
    extra_fit_keypoints: tuple[FitKeypointSpec, ...] = ()
    close_ups: dict[str, str] = field(default_factory=dict)  # part name -> the URDF link whose subtree it is
    joint_symmetry: dict[str, float] = field(default_factory=dict)  # joint -> the turn (radians) it looks alike after
    source_file: str | None = None

    @property
    def fit_keypoints(self) -> tuple[FitKeypointSpec, ...]:
        """DREAM's keypoints (link origins, same order) followed by the extra fit points of the YAML."""
        return tuple(FitKeypointSpec(k.name, k.link) for k in self.keypoints) + self.extra_fit_keypoints

    @property
    def keypoint_names(self) -> list[str]:
        return [k.name for k in self.keypoints]

    @property
    def joint_names(self) -> list[str]:
        return [j.name for j in self.joints]

    @property
    def root_index(self) -> int:
        return self.keypoint_names.index(self.root_keypoint)


def available_robots() -> list[str]:
    """Names of the robots shipped in config/robots."""
    return sorted(p.stem for p in (config_dir() / "robots").glob("*.yaml"))


def _require(data: dict, key: str, where: str):
    if key not in data:
        raise ValueError(f"{where}: missing required key '{key}'")
    return data[key]


def _fit_keypoints(entries: list, where: str) -> tuple[FitKeypointSpec, ...]:
    """The YAML's `fit_keypoints` list ({name, link, xyz}), each entry checked."""
    out = []
    for i, e in enumerate(entries):
        if not isinstance(e, dict) or not {"name", "link", "xyz"} <= set(e):
            raise ValueError(f"{where}: fit_keypoints[{i}] needs name, link and xyz (metres)")
        xyz = tuple(float(v) for v in e["xyz"])
        if len(xyz) != 3:
            raise ValueError(f"{where}: fit_keypoints[{i}] ('{e['name']}'): xyz needs 3 values, got {len(xyz)}")
        out.append(FitKeypointSpec(str(e["name"]), str(e["link"]), xyz))
    return tuple(out)


def _close_ups(entries, where: str) -> dict[str, str]:
    """The YAML's `close_ups` ({name: link}): the robot's parts that the estimator may crop on their own (an arm,
    a hand) for a second pass at their own scale, each the subtree of URDF link `link`."""
    if not isinstance(entries, dict) or not all(isinstance(v, str) and v for v in entries.values()):
        raise ValueError(f"{where}: 'close_ups' must map each part's name to the URDF link its subtree starts at")
    return {str(k): v for k, v in entries.items()}


def _joint_symmetry(entries, joint_names: list[str], where: str) -> dict[str, float]:
    """The YAML's `joint_symmetry_deg` ({joint: degrees}) in radians: joints whose distal links look the same after
    that part of a turn (a hand's roll), so that no image tells q from q + the period. Each a joint of the YAML,
    each period in (0, 360] degrees."""
    if not isinstance(entries, dict):
        raise ValueError(f"{where}: 'joint_symmetry_deg' must map joint names to a period in degrees")
    out = {}
    for name, value in entries.items():
        if name not in joint_names:
            raise ValueError(f"{where}: joint_symmetry_deg names '{name}', which is not one of the joints "
                             f"({', '.join(joint_names)})")
        try:
            degrees = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: joint_symmetry_deg.{name}: '{value}' is not a number of degrees") from None
        if not 0.0 < degrees <= 360.0:
            raise ValueError(f"{where}: joint_symmetry_deg.{name}: {degrees:g} is not in (0, 360] degrees")
        out[str(name)] = math.radians(degrees)
    return out


def load_robot_spec(robot: str | Path) -> RobotSpec:
    """Load a robot by shipped name ('panda', 'kuka', 'baxter') or by path to a robot YAML file."""
    path = Path(robot)
    if not path.suffix:
        path = config_dir() / "robots" / f"{robot}.yaml"
        if not path.is_file():
            raise ValueError(f"unknown robot '{robot}'; shipped robots: {', '.join(available_robots())}")
    where = str(path)
    with open(path) as f:
        data = yaml.safe_load(f)
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a mapping at the top level")
    urdf = UrdfSource(**_require(data, "urdf", where))
    if sum(x is not None for x in (urdf.path, urdf.file, urdf.string)) != 1 or (urdf.path and not urdf.package):
        raise ValueError(f"{where}: 'urdf' needs exactly one of package+path, file, or string")
    keypoints = tuple(KeypointSpec(**k) for k in _require(data, "keypoints", where))
    joints = tuple(JointSpec(**j) for j in _require(data, "joints", where))
    neutral = tuple(float(x) for x in _require(data, "neutral", where))
    if len(neutral) != len(joints):
        raise ValueError(f"{where}: 'neutral' has {len(neutral)} values for {len(joints)} joints")
    spec = RobotSpec(
        name=str(_require(data, "name", where)),
        urdf=urdf,
        base_link=str(_require(data, "base_link", where)),
        keypoints=keypoints,
        root_keypoint=str(_require(data, "root_keypoint", where)),
        joints=joints,
        neutral=neutral,
        fixed_joints={str(k): float(v) for k, v in (data.get("fixed_joints") or {}).items()},
        constants={str(k): float(v) for k, v in (data.get("constants") or {}).items()},
        extra_fit_keypoints=_fit_keypoints(data.get("fit_keypoints") or [], where),
        close_ups=_close_ups(data.get("close_ups") or {}, where),
        joint_symmetry=_joint_symmetry(data.get("joint_symmetry_deg") or {}, [j.name for j in joints], where),
        source_file=where,
    )
    names = [k.name for k in spec.fit_keypoints]
    if len(set(names)) != len(names):
        raise ValueError(f"{where}: fit keypoint names must be unique (DREAM keypoints included)")
    if spec.root_keypoint not in spec.keypoint_names:
        raise ValueError(f"{where}: root_keypoint '{spec.root_keypoint}' is not one of the keypoints")
    return spec
