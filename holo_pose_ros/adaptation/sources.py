"""The user's images for `holo-pose adapt`, from any of three sources, as (RGB image, K) and, when the robot
reports them, its joints. Nothing else is read: a DREAM folder gives only its images and `_camera_settings.json`
(its per-frame labels are never opened), an image folder its images and a ROS `camera_info` YAML (the file
`camera_calibration` writes), a bag (mcap or sqlite3) its Image and CameraInfo topics and, when named, the
robot's JointState topic, matched to each image by stamp as the node's calibration mode does."""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

logger = logging.getLogger(__name__)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
DREAM_CAMERA_FILE = "_camera_settings.json"


class AdaptationInputError(ValueError):
    """Input that adaptation cannot use; the message names the source and what is wrong with it."""


@dataclass
class SourceFrame:
    """One image of the source: RGB (H, W, 3) uint8, intrinsics K (3, 3) pixels, the robot's joints (J,) radians /
    metres in the robot YAML's order when the source reports them, else None."""

    name: str
    image: np.ndarray
    K: np.ndarray
    joints: np.ndarray | None = None


@dataclass
class Source:
    """What a source gave: its frames, its kind ('dream', 'images', 'bag') and what was skipped, by reason."""

    path: Path
    kind: str
    frames: list[SourceFrame]
    skipped: Counter = field(default_factory=Counter)

    @property
    def has_joints(self) -> bool:
        return bool(self.frames) and all(f.joints is not None for f in self.frames)


def read_camera_info_yaml(path: Path) -> tuple[np.ndarray, int, int]:
    """(K (3, 3), width, height) of a ROS camera_info YAML (camera_calibration's format: image_width,
    image_height, camera_matrix {rows, cols, data}); AdaptationInputError naming the file and the field."""
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        raise AdaptationInputError(f"{path}: cannot read the camera_info YAML ({e})") from e
    if not isinstance(data, dict):
        raise AdaptationInputError(f"{path}: a camera_info YAML is a mapping with image_width, image_height and "
                                   "camera_matrix")
    try:
        width, height = int(data["image_width"]), int(data["image_height"])
    except (KeyError, TypeError, ValueError) as e:
        raise AdaptationInputError(f"{path}: field image_width / image_height missing or not an integer ({e!r})") from e
    matrix = data.get("camera_matrix")
    values = matrix.get("data") if isinstance(matrix, dict) else None
    try:
        K = np.asarray(values, dtype=np.float64).reshape(3, 3)
    except (TypeError, ValueError) as e:
        raise AdaptationInputError(f"{path}: field camera_matrix.data must hold 9 numbers ({e})") from e
    if width <= 0 or height <= 0 or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0 or \
            not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise AdaptationInputError(f"{path}: camera_matrix must be a finite intrinsics matrix with fx, fy > 0 and "
                                   f"last row (0, 0, 1), and the image size positive; got {K.tolist()}, "
                                   f"{width} x {height}")
    distortion = (data.get("distortion_coefficients") or {}).get("data") or []
    if np.any(np.abs(np.asarray(distortion, dtype=np.float64)) > 1e-9):
        logger.warning("%s: non-zero distortion coefficients are ignored (as by the node, which reads K only): "
                       "give rectified images for the best result", path)
    return K, width, height


def _read_rgb(path: Path) -> np.ndarray:
    from holo_pose_ros.data.dream import DreamFormatError, decode_image

    try:
        return cv2.cvtColor(decode_image(path), cv2.COLOR_BGR2RGB)
    except DreamFormatError as e:
        raise AdaptationInputError(str(e)) from e


def _folder_frames(folder: Path, images: list[Path], K: np.ndarray, width: int, height: int, camera_file: Path,
                   limit: int | None) -> list[SourceFrame]:
    frames = []
    for path in images[:limit]:
        image = _read_rgb(path)
        if image.shape[:2] != (height, width):
            raise AdaptationInputError(f"{path} is {image.shape[1]} x {image.shape[0]} px but {camera_file} is for "
                                       f"{width} x {height} px: the camera file belongs to another camera or size")
        frames.append(SourceFrame(path.name, image, K.copy()))
    return frames


def read_dream_images(folder: Path, limit: int | None = None) -> Source:
    """The images and the camera of a DREAM folder, and nothing else (no frame JSON is opened)."""
    from holo_pose_ros.data.dream import DreamFormatError, read_camera_settings

    camera_file = folder / DREAM_CAMERA_FILE
    try:
        K, width, height = read_camera_settings(camera_file)
    except DreamFormatError as e:
        raise AdaptationInputError(str(e)) from e
    images = sorted(p for p in folder.iterdir() if p.name.endswith((".rgb.jpg", ".rgb.png")))
    return Source(folder, "dream", _folder_frames(folder, images, K, width, height, camera_file, limit))


def read_image_folder(folder: Path, camera_info: Path | None = None, limit: int | None = None) -> Source:
    """The images (PNG, JPEG; name order) of a folder with their camera_info YAML: `camera_info`, else the
    folder's only YAML file."""
    if camera_info is None:
        yamls = sorted(p for p in folder.iterdir() if p.suffix in (".yaml", ".yml"))
        if len(yamls) != 1:
            raise AdaptationInputError(f"{folder}: an image folder needs its camera_info YAML (camera_calibration's "
                                       f"format); found {len(yamls)} YAML files ({[p.name for p in yamls]}): name "
                                       "it with --camera-info")
        camera_info = yamls[0]
    K, width, height = read_camera_info_yaml(Path(camera_info))
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and
                    not p.name.endswith((".seg.png", ".mask.png")))
    return Source(folder, "images", _folder_frames(folder, images, K, width, height, Path(camera_info), limit))


