"""Read and write DREAM/NDDS robot-pose folders: `_camera_settings.json` plus one `NNNNNN.json` and
`NNNNNN.rgb.jpg|png` per frame. Frames come out in metres, in the OpenCV camera frame, with the robot's YAML
joint order; malformed frames are reported once (logger `holo_pose_ros.data.dream`) and skipped."""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from holo_pose_ros.geometry.alignment import (
    UE_TO_OPENCV,
    matrix_to_quaternion_xyzw,
    quaternion_xyzw_to_matrix,
    rigid_align,
)
from holo_pose_ros.geometry.camera import in_image, project
from holo_pose_ros.robots.kinematics import RobotModel

logger = logging.getLogger(__name__)

CAMERA_FILE = "_camera_settings.json"
OBJECT_FILE = "_object_settings.json"
IMAGE_EXTS = ("jpg", "png")
UNIT_SCALES = {"m": 1.0, "cm": 0.01}
UNIT_DETECTION_FRAMES = 20  # frames sampled to detect the units
CM_DEPTH_THRESHOLD = 20.0  # median keypoint depth (file units) above which a folder without joints is in cm
POSE_TOLERANCE_M = 0.01  # RMS of FK-vs-file keypoints above which a quaternion pose is distrusted (metres)


class DreamFormatError(ValueError):
    """A DREAM folder, file or field that cannot be used; the message names the path."""


@dataclass(frozen=True, eq=False)
class DreamFrame:
    """One good DREAM frame, in metres (OpenCV camera frame), pixels and the robot's YAML joint order."""

    name: str
    image_path: Path
    mask_path: Path | None
    K: np.ndarray  # (3, 3) pinhole intrinsics, pixels
    width: int
    height: int
    keypoint_names: tuple[str, ...]
    keypoints_3d: np.ndarray  # (N, 3) camera frame, metres
    keypoints_2d: np.ndarray  # (N, 2) projected_location, pixels
    in_image: np.ndarray  # (N,) bool: DREAM's rule 0 <= u <= W and 0 <= v <= H (inclusive)
    joints: np.ndarray | None  # (J,) radians (metres for prismatic), None when the file lacks some
    T_cam_base: np.ndarray | None  # (4, 4) T_cam<-base, metres
    base_pose_source: str | None  # 'quaternion' | 'alignment' | None
    alignment_residual_m: float  # RMS of T_cam_base·FK(joints) - keypoints_3d, metres; NaN without joints


class _Malformed(Exception):
    """A frame-file problem: the field (a JSON path like 'objects[0].keypoints[2].location') and what is wrong."""

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field, self.message = field, message


@dataclass(frozen=True)
class _RawFrame:
    """A parsed frame file, 3D values still in file units."""

    name: str
    image_path: Path
    mask_path: Path | None
    keypoints_3d: np.ndarray
    keypoints_2d: np.ndarray
    joints: np.ndarray | None
    location: np.ndarray | None
    quaternion: np.ndarray | None


# -- shared helpers -----------------------------------------------------------------------------------------------

def _float64_model(robot: RobotModel | str) -> RobotModel:
    """A float64 CPU RobotModel of `robot` (a RobotModel or a robot name), for sub-micrometre FK."""
    if isinstance(robot, RobotModel):
        if robot.dtype == torch.float64 and robot.device.type == "cpu":
            return robot
        return RobotModel(robot.spec, dtype=torch.float64)
    return RobotModel(robot, dtype=torch.float64)


def _base_keypoints(robot: RobotModel, joints: np.ndarray) -> np.ndarray:
    """(B, N, 3) FK keypoints in the base frame (metres) of (B, J) joints, in chunks to bound memory."""
    out = [robot.keypoints(torch.from_numpy(joints[i:i + 2048])).numpy() for i in range(0, len(joints), 2048)]
    return np.concatenate(out).astype(np.float64)


def _readonly(a: np.ndarray | None) -> np.ndarray | None:
    """`a` marked read-only (frames are shared and immutable), or None."""
    if a is not None:
        a.setflags(write=False)
    return a


