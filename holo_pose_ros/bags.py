"""ROS 2 bags without DDS or rclpy (rosbags, Jazzy typestore; mcap and sqlite3), and the ground-truth message
layout shared by the DREAM replay node, the evaluation node and the bag tools.

- `dream_to_bag(folder, out)`: a DREAM folder as a bag: Image (rgb8) + CameraInfo, and the ground truth.
- `bag_eval(bag, model, out)`: estimate every image of a bag with the same core as the node (each image paired
  with its CameraInfo), write the estimates to the bag `out` (the images' headers and log times) and, when the
  bag holds ground truth, `out/report.json` (the report of `holo-pose evaluate`).

Topic layout (a bag recorded from the live replay graph has the same one):

    /image, /camera_info                          sensor_msgs/Image (rgb8), sensor_msgs/CameraInfo
    /dream_replay/ground_truth/joint_states       sensor_msgs/JointState   (robot YAML names and order)
    /dream_replay/ground_truth/pose               geometry_msgs/PoseStamped  (robot base in the camera, metres)
    /dream_replay/ground_truth/keypoints          geometry_msgs/PoseArray  (3D keypoints, camera frame, metres)
    /dream_replay/ground_truth/keypoints_2d       sensor_msgs/PointCloud2 (u, v, confidence): DREAM's
                                                  projected_location; confidence 1 inside the image, 0 outside
    /holo_pose_estimator/{joint_states,pose,keypoints,keypoints_2d}   the estimates (same types and units)

All messages of one frame carry the image's header (stamp and frame_id); messages are matched by exact stamp.
The ground truth is encoded by msg_adapters' Estimate converters (a ground truth is an Estimate that is always
found), so ground truth and estimates share one encoding. Synthetic stamps are `start + index / rate`
(`frame_stamp_ns`), identical in the replay node and in `dream_to_bag`, so runs are reproducible.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msg_adapters import (camera_info_from_K, camera_info_to_K, check_image_size, image_to_rgb, joint_positions,
                          keypoints_2d_from_msg, make_header, pose_array_points, pose_to_matrix, rgb_to_image,
                          stamp_ns, to_joint_state, to_keypoints_2d, to_keypoints_3d, to_pose_stamped)

logger = logging.getLogger(__name__)

DEFAULT_FRAME_ID = "camera_color_optical_frame"
DEFAULT_START_TIME_S = 1.0  # synthetic stamps start here (non-zero: a zero stamp often means "no stamp")
DEFAULT_RATE_HZ = 10.0
IMAGE_TOPIC = "/image"  # the replay node's relative `image` and `camera_info`, resolved in the root namespace
CAMERA_INFO_TOPIC = "/camera_info"
REPLAY_NODE = "dream_replay"
GROUND_TRUTH_NS = f"/{REPLAY_NODE}/ground_truth"
ESTIMATOR_NS = "/holo_pose_estimator"
# per-frame outputs, under both GROUND_TRUTH_NS and ESTIMATOR_NS
MSGTYPES = {
    "joint_states": "sensor_msgs/msg/JointState",
    "pose": "geometry_msgs/msg/PoseStamped",
    "keypoints": "geometry_msgs/msg/PoseArray",
    "keypoints_2d": "sensor_msgs/msg/PointCloud2",
}
IMAGE_MSGTYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_MSGTYPE = "sensor_msgs/msg/CameraInfo"
STORAGES = ("mcap", "sqlite3")


# -- stamps and headers -------------------------------------------------------------------------------------------

def frame_stamp_ns(index: int, start_time_s: float = DEFAULT_START_TIME_S, rate_hz: float = DEFAULT_RATE_HZ) -> int:
    """The synthetic stamp (ns) of the `index`-th frame sent: start + index / rate, strictly increasing."""
    if not rate_hz > 0 or not math.isfinite(rate_hz):
        raise ValueError(f"rate must be a positive number of frames per second, got {rate_hz}")
    if start_time_s < 0:
        raise ValueError(f"start time must be >= 0 s, got {start_time_s}")
    return int(round(start_time_s * 1e9)) + int(round(index * 1e9 / rate_hz))


# -- ground truth as messages and back -----------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class GroundTruth:
    """One frame's ground truth, shaped both as an always-found Estimate (for msg_adapters' converters) and as a
    DreamFrame (for holo_pose_ros.evaluation.run.frame_result). Metres, radians, pixels, camera frame OpenCV."""

    name: str
    joint_names: list[str]
    keypoint_names: list[str]
    keypoints_3d: np.ndarray  # (N, 3)
    keypoints_2d: np.ndarray  # (N, 2)
    in_image: np.ndarray  # (N,) bool
    joints: np.ndarray | None = None  # (J,)
    T_cam_base: np.ndarray | None = None  # (4, 4)
    found: bool = field(default=True, init=False)
    confidence: float = field(default=1.0, init=False)

    @property
    def keypoint_confidence(self) -> np.ndarray:
        """The `confidence` field of the ground-truth 2D keypoint cloud: 1 inside the image, 0 outside."""
        return self.in_image.astype(np.float32)

    @classmethod
    def from_frame(cls, frame, joint_names: list[str]) -> "GroundTruth":
        """The ground truth of a DreamFrame (joints in `joint_names` order, the reader's robot)."""
        return cls(name=frame.name, joint_names=list(joint_names), keypoint_names=list(frame.keypoint_names),
                   keypoints_3d=np.asarray(frame.keypoints_3d, np.float64),
                   keypoints_2d=np.asarray(frame.keypoints_2d, np.float64), in_image=np.asarray(frame.in_image, bool),
                   joints=frame.joints, T_cam_base=frame.T_cam_base)


def estimate_messages(estimate, header) -> dict:
    """{'keypoints', 'keypoints_2d', 'joint_states', 'pose': message} of a found Estimate or a GroundTruth (joint
    states and pose only when known), each with a copy of `header`."""
    messages = {"keypoints": to_keypoints_3d(estimate, header), "keypoints_2d": to_keypoints_2d(estimate, header)}
    if estimate.joints is not None:
        messages["joint_states"] = to_joint_state(estimate, header)
    if estimate.T_cam_base is not None:
        messages["pose"] = to_pose_stamped(estimate, header)
    return messages


def ground_truth_from_messages(name: str, keypoints, keypoints_2d, joint_state, pose, joint_names: list[str],
                               keypoint_names: list[str]) -> GroundTruth:
    """A GroundTruth from its messages (joint_state and pose may be None); ValueError when the keypoint count is
    not the robot's."""
    points = pose_array_points(keypoints)
    uvc = keypoints_2d_from_msg(keypoints_2d).astype(np.float64)
    if len(points) != len(keypoint_names) or len(uvc) != len(keypoint_names):
        raise ValueError(f"ground truth {name}: {len(points)} 3D and {len(uvc)} 2D keypoints, the robot has "
                         f"{len(keypoint_names)}")
    return GroundTruth(name=name, joint_names=list(joint_names), keypoint_names=list(keypoint_names),
                       keypoints_3d=points, keypoints_2d=uvc[:, :2], in_image=uvc[:, 2] > 0.5,
                       joints=None if joint_state is None else joint_positions(joint_state, joint_names),
                       T_cam_base=None if pose is None else pose_to_matrix(pose.pose))


def estimate_from_messages(keypoints, keypoints_2d, joint_state, pose, joint_names: list[str],
                           keypoint_names: list[str]):
    """The found Estimate that `estimate_messages` encoded (confidence unknown: NaN; no timings); ValueError when
    the keypoint count is not the robot's or a joint is missing."""
    from holo_pose_ros.estimator import Estimate

    points = pose_array_points(keypoints)
    uvc = keypoints_2d_from_msg(keypoints_2d).astype(np.float64)
    joints = joint_positions(joint_state, joint_names)
    if len(points) != len(keypoint_names) or len(uvc) != len(keypoint_names) or joints is None:
        raise ValueError(f"estimate messages: {len(points)} 3D and {len(uvc)} 2D keypoints (the robot has "
                         f"{len(keypoint_names)}), joints {list(joint_state.name)}")
    return Estimate(True, float("nan"), joint_names=list(joint_names), keypoint_names=list(keypoint_names),
                    joints=joints, T_cam_base=pose_to_matrix(pose.pose), keypoints_3d=points,
                    keypoints_2d=uvc[:, :2], keypoint_confidence=uvc[:, 2])


# -- rclpy-style messages -> rosbags messages ------------------------------------------------------------------------

def _rosidl_msgtype(msg) -> str:
    """'pkg/msg/Name' of a rosidl-generated Python message (module 'pkg.msg._name')."""
    return f"{type(msg).__module__.split('.')[0]}/msg/{type(msg).__name__}"


def to_rosbags(msg, typestore, msgtype: str | None = None):
    """The rosbags message (of `typestore`) equal to a rosidl-generated Python message such as msg_adapters
    returns, field by field, from the typestore's own field definitions: no per-type code."""
    from rosbags.typesys.store import Nodetype

    msgtype = msgtype or _rosidl_msgtype(msg)
    _, fields = typestore.fielddefs[msgtype]

    def convert(value, desc):
        kind, detail = desc
        if kind == Nodetype.NAME:
            return to_rosbags(value, typestore, detail)
        if kind == Nodetype.BASE:
            base = detail[0]
            return str(value) if base == "string" else bool(value) if base == "bool" else \
                float(value) if base.startswith("float") else int(value)
        (sub_kind, sub_detail), _ = detail  # ARRAY or SEQUENCE
        if sub_kind == Nodetype.BASE:
            base = sub_detail[0]
            if base == "string":
                return [str(v) for v in value]
            return np.array(value, dtype=bool if base == "bool" else np.dtype(base))
        return [convert(v, (sub_kind, sub_detail)) for v in value]

    return typestore.types[msgtype](**{name: convert(getattr(msg, name), desc) for name, desc in fields})


def jazzy_typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def _writer(out: Path, storage: str):
    """An open rosbags Writer (format 9) for the new bag folder `out`."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    if storage not in STORAGES:
        raise ValueError(f"storage must be one of {STORAGES}, got {storage!r}")
    if out.exists():
        raise ValueError(f"output bag {out} already exists (rosbag2 writes a new folder)")
    out.parent.mkdir(parents=True, exist_ok=True)
    writer = Writer(out, version=9, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
    writer.open()
    return writer


class _BagOut:
    """Writes rclpy-style messages into a rosbags Writer, one connection per topic."""

    def __init__(self, writer, typestore):
        self.writer, self.typestore, self.connections = writer, typestore, {}

    def write(self, topic: str, msgtype: str, msg, t_ns: int) -> None:
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.typestore)
        data = self.typestore.serialize_cdr(to_rosbags(msg, self.typestore, msgtype), msgtype)
        self.writer.write(self.connections[topic], int(t_ns), data)


# -- dream-to-bag ----------------------------------------------------------------------------------------------------

def robot_of_folder(folder: str | Path) -> str:
    """The robot named by a DREAM folder's `_object_settings.json` (exported_object_classes) when it is a known
    robot (config/robots/<name>.yaml); ValueError otherwise."""
    import json

    from holo_pose_ros.data.dream import OBJECT_FILE, _resolve_folder
    from holo_pose_ros.resources import config_dir

    path = _resolve_folder(folder) / OBJECT_FILE
    try:
        classes = json.loads(path.read_text()).get("exported_object_classes", [])
    except (OSError, ValueError, AttributeError):
        classes = []
    known = [c for c in classes if isinstance(c, str) and (config_dir() / "robots" / f"{c}.yaml").is_file()]
    if len(known) != 1:
        raise ValueError(f"cannot tell the robot of {folder} from {path.name} (classes {classes}); pass --robot")
    return known[0]


def dream_to_bag(folder: str | Path, out: str | Path, storage: str = "mcap", robot: str | None = None,
                 units: str = "auto", rate_hz: float = DEFAULT_RATE_HZ, start_time_s: float = DEFAULT_START_TIME_S,
                 frame_id: str = DEFAULT_FRAME_ID, image_topic: str = IMAGE_TOPIC,
                 camera_info_topic: str = CAMERA_INFO_TOPIC, ground_truth_ns: str = GROUND_TRUTH_NS,
                 limit: int | None = None, progress: bool = True) -> int:
    """Write the frames of a DREAM folder (file order) into the new bag `out`: per frame an Image (rgb8, the
    decoded image file), a CameraInfo and the ground truth, all with the header (frame_id, start + index / rate)
    and that stamp as log time. Returns the number of frames written."""
    from tqdm import tqdm

    from holo_pose_ros.data.dream import DreamReader

    reader = DreamReader(folder, robot or robot_of_folder(folder), units=units)
    frames = list(reader)[:limit]
    typestore = jazzy_typestore()
    writer = _writer(Path(out), storage)
    bag = _BagOut(writer, typestore)
    try:
        for index, frame in enumerate(tqdm(frames, desc="dream-to-bag", unit="frame", disable=not progress)):
            t_ns = frame_stamp_ns(index, start_time_s, rate_hz)
            header = make_header(t_ns, frame_id)
            truth = GroundTruth.from_frame(frame, reader.robot.joint_names)
            bag.write(camera_info_topic, CAMERA_INFO_MSGTYPE,
                      camera_info_from_K(frame.K, frame.width, frame.height, header), t_ns)
            bag.write(image_topic, IMAGE_MSGTYPE, rgb_to_image(reader.load_image(frame), header), t_ns)
            for name, msg in estimate_messages(truth, header).items():
                bag.write(f"{ground_truth_ns}/{name}", MSGTYPES[name], msg, t_ns)
    finally:
        writer.close()
    return len(frames)


# -- bag-eval --------------------------------------------------------------------------------------------------------

@dataclass
class BagEvalSummary:
    """What bag_eval did: images read, estimated (found / not found), skipped (unreadable image or CameraInfo),
    and the report (None when the bag has no ground truth)."""

    n_images: int
    n_found: int
    n_not_found: int
    n_skipped: int
    out: Path
    report: dict | None
    report_path: Path | None
    n_other_type: int = 0      # messages of another type on the image topic, ignored
    problems: list[str] = field(default_factory=list)  # the bag ended early or was corrupt


class BagReadError(ValueError):
    """A bag that cannot be read at all; the message names the bag and its storage files."""


@contextlib.contextmanager
def open_bag(bag: Path, typestore):
    """An open rosbags AnyReader of `bag` (closed on exit); BagReadError naming the folder and its files when it
    cannot be opened (missing, empty, truncated mcap without its footer, malformed sqlite3, bad metadata.yaml)."""
    from rosbags.highlevel import AnyReader, AnyReaderError

    if not bag.exists():
        raise BagReadError(f"bag {bag} does not exist")
    files = sorted(p.name for p in bag.iterdir()) if bag.is_dir() else [bag.name]
    reader = AnyReader([bag], default_typestore=typestore)
    try:
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError) as e:
        raise BagReadError(f"cannot read bag {bag} ({', '.join(files)}): {e}") from e
    try:
        yield reader
    finally:
        reader.close()


def read_messages(reader, connections, bag: Path, problems: list[str]):
    """(connection, log time ns, message) of `connections`, deserialized; the message is None (logged) when its
    bytes do not deserialize. Stops with a warning (recorded in `problems`) when the storage ends early or is
    corrupt: what was read before still counts."""
    iterator = reader.messages(connections=connections)
    while True:
        try:
            conn, t_ns, raw = next(iterator)
        except StopIteration:
            return
        except Exception as e:  # noqa: BLE001 - rosbags' storage readers raise many kinds on damaged files
            problem = f"bag {bag} is truncated or corrupt: reading stopped early ({type(e).__name__}: {e})"
            logger.warning(problem)
            problems.append(problem)
            return
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except Exception as e:  # noqa: BLE001 - a corrupt message is skipped, never the run
            logger.warning("a %s message on %s at %d ns does not deserialize, skipped: %s", conn.msgtype, conn.topic,
                           t_ns, e)
            msg = None
        yield conn, t_ns, msg


def pick_topic(connections, msgtype: str, wanted: str | None, what: str) -> str:
    """`wanted`, checked, or the bag's only topic with `msgtype` messages (a topic may also carry other types);
    ValueError listing the candidates otherwise."""
    types: dict[str, set[str]] = {}
    for c in connections:
        types.setdefault(c.topic, set()).add(c.msgtype)
    candidates = sorted(t for t, kinds in types.items() if msgtype in kinds)
    if wanted is not None:
        if wanted not in types:
            raise ValueError(f"no topic {wanted} in the bag; {msgtype} topics: {candidates or 'none'}")
        if msgtype not in types[wanted]:
            raise ValueError(f"topic {wanted} is {', '.join(sorted(types[wanted]))}, expected {msgtype}")
        return wanted
    if len(candidates) != 1:
        raise ValueError(f"the bag has {len(candidates)} {msgtype} topics ({candidates}); choose one with "
                         f"--{what}-topic")
    return candidates[0]


def image_and_intrinsics(msg, infos: list[tuple[int, int, object]], t_ns: int, camera_info_topic: str,
                         use_rectified_p: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(RGB image, K) of an Image message with its CameraInfo (camera_info_for); ValueError (the message adapters'
    errors are ValueErrors) when there is none yet, or the image or the intrinsics are unusable."""
    info = camera_info_for(infos, stamp_ns(msg.header.stamp), t_ns)
    if info is None:
        raise ValueError(f"no CameraInfo on {camera_info_topic} at or before this image")
    image = image_to_rgb(msg)
    check_image_size(info, image.shape[1], image.shape[0])
    return image, camera_info_to_K(info, use_rectified_p)


def image_or_skip(msg, infos: list[tuple[int, int, object]], t_ns: int, camera_info_topic: str, skipped,
                  stamp: int) -> tuple[np.ndarray, np.ndarray] | None:
    """image_and_intrinsics, or None (counted in the Counter `skipped`, logged) when the image is unusable."""
    try:
        return image_and_intrinsics(msg, infos, t_ns, camera_info_topic)
    except ValueError as e:
        skipped["unreadable image or CameraInfo"] += 1
        logger.warning("image at %d ns skipped: %s", stamp, e)
        return None


def camera_info_for(infos: list[tuple[int, int, object]], image_stamp: int, image_time: int):
    """The CameraInfo with the image's stamp, else the latest one logged at or before the image, else None."""
    exact = [m for t, s, m in infos if s == image_stamp]
    if exact:
        return exact[-1]
    before = [m for t, s, m in infos if t <= image_time]
    return before[-1] if before else None


def bag_eval(bag: str | Path, model: str | Path, out: str | Path, image_topic: str | None = None,
             camera_info_topic: str | None = None, device: str = "cpu", min_confidence: float | None = None,
             tracking: bool = False, storage: str = "mcap", ground_truth_ns: str = GROUND_TRUTH_NS,
             estimates_ns: str = ESTIMATOR_NS, use_rectified_p: bool = False, limit: int | None = None,
             backend: str = "torch", fit: bool | None = None,
             progress: bool = True) -> BagEvalSummary:
    """Estimate every Image of the bag (log-time order) with the latest CameraInfo (the one with the same stamp
    when there is one) and write the estimates (found frames) into the new bag `out` under `estimates_ns`, with
    the images' headers and log times. When the bag has ground truth (`ground_truth_ns`/keypoints and
    keypoints_2d) for the images' stamps, also write `out`/report.json; images without ground truth are left out
    of the report, and images that could not be estimated count as not found."""
    from tqdm import tqdm

    from holo_pose_ros.estimator import Estimator
    from holo_pose_ros.evaluation.report import build_report, write_report
    from holo_pose_ros.evaluation.run import frame_result

    bag, out = Path(bag), Path(out)
    if out.exists():  # before the model is loaded
        raise ValueError(f"output bag {out} already exists (rosbag2 writes a new folder)")
    if storage not in STORAGES:
        raise ValueError(f"storage must be one of {STORAGES}, got {storage!r}")
    typestore = jazzy_typestore()
    kwargs = {} if min_confidence is None else {"min_confidence": min_confidence}
    estimator = Estimator.from_model(model, device=device, backend=backend, tracking=tracking, fit=fit, **kwargs)
    robot = estimator.robot
    problems: list[str] = []
    with open_bag(bag, typestore) as reader:
        topics = reader.topics
        image_topic = pick_topic(reader.connections, IMAGE_MSGTYPE, image_topic, "image")
        camera_info_topic = pick_topic(reader.connections, CAMERA_INFO_MSGTYPE, camera_info_topic, "info")
        gt_topics = {f"{ground_truth_ns}/{name}": name for name, msgtype in MSGTYPES.items()
                     if topics.get(f"{ground_truth_ns}/{name}") is not None
                     and topics[f"{ground_truth_ns}/{name}"].msgtype == msgtype}
        infos: list[tuple[int, int, object]] = []
        truth_msgs: dict[int, dict[str, object]] = {}
        small = [c for c in reader.connections if (c.topic == camera_info_topic and c.msgtype == CAMERA_INFO_MSGTYPE)
                 or (c.topic in gt_topics and c.msgtype == MSGTYPES[gt_topics[c.topic]])]
        for conn, t_ns, msg in read_messages(reader, small, bag, problems):
            if msg is None:
                continue
            if conn.topic == camera_info_topic:
                infos.append((t_ns, stamp_ns(msg.header.stamp), msg))
            else:
                truth_msgs.setdefault(stamp_ns(msg.header.stamp), {})[gt_topics[conn.topic]] = msg
        has_truth = "keypoints" in gt_topics.values() and "keypoints_2d" in gt_topics.values()
        image_conns = [c for c in reader.connections if c.topic == image_topic and c.msgtype == IMAGE_MSGTYPE]
        others = [c for c in reader.connections if c.topic == image_topic and c.msgtype != IMAGE_MSGTYPE]
        n_other = sum(c.msgcount for c in others)
        if n_other:
            logger.warning("%d message(s) of other types (%s) on %s ignored", n_other,
                           ", ".join(sorted({c.msgtype for c in others})), image_topic)
        n_images = sum(c.msgcount for c in image_conns)
        if limit is not None:
            n_images = min(n_images, limit)

        writer = _writer(out, storage)
        bag_out = _BagOut(writer, typestore)
        results, n_done, found, skipped, no_truth = [], 0, 0, 0, 0
        try:
            messages = read_messages(reader, image_conns, bag, problems)
            for conn, t_ns, msg in tqdm(messages, total=n_images, desc="bag-eval", unit="image", disable=not progress):
                if n_done == n_images:
                    break
                index, n_done = n_done, n_done + 1
                if msg is None:  # logged by read_messages
                    skipped += 1
                    continue
                stamp = stamp_ns(msg.header.stamp)
                estimate, seconds = None, 0.0
                try:
                    image, K = image_and_intrinsics(msg, infos, t_ns, camera_info_topic, use_rectified_p)
                    start = time.perf_counter()
                    estimate = estimator.estimate(image, K)
                    seconds = time.perf_counter() - start
                except ValueError as e:  # ImageConversionError and CameraInfoError are ValueErrors
                    skipped += 1
                    logger.warning("image %d (stamp %d ns) skipped: %s", index, stamp, e)
                if estimate is not None and estimate.found:
                    found += 1
                    for name, out_msg in estimate_messages(estimate, msg.header).items():
                        bag_out.write(f"{estimates_ns}/{name}", MSGTYPES[name], out_msg, t_ns)
                if has_truth:
                    parts = truth_msgs.get(stamp, {})
                    if "keypoints" not in parts or "keypoints_2d" not in parts:
                        no_truth += 1
                        continue
                    truth = ground_truth_from_messages(str(stamp), parts["keypoints"], parts["keypoints_2d"],
                                                       parts.get("joint_states"), parts.get("pose"), robot.joint_names,
                                                       robot.keypoint_names)
                    if estimate is None:
                        estimate = _not_found(robot)
                    results.append(frame_result(truth, estimate, seconds, robot))
        finally:
            writer.close()
    if no_truth:
        logger.warning("%d image(s) have no ground truth at their stamp: left out of the report", no_truth)
    report, report_path = None, None
    if has_truth and results:
        report = build_report(results, robot.spec.joint_names, robot.joint_types, robot.spec.keypoint_names,
                              robot.spec.joint_symmetry)
        report_path = out / "report.json"
        write_report(report, report_path)
    return BagEvalSummary(n_images=n_done, n_found=found, n_not_found=n_done - found - skipped, n_skipped=skipped,
                          out=out, report=report, report_path=report_path, n_other_type=n_other, problems=problems)


def _not_found(robot):
    """An Estimate of nothing found (for an image that could not be estimated at all)."""
    from holo_pose_ros.estimator import Estimate

    return Estimate(False, 0.0, joint_names=robot.joint_names, keypoint_names=robot.keypoint_names)