def read_bag_frames(bag: Path, joint_names: list[str], joint_states_topic: str | None = None,
                    image_topic: str | None = None, camera_info_topic: str | None = None,
                    tolerance_s: float | None = None, limit: int | None = None) -> Source:
    """Images of a bag with their CameraInfo and, with `joint_states_topic`, the robot's joints nearest in stamp
    (within `tolerance_s`, default the node's calibration tolerance). Unusable images are skipped and counted;
    a joint-state topic none of whose messages holds every joint of `joint_names` is an error naming them."""
    from holo_pose_ros.bag_calibration import JOINT_STATE_MSGTYPE, calibration_defaults
    from holo_pose_ros.bags import (CAMERA_INFO_MSGTYPE, IMAGE_MSGTYPE, BagReadError, image_or_skip,
                                    jazzy_typestore, open_bag, pick_topic, read_messages)
    from holo_pose_ros.monitoring.stamps import NS, StampBuffer
    from msg_adapters import stamp_ns
    from msg_adapters.joint_states import joint_positions_by_name

    tolerance_ns = int(NS * (calibration_defaults()["joint_states_tolerance_s"] if tolerance_s is None else tolerance_s))
    skipped, problems, frames = Counter(), [], []
    try:
        with open_bag(bag, jazzy_typestore()) as reader:
            try:
                image_topic = pick_topic(reader.connections, IMAGE_MSGTYPE, image_topic, "image")
                camera_info_topic = pick_topic(reader.connections, CAMERA_INFO_MSGTYPE, camera_info_topic, "info")
                if joint_states_topic is not None:
                    joint_states_topic = pick_topic(reader.connections, JOINT_STATE_MSGTYPE, joint_states_topic,
                                                    "joint-states")
            except ValueError as e:
                raise AdaptationInputError(f"bag {bag}: {e}") from e
            small = [c for c in reader.connections if (c.topic, c.msgtype) in {
                (camera_info_topic, CAMERA_INFO_MSGTYPE), (joint_states_topic, JOINT_STATE_MSGTYPE)}]
            infos, joints, lacking = [], StampBuffer(history_s=1e9), Counter()
            for conn, t_ns, msg in read_messages(reader, small, bag, problems):
                if msg is None:
                    skipped["undeserializable message"] += 1
                elif conn.topic == camera_info_topic:
                    infos.append((t_ns, stamp_ns(msg.header.stamp), msg))
                else:
                    try:
                        selection, stamp = joint_positions_by_name(msg, joint_names)
                    except ValueError:
                        skipped["malformed joint state"] += 1
                        continue
                    if selection.missing or selection.nonfinite:
                        lacking.update(selection.missing + selection.nonfinite)
                        continue
                    joints.add(stamp, selection.values)
            if joint_states_topic is not None and not len(joints):
                raise AdaptationInputError(
                    f"bag {bag}: no message on {joint_states_topic} holds every joint of the robot"
                    + (f" (lacking {', '.join(sorted(lacking))})" if lacking else " (the topic has no message)"))
            image_conns = [c for c in reader.connections if c.topic == image_topic and c.msgtype == IMAGE_MSGTYPE]
            for conn, t_ns, msg in read_messages(reader, image_conns, bag, problems):
                if limit is not None and len(frames) >= limit:
                    break
                if msg is None:
                    skipped["undeserializable image"] += 1
                    continue
                stamp = stamp_ns(msg.header.stamp)
                q = None
                if joint_states_topic is not None:
                    nearest = joints.nearest(stamp, tolerance_ns)
                    if nearest is None:
                        skipped["no joint state within the tolerance"] += 1
                        continue
                    q = np.asarray(nearest[1], dtype=np.float64)
                usable = image_or_skip(msg, infos, t_ns, camera_info_topic, skipped, stamp)
                if usable is None:
                    continue
                image, K = usable
                frames.append(SourceFrame(f"{image_topic}@{stamp}", image, K, q))
    except BagReadError as e:
        raise AdaptationInputError(str(e)) from e
    for problem in problems:
        skipped[problem] += 1
    return Source(bag, "bag", frames, skipped)


def is_bag(path: Path) -> bool:
    """A ROS 2 bag: a folder with metadata.yaml, or an .mcap / .db3 file."""
    return (path.is_dir() and (path / "metadata.yaml").is_file()) or path.suffix in (".mcap", ".db3")


def read_source(path: str | Path, joint_names: list[str], joint_states_topic: str | None = None,
                camera_info: str | Path | None = None, image_topic: str | None = None,
                camera_info_topic: str | None = None, limit: int | None = None) -> Source:
    """The frames of a DREAM folder, an image folder with a camera_info YAML or a bag (see the module docstring);
    AdaptationInputError when the source is none of these, holds no image, or names joint states it cannot
    give. Only a bag reports joint states."""
    path = Path(path)
    if not path.exists():
        raise AdaptationInputError(f"{path} does not exist")
    if is_bag(path):
        source = read_bag_frames(path, joint_names, joint_states_topic, image_topic, camera_info_topic, limit=limit)
    else:
        if joint_states_topic is not None:
            raise AdaptationInputError(f"{path}: joint states come from a bag's JointState topic; this is a folder")
        if not path.is_dir():
            raise AdaptationInputError(f"{path}: not a DREAM folder, an image folder or a bag (.mcap, .db3 or a "
                                       "folder with metadata.yaml)")
        if (path / DREAM_CAMERA_FILE).is_file():
            source = read_dream_images(path, limit)
        else:
            source = read_image_folder(path, None if camera_info is None else Path(camera_info), limit)
    if not source.frames:
        reasons = ", ".join(f"{n} {why}" for why, n in source.skipped.items())
        raise AdaptationInputError(f"{path}: no usable image" + (f" ({reasons})" if reasons else ""))
    return source