def _check_units(units: str, allow_auto: bool) -> str:
    """`units` if it is 'm', 'cm' (or 'auto' when allowed), else a ValueError."""
    allowed = ("auto", *UNIT_SCALES) if allow_auto else tuple(UNIT_SCALES)
    if units not in allowed:
        raise ValueError(f"units must be one of {allowed}, got {units!r}")
    return units


# -- folder and camera --------------------------------------------------------------------------------------------

def _is_frame_file(name: str) -> bool:
    """DREAM's rule: a frame file is a `*.json` whose name starts with a digit."""
    return name.endswith(".json") and name[:1].isdigit()


def _resolve_folder(folder: str | Path) -> Path:
    """The folder holding the frames: `folder` itself, or its only sub-folder when that has the same name."""
    path = Path(folder).expanduser()
    if not path.is_dir():
        raise DreamFormatError(f"DREAM folder not found or not a directory: {path}")
    entries = list(os.scandir(path))
    subdirs = [e for e in entries if e.is_dir()]
    if (len(subdirs) == 1 and subdirs[0].name == path.name and CAMERA_FILE not in {e.name for e in entries}
            and not any(_is_frame_file(e.name) for e in entries)):
        return path / path.name
    return path


def _field(data, keys: list, where: str):
    """data[k0][k1]... or a DreamFormatError naming the file `where` and the missing or wrong field."""
    path = ""
    for k in keys:
        path += f"[{k}]" if isinstance(k, int) else (f".{k}" if path else k)
        try:
            data = data[k]
        except (KeyError, IndexError, TypeError):
            raise DreamFormatError(f"{where}: missing or invalid field '{path}'") from None
    return data


def read_camera_settings(path: Path) -> tuple[np.ndarray, int, int]:
    """K (3, 3) and the image width, height (pixels) from an NDDS `_camera_settings.json`."""
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DreamFormatError(f"{path}: cannot read camera settings: {e}") from None
    intr = _field(data, ["camera_settings", 0, "intrinsic_settings"], str(path))
    size = _field(data, ["camera_settings", 0, "captured_image_size"], str(path))
    try:
        fx, fy, cx, cy = (float(intr[k]) for k in ("fx", "fy", "cx", "cy"))
        width, height = int(size["width"]), int(size["height"])
    except (KeyError, TypeError, ValueError) as e:
        raise DreamFormatError(f"{path}: bad intrinsic_settings/captured_image_size: {e!r}") from None
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or fx <= 0 or fy <= 0 or width <= 0 or height <= 0:
        raise DreamFormatError(f"{path}: intrinsics and image size must be finite and positive")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), width, height


# -- frame parsing ------------------------------------------------------------------------------------------------

def _numbers(value, length: int, field: str) -> list[float]:
    """`value` checked to be a list of `length` finite numbers, or _Malformed naming `field` (plain Python: fast)."""
    if not isinstance(value, list) or len(value) != length or not all(type(v) in (float, int) for v in value):
        raise _Malformed(field, f"expected a list of {length} numbers, got {str(value)[:60]}")
    if not all(math.isfinite(v) for v in value):
        raise _Malformed(field, "contains NaN or inf")
    return value


def _vector(value, length: int, field: str) -> np.ndarray:
    """`value` as a finite float64 vector of `length` numbers, or _Malformed naming `field`."""
    return np.array(_numbers(value, length, field), dtype=np.float64)


def _get(data: dict, key: str, field: str, kind: type | tuple[type, ...]):
    """data[key] checked to be of type `kind`, or _Malformed naming `field`."""
    if not isinstance(data, dict) or key not in data:
        raise _Malformed(field, "missing key")
    if not isinstance(data[key], kind) or isinstance(data[key], bool):
        raise _Malformed(field, f"expected {getattr(kind, '__name__', 'a number')}, got {type(data[key]).__name__}")
    return data[key]


def _select_object(data: dict, robot_name: str) -> tuple[int, dict]:
    """The object whose `class` is the robot name, else objects[0]; returns (index, object)."""
    objects = _get(data, "objects", "objects", list)
    if not objects:
        raise _Malformed("objects", "empty list")
    index = next((i for i, o in enumerate(objects) if isinstance(o, dict) and o.get("class") == robot_name), 0)
    if not isinstance(objects[index], dict):
        raise _Malformed(f"objects[{index}]", "expected an object")
    return index, objects[index]


def _keypoints(obj: dict, prefix: str, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) locations (file units) and (N, 2) projected locations (pixels) of the named keypoints."""
    items = _get(obj, "keypoints", f"{prefix}.keypoints", list)
    by_name: dict[str, int] = {}
    for i, item in enumerate(items):
        if not isinstance(item, dict) or not isinstance(item.get("name"), str):
            raise _Malformed(f"{prefix}.keypoints[{i}].name", "missing or not a string")
        by_name.setdefault(item["name"], i)
    loc, proj = [], []
    for name in names:
        if name not in by_name:
            raise _Malformed(f"{prefix}.keypoints", f"missing keypoint '{name}'")
        i = by_name[name]
        where = f"{prefix}.keypoints[{i}]"
        loc.append(_numbers(_get(items[i], "location", f"{where}.location", list), 3, f"{where}.location"))
        proj.append(_numbers(_get(items[i], "projected_location", f"{where}.projected_location", list), 2,
                             f"{where}.projected_location"))
    return np.array(loc, dtype=np.float64), np.array(proj, dtype=np.float64)


def _joints(data: dict, names: list[str]) -> np.ndarray | None:
    """(J,) joint positions in `names` order, matched after stripping any '.../' prefix; None if some are absent."""
    if "sim_state" not in data:
        return None
    entries = _get(_get(data, "sim_state", "sim_state", dict), "joints", "sim_state.joints", list)
    positions: dict[str, float] = {}
    for i, entry in enumerate(entries):
        where = f"sim_state.joints[{i}]"
        name = _get(entry, "name", f"{where}.name", str).split("/")[-1]
        value = _get(entry, "position", f"{where}.position", (int, float))
        if not math.isfinite(value):
            raise _Malformed(f"{where}.position", f"not a finite number: {value}")
        positions.setdefault(name, float(value))
    if not all(n in positions for n in names):
        return None
    return np.array([positions[n] for n in names])


def _object_pose(obj: dict, prefix: str) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The object's `location` (3,) (file units) and `quaternion_xyzw` (4,), each None when absent."""
    location = _vector(obj["location"], 3, f"{prefix}.location") if "location" in obj else None
    if "quaternion_xyzw" not in obj:
        return location, None
    q = _vector(obj["quaternion_xyzw"], 4, f"{prefix}.quaternion_xyzw")
    if np.linalg.norm(q) < 1e-6:
        raise _Malformed(f"{prefix}.quaternion_xyzw", "zero quaternion")
    if location is None:
        raise _Malformed(f"{prefix}.location", "missing key (needed with quaternion_xyzw)")
    return location, q


def _image_path(folder: Path, name: str, files: set[str]) -> Path:
    """`<name>.rgb.jpg` or `<name>.rgb.png`, or _Malformed('image')."""
    for ext in IMAGE_EXTS:
        if f"{name}.rgb.{ext}" in files:
            return folder / f"{name}.rgb.{ext}"
    raise _Malformed("image", f"no {name}.rgb.jpg or {name}.rgb.png")


def decode_image(path: Path) -> np.ndarray:
    """The BGR image of a JPEG or PNG file; DreamFormatError naming the file when it cannot be read, does not
    decode, or is cut short (OpenCV decodes a truncated JPEG into a grey-padded image without an error, so the
    end-of-image marker of JPEG and the IEND chunk of PNG are checked)."""
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as e:
        raise DreamFormatError(f"cannot read image {path}: {e}") from e
    head, tail = data[:8].tobytes(), data[-1024:].tobytes()
    if head[:2] == b"\xff\xd8" and b"\xff\xd9" not in tail:  # some writers append bytes after the marker
        raise DreamFormatError(f"image {path} is truncated (the JPEG has no end-of-image marker)")
    if head == b"\x89PNG\r\n\x1a\n" and b"IEND" not in tail[-16:]:
        raise DreamFormatError(f"image {path} is truncated (the PNG has no IEND chunk)")
    image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if image is None:
        raise DreamFormatError(f"cannot read image {path}: empty or not a JPEG/PNG image")
    return image


def _check_image(path: Path, width: int, height: int) -> None:
    """_Malformed('image') unless the image decodes to width x height pixels."""
    try:
        image = decode_image(path)
    except DreamFormatError as e:
        raise _Malformed("image", str(e)) from e
    if image.shape[:2] != (height, width):
        raise _Malformed("image", f"{path.name} is {image.shape[1]}x{image.shape[0]}, expected {width}x{height}")


def _parse_frame(folder: Path, file_name: str, files: set[str], robot: RobotModel) -> _RawFrame:
    """One frame file parsed and checked, or _Malformed naming the first bad field."""
    name = file_name[: -len(".json")]
    try:
        with open(folder / file_name, "rb") as f:
            data = json.loads(f.read())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise _Malformed("<json>", f"invalid JSON: {e}") from None
    if not isinstance(data, dict):
        raise _Malformed("<json>", "top level is not an object")
    index, obj = _select_object(data, robot.name)
    kp3d, kp2d = _keypoints(obj, f"objects[{index}]", robot.keypoint_names)
    location, quaternion = _object_pose(obj, f"objects[{index}]")
    mask = f"{name}.mask.png"
    return _RawFrame(
        name=name,
        image_path=_image_path(folder, name, files),
        mask_path=folder / mask if mask in files else None,
        keypoints_3d=kp3d,
        keypoints_2d=kp2d,
        joints=_joints(data, robot.joint_names),
        location=location,
        quaternion=quaternion,
    )


# -- units and base pose ------------------------------------------------------------------------------------------

def _pair_distance_sum(points: np.ndarray) -> np.ndarray:
    """(B,) sum of all pairwise distances between the N points of each of B sets (B, N, 3)."""
    diff = points[:, :, None, :] - points[:, None, :, :]
    return np.linalg.norm(diff, axis=-1).sum(axis=(1, 2))


def _detect_units(frames: list[_RawFrame], robot: RobotModel) -> str:
    """'cm' or 'm' from the data: inter-keypoint distances in the files over the same distances by FK at the
    files' joints (≈100 → cm, ≈1 → m) on up to 20 frames; without joints, median |depth| > 20 → cm."""
    with_joints = [f for f in frames if f.joints is not None]
    candidates = with_joints or frames
    picks = np.unique(np.linspace(0, len(candidates) - 1, min(UNIT_DETECTION_FRAMES, len(candidates))).astype(int))
    sample = [candidates[i] for i in picks]
    file_points = np.stack([f.keypoints_3d for f in sample])
    if not with_joints:
        return "cm" if np.median(np.abs(file_points[..., 2])) > CM_DEPTH_THRESHOLD else "m"
    fk = _base_keypoints(robot, np.stack([f.joints for f in sample]))
    ratio = float(np.median(_pair_distance_sum(file_points) / np.maximum(_pair_distance_sum(fk), 1e-9)))
    units = "cm" if ratio > 10.0 else "m"  # 10 = geometric midpoint of 1 and 100
    expected = 100.0 if units == "cm" else 1.0
    if not 0.5 < ratio / expected < 2.0:
        logger.warning("unit detection uncertain: file/FK keypoint distance ratio %.3g; assuming '%s' "
                       "(wrong robot or URDF?)", ratio, units)
    return units


def _rms(T: np.ndarray, base_points: np.ndarray, cam_points: np.ndarray) -> float:
    """RMS distance between T·base_points and cam_points (N, 3), metres."""
    moved = base_points @ T[:3, :3].T + T[:3, 3]
    return float(np.sqrt(np.mean(np.sum((moved - cam_points) ** 2, axis=1))))


def pose_from_quaternion(quaternion_xyzw: np.ndarray, location_m: np.ndarray) -> np.ndarray:
    """T_cam<-base (4, 4) of a DREAM object pose: R = R(q)·UE_TO_OPENCV, t = location (metres)."""
    T = np.eye(4)
    T[:3, :3] = quaternion_xyzw_to_matrix(quaternion_xyzw) @ UE_TO_OPENCV
    T[:3, 3] = location_m
    return T


def _base_pose(raw: _RawFrame, scale: float, fk: np.ndarray | None) -> tuple[np.ndarray | None, str | None, float]:
    """(T_cam_base, source, residual_m): the file's quaternion pose while it explains the keypoints within
    POSE_TOLERANCE_M (or no joints to check it), else the rigid alignment of FK to the keypoints."""
    T_q = pose_from_quaternion(raw.quaternion, raw.location * scale) if raw.quaternion is not None else None
    if fk is None:
        return T_q, ("quaternion" if T_q is not None else None), math.nan
    cam = raw.keypoints_3d * scale
    if T_q is not None:
        r_q = _rms(T_q, fk, cam)
        if r_q <= POSE_TOLERANCE_M:
            return T_q, "quaternion", r_q
    T_a, r_a = rigid_align(fk, cam)
    if T_q is None or r_a <= POSE_TOLERANCE_M:
        return T_a, "alignment", r_a
    return T_q, "quaternion", r_q


# -- reader -------------------------------------------------------------------------------------------------------

class DreamReader:
    """A DREAM folder's good frames (all JSON parsed up front), in metres and the robot's joint order.

    `units` is 'auto' (detected from the data, see `_detect_units`), 'm' or 'cm'; `reader.units` and
    `reader.scale` (file units -> metres) tell what was used. Malformed frames are logged once and listed in
    `reader.problems` as (file, field, message). `check_images` also decodes every image up front.
    """

    def __init__(self, folder: str | Path, robot: RobotModel | str, units: str = "auto", check_images: bool = False):
        _check_units(units, allow_auto=True)
        self.robot = _float64_model(robot)
        self.folder = _resolve_folder(folder)
        files = set(os.listdir(self.folder))
        frame_files = sorted(n for n in files if _is_frame_file(n))
        missing = ([f"missing {CAMERA_FILE}"] if CAMERA_FILE not in files else []) + \
                  (["no frame files (NNNNNN.json)"] if not frame_files else [])
        if missing:
            raise DreamFormatError(f"not a DREAM folder: {self.folder}: {'; '.join(missing)}")
        self.K, self.width, self.height = read_camera_settings(self.folder / CAMERA_FILE)
        self.problems: list[tuple[str, str, str]] = []
        raw = self._parse_all(frame_files, files, check_images)
        self.n_malformed_files = len(self.problems)  # problems found reading the folder; `images` adds later ones
        if not raw:
            first = self.problems[0]
            raise DreamFormatError(f"no valid frames in {self.folder} ({len(self.problems)} malformed; first: "
                                   f"{first[0]}: {first[1]}: {first[2]})")
        self.units = _detect_units(raw, self.robot) if units == "auto" else units
        self.scale = UNIT_SCALES[self.units]
        self._frames = self._build_frames(raw)

    def _parse_all(self, frame_files: list[str], files: set[str], check_images: bool) -> list[_RawFrame]:
        """Every frame file parsed; bad ones logged once, recorded in self.problems and dropped."""
        raw = []
        for file_name in frame_files:
            try:
                frame = _parse_frame(self.folder, file_name, files, self.robot)
                if check_images:
                    _check_image(frame.image_path, self.width, self.height)
                raw.append(frame)
            except _Malformed as e:
                path = str(self.folder / file_name)
                self.problems.append((path, e.field, e.message))
                logger.warning("skipping malformed DREAM frame %s: field '%s': %s", path, e.field, e.message)
        return raw

    def _build_frames(self, raw: list[_RawFrame]) -> list[DreamFrame]:
        """DreamFrames in metres with their base poses (FK of all frames with joints in one batch)."""
        has_joints = [i for i, r in enumerate(raw) if r.joints is not None]
        fk_all = _base_keypoints(self.robot, np.stack([raw[i].joints for i in has_joints])) if has_joints else []
        fk = dict(zip(has_joints, fk_all))
        frames, overridden = [], 0
        for i, r in enumerate(raw):
            T, source, residual = _base_pose(r, self.scale, fk.get(i))
            overridden += int(r.quaternion is not None and source == "alignment")
            frames.append(self._frame(r, T, source, residual))
        if overridden:
            logger.warning("%s: %d frame(s) have a quaternion_xyzw pose that misses the FK keypoints by > %.0f mm "
                           "RMS; using the rigid alignment of FK to the keypoints instead", self.folder, overridden,
                           POSE_TOLERANCE_M * 1000)
        return frames

    def _frame(self, r: _RawFrame, T: np.ndarray | None, source: str | None, residual: float) -> DreamFrame:
        """A read-only DreamFrame of a parsed frame and its base pose."""
        return DreamFrame(
            name=r.name, image_path=r.image_path, mask_path=r.mask_path, K=_readonly(self.K.copy()),
            width=self.width, height=self.height, keypoint_names=tuple(self.robot.keypoint_names),
            keypoints_3d=_readonly(r.keypoints_3d * self.scale), keypoints_2d=_readonly(r.keypoints_2d),
            in_image=_readonly(in_image(r.keypoints_2d, self.width, self.height)), joints=_readonly(r.joints),
            T_cam_base=_readonly(T), base_pose_source=source, alignment_residual_m=residual)

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, index: int) -> DreamFrame:
        return self._frames[index]

    def __iter__(self):
        return iter(self._frames)

    def load_image(self, frame: DreamFrame) -> np.ndarray:
        """The frame's image as (H, W, 3) uint8 RGB; DreamFormatError naming the file if unreadable or mis-sized."""
        image = decode_image(frame.image_path)
        if image.shape[:2] != (frame.height, frame.width):
            raise DreamFormatError(f"image {frame.image_path} is {image.shape[1]}x{image.shape[0]}, but "
                                   f"{CAMERA_FILE} says {frame.width}x{frame.height}")
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)

    def images(self, frames=None):
        """(frame, RGB image) of every frame of `frames` (default: all) whose image reads; an unreadable one
        (truncated, empty, not an image, of another size) is logged, added to `problems` as (file, 'image',
        message) and skipped, so one bad file never ends a run."""
        for frame in (self._frames if frames is None else frames):
            try:
                image = self.load_image(frame)
            except DreamFormatError as e:
                self.problems.append((str(frame.image_path), "image", str(e)))
                logger.warning("skipping DREAM frame %s: field 'image': %s", frame.name, e)
                continue
            yield frame, image

    def load_mask(self, frame: DreamFrame) -> np.ndarray | None:
        """The frame's robot mask (H, W) uint8, or None when the frame has none."""
        if frame.mask_path is None:
            return None
        mask = cv2.imread(str(frame.mask_path), cv2.IMREAD_UNCHANGED)
        if mask is None:
            raise DreamFormatError(f"cannot read mask {frame.mask_path}")
        return mask if mask.ndim == 2 else mask[..., 0]


# -- writer -------------------------------------------------------------------------------------------------------

def _write_atomically(path: Path, text: str) -> None:
    """Write `text` to `path` through a temporary file and a rename: parallel writers (generator workers) of the
    same folder never leave a half-written settings file."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


class DreamWriter:
    """Writes frames as a DREAM/NDDS folder that DreamReader, DREAM and RoboPose read: 3D values in `units`
    ('m' or 'cm'), pixels unscaled, object pose as NDDS quaternion_xyzw + location.

    `others`: further robots in the same images (of other types: a DreamReader finds its robot's object by class,
    so each reads its own); each frame then lists one object per robot, `robot` first, and sim_state the joints of
    all of them, which must therefore have distinct joint names."""

    def __init__(self, folder: str | Path, robot: RobotModel | str, K, width: int, height: int, units: str = "m",
                 image_ext: str = "jpg", jpeg_quality: int = 95, others: Sequence[RobotModel | str] = ()):
        self.robot = _float64_model(robot)
        self.others = [_float64_model(o) for o in others]
        names = [r.name for r in (self.robot, *self.others)]
        if len(set(names)) < len(names):
            raise ValueError(f"robots of one DREAM folder must be of different types (their object class), got {names}")
        joints = [j for r in (self.robot, *self.others) for j in r.joint_names]
        if len(set(joints)) < len(joints):
            raise ValueError(f"robots {names} share joint names: sim_state could not tell their joints apart")
        self.folder = Path(folder)
        self.K = np.asarray(K, dtype=np.float64)
        if self.K.shape != (3, 3) or not np.isfinite(self.K).all() or self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise ValueError(f"K: expected a finite (3, 3) pinhole matrix with fx, fy > 0, got {self.K}")
        if image_ext not in IMAGE_EXTS:
            raise ValueError(f"image_ext must be one of {IMAGE_EXTS}, got {image_ext!r}")
        self.width, self.height, self.image_ext = int(width), int(height), image_ext
        self.factor = 1.0 / UNIT_SCALES[_check_units(units, allow_auto=False)]  # metres -> file units
        self.units = units
        self._encode = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if image_ext == "jpg" else []
        self.folder.mkdir(parents=True, exist_ok=True)
        self._write_settings()

    def _write_settings(self) -> None:
        """`_camera_settings.json` (NDDS layout) and a minimal `_object_settings.json`."""
        K = self.K
        size = {"width": self.width, "height": self.height}
        camera = {"camera_settings": [{
            "name": "camera",
            "intrinsic_settings": {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "s": 0,
                                   "resolution": size},
            "captured_image_size": size,
        }]}
        _write_atomically(self.folder / CAMERA_FILE, json.dumps(camera, indent=2))
        _write_atomically(self.folder / OBJECT_FILE, json.dumps(
            {"exported_object_classes": [r.name for r in (self.robot, *self.others)]}, indent=2))

    def _object_json(self, robot: RobotModel, T: np.ndarray, kp3d: np.ndarray) -> dict:
        """One robot's NDDS object (3D values converted to file units)."""
        quaternion = matrix_to_quaternion_xyzw(T[:3, :3] @ UE_TO_OPENCV.T)  # inverse of R = R(q)·UE_TO_OPENCV
        uv = project(kp3d, self.K)
        keypoints = [{"name": n, "location": (p * self.factor).tolist(), "projected_location": q.tolist()}
                     for n, p, q in zip(robot.keypoint_names, kp3d, uv)]
        return {"class": robot.name, "visibility": 1, "location": (T[:3, 3] * self.factor).tolist(),
                "quaternion_xyzw": quaternion.tolist(), "keypoints": keypoints}

    def _frame_json(self, joints: np.ndarray, T: np.ndarray, kp3d: np.ndarray, extra: dict | None,
                    others: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]] = ()) -> dict:
        """The NDDS frame dictionary; `others`: (joints, T, keypoints_3d) of each of self.others."""
        robots = [(self.robot, joints, T, kp3d)] + [(r, *o) for r, o in zip(self.others, others)]
        data = {
            "objects": [self._object_json(r, t, k) for r, _, t, k in robots],
            "sim_state": {"joints": [{"name": n, "position": float(v)} for r, q, _, _ in robots
                                     for n, v in zip(r.joint_names, q)]},
        }
        return {**data, **(extra or {})}

    def _checked(self, rgb, joints, T_cam_base, mask) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """The write() inputs as arrays of the right shapes and types, or a ValueError saying which is wrong."""
        rgb = np.asarray(rgb)
        if rgb.shape != (self.height, self.width, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"rgb: expected ({self.height}, {self.width}, 3) uint8, got {rgb.shape} {rgb.dtype}")
        joints = np.asarray(joints, dtype=np.float64).reshape(-1)
        if joints.shape != (self.robot.n_joints,) or not np.isfinite(joints).all():
            raise ValueError(f"joints: expected {self.robot.n_joints} finite values, got {joints.shape}")
        T = np.asarray(T_cam_base, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"T_cam_base: expected a finite (4, 4) matrix, got {T.shape}")
        if mask is not None:
            mask = np.asarray(mask)
            mask = mask.astype(np.uint8) * 255 if mask.dtype == bool else mask
            if mask.shape != (self.height, self.width) or mask.dtype != np.uint8:
                raise ValueError(f"mask: expected ({self.height}, {self.width}) uint8 or bool, got {mask.shape} "
                                 f"{mask.dtype}")
        return rgb, joints, T, mask

    def write(self, index: int, rgb, joints, T_cam_base, keypoints_3d=None, mask=None, extra: dict | None = None,
              others: Sequence[tuple] = ()) -> Path:
        """Write frame `index` (rgb (H, W, 3) uint8, joints (J,) rad/m, T_cam<-base (4, 4) metres, optional
        keypoints_3d (N, 3) metres in the camera frame (default: FK), mask (H, W), extra top-level JSON keys,
        and for each robot of self.others its (joints, T_cam<-base), keypoints by FK); returns the JSON path,
        written last so that a reader never sees a frame without its image."""
        if int(index) < 0:
            raise ValueError(f"index must be >= 0, got {index}")
        if extra is not None and {"objects", "sim_state"} & set(extra):
            raise ValueError(f"extra may not replace 'objects' or 'sim_state', got keys {sorted(extra)}")
        if len(others) != len(self.others):
            raise ValueError(f"others: expected (joints, T_cam_base) of {len(self.others)} robot(s), got {len(others)}")
        rgb, joints, T, mask = self._checked(rgb, joints, T_cam_base, mask)
        if keypoints_3d is None:
            kp3d = self.robot.keypoints_in_camera(torch.from_numpy(joints), torch.from_numpy(T))[0].numpy()
        else:
            kp3d = np.asarray(keypoints_3d, dtype=np.float64)
        if kp3d.shape != (self.robot.n_keypoints, 3) or not np.isfinite(kp3d).all():
            raise ValueError(f"keypoints_3d: expected ({self.robot.n_keypoints}, 3) finite values, got {kp3d.shape}")
        placed = [self._other(robot, q, T_other) for robot, (q, T_other) in zip(self.others, others)]
        for robot, points in [(self.robot, kp3d)] + [(r, p[2]) for r, p in zip(self.others, placed)]:
            if (points[:, 2] <= 0).any():
                raise ValueError(f"keypoints_3d: every keypoint must be in front of the camera (z > 0), min z of "
                                 f"{robot.name} is {points[:, 2].min():.3f} m")
        name = f"{int(index):06d}"
        self._imwrite(self.folder / f"{name}.rgb.{self.image_ext}", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), self._encode)
        if mask is not None:
            self._imwrite(self.folder / f"{name}.mask.png", mask, [])
        path = self.folder / f"{name}.json"
        path.write_text(json.dumps(self._frame_json(joints, T, kp3d, extra, placed)))
        return path

    @staticmethod
    def _other(robot: RobotModel, joints, T_cam_base) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(joints, T, keypoints_3d by FK) of a further robot, checked."""
        q = np.asarray(joints, dtype=np.float64).reshape(-1)
        T = np.asarray(T_cam_base, dtype=np.float64)
        if q.shape != (robot.n_joints,) or not np.isfinite(q).all():
            raise ValueError(f"others: {robot.name} joints: expected {robot.n_joints} finite values, got {q.shape}")
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"others: {robot.name} T_cam_base: expected a finite (4, 4) matrix, got {T.shape}")
        return q, T, robot.keypoints_in_camera(torch.from_numpy(q), torch.from_numpy(T))[0].numpy()

    @staticmethod
    def _imwrite(path: Path, image: np.ndarray, params: list[int]) -> None:
        """cv2.imwrite that raises (naming the file) instead of returning False."""
        if not cv2.imwrite(str(path), image, params):
            raise OSError(f"cannot write image {path}")
