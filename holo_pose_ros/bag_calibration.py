"""`holo-pose calibrate`: the camera-to-robot calibration from a ROS 2 bag (mcap or sqlite3, no DDS) with the
robot's trusted joint states. Each image is estimated with the joint state nearest its stamp (by joint name, any
order, extra joints ignored) so that only T_cam<-base is fitted; the robust average of those poses is the
calibration (holo_pose_ros/calibration.py). The same frames estimated without the joints give the comparison a
user asks for: how much the trusted joints are worth. Defaults: config/estimator.yaml (the node's calibration
parameters), so the command and the node agree."""

from __future__ import annotations

import logging
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from holo_pose_ros.bags import (CAMERA_INFO_MSGTYPE, GROUND_TRUTH_NS, IMAGE_MSGTYPE, image_or_skip,
                                jazzy_typestore, open_bag, pick_topic, read_messages)
from holo_pose_ros.calibration import Calibration, average_poses, pose_error
from holo_pose_ros.geometry.alignment import matrix_to_quaternion_xyzw
from holo_pose_ros.monitoring.stamps import NS, StampBuffer
from msg_adapters import stamp_ns
from msg_adapters.estimate import pose_to_matrix
from msg_adapters.joint_states import joint_positions_by_name

logger = logging.getLogger(__name__)
JOINT_STATE_MSGTYPE = "sensor_msgs/msg/JointState"
POSE_MSGTYPE = "geometry_msgs/msg/PoseStamped"


def calibration_defaults() -> dict:
    """The calibration parameters of config/estimator.yaml (the node's): window, tolerance, outlier limits."""
    from holo_pose_ros.resources import config_dir

    with open(config_dir() / "estimator.yaml") as f:
        params = yaml.safe_load(f)["holo_pose_estimator"]["ros__parameters"]
    return {k: params[k] for k in ("joint_states_tolerance_s", "calibration_window", "calibration_max_translation_m",
                                   "calibration_max_rotation_deg")}


@dataclass
class BagCalibration:
    """What `calibrate_bag` found: the calibration with trusted joints, the one without (same frames), counts of
    skipped images by reason, and the errors against the bag's ground-truth pose when it has one."""

    calibration: Calibration | None
    without_joints: Calibration | None
    n_images: int
    n_used: int
    frame_id: str
    skipped: Counter = field(default_factory=Counter)
    truth: np.ndarray | None = None
    errors: dict = field(default_factory=dict)


def calibrate_bag(bag: str | Path, model: str | Path, joint_states_topic: str, image_topic: str | None = None,
                  camera_info_topic: str | None = None, window: int | None = None, tolerance_s: float | None = None,
                  max_translation_m: float | None = None, max_rotation_deg: float | None = None,
                  compare: bool = True, backend: str = "torch", device: str = "cpu", limit: int | None = None,
                  ground_truth_ns: str = GROUND_TRUTH_NS, progress: bool = True) -> BagCalibration:
    """Calibrate from the bag's images (log-time order) with the joint states of `joint_states_topic`; `window`
    (default: every usable frame) bounds the frames averaged, the last ones. See the module docstring."""
    from tqdm import tqdm

    from holo_pose_ros.estimator import Estimator

    defaults = calibration_defaults()
    tolerance_ns = int(NS * (defaults["joint_states_tolerance_s"] if tolerance_s is None else tolerance_s))
    max_t = defaults["calibration_max_translation_m"] if max_translation_m is None else max_translation_m
    max_r = defaults["calibration_max_rotation_deg"] if max_rotation_deg is None else max_rotation_deg
    bag = Path(bag)
    estimator = Estimator.from_model(model, device=device, backend=backend)
    robot = estimator.robot
    typestore = jazzy_typestore()
    skipped, problems = Counter(), []
    poses, poses_free, truths = [], [], []
    with open_bag(bag, typestore) as reader:
        image_topic = pick_topic(reader.connections, IMAGE_MSGTYPE, image_topic, "image")
        camera_info_topic = pick_topic(reader.connections, CAMERA_INFO_MSGTYPE, camera_info_topic, "info")
        joint_states_topic = pick_topic(reader.connections, JOINT_STATE_MSGTYPE, joint_states_topic, "joint-states")
        truth_topic = f"{ground_truth_ns}/pose"
        small = [c for c in reader.connections if (c.topic, c.msgtype) in {
            (camera_info_topic, CAMERA_INFO_MSGTYPE), (joint_states_topic, JOINT_STATE_MSGTYPE),
            (truth_topic, POSE_MSGTYPE)}]
        infos, joints, truth = [], StampBuffer(history_s=1e9), {}
        for conn, t_ns, msg in read_messages(reader, small, bag, problems):
            if msg is None:
                skipped["undeserializable message"] += 1
                continue
            if conn.topic == camera_info_topic:
                infos.append((t_ns, stamp_ns(msg.header.stamp), msg))
            elif conn.topic == joint_states_topic:
                try:
                    selection, stamp = joint_positions_by_name(msg, robot.joint_names)
                except ValueError as e:
                    skipped["malformed joint state"] += 1
                    logger.warning("joint state at %d ns skipped: %s", stamp_ns(msg.header.stamp), e)
                    continue
                joints.add(stamp, selection)
            else:
                truth[stamp_ns(msg.header.stamp)] = pose_to_matrix(msg.pose)
        image_conns = [c for c in reader.connections if c.topic == image_topic and c.msgtype == IMAGE_MSGTYPE]
        n_images = sum(c.msgcount for c in image_conns) if limit is None else min(limit, sum(c.msgcount for c in image_conns))
        frame_id, done = "", 0
        for conn, t_ns, msg in tqdm(read_messages(reader, image_conns, bag, problems), total=n_images,
                                    desc="calibrate", unit="image", disable=not progress):
            if done == n_images:
                break
            done += 1
            if msg is None:
                skipped["undeserializable image"] += 1
                continue
            stamp = stamp_ns(msg.header.stamp)
            frame_id = frame_id or msg.header.frame_id
            nearest = joints.nearest(stamp, tolerance_ns)
            if nearest is None:
                skipped["no joint state within the tolerance"] += 1
                continue
            selection = nearest[1]
            if selection.missing or selection.nonfinite:
                skipped["joint state lacks joints"] += 1
                logger.warning("image at %d ns skipped: joint state lacks %s", stamp,
                               ", ".join(selection.missing + selection.nonfinite))
                continue
            usable = image_or_skip(msg, infos, t_ns, camera_info_topic, skipped, stamp)
            if usable is None:
                continue
            image, K = usable
            estimate = estimator.calibrate(image, K, selection.values)
            if not estimate.found:
                skipped["robot not found"] += 1
                continue
            poses.append(estimate.T_cam_base)
            if stamp in truth:
                truths.append(truth[stamp])
            if compare:
                free = estimator.estimate(image, K)
                if free.found:
                    poses_free.append(free.T_cam_base)
    if window:
        poses, poses_free = poses[-window:], poses_free[-window:]
    calibration = average_poses(np.stack(poses), max_t, max_r) if poses else None
    without = average_poses(np.stack(poses_free), max_t, max_r) if poses_free else None
    result = BagCalibration(calibration, without, done, len(poses), frame_id, skipped)
    if truths:
        result.truth = average_poses(np.stack(truths), max_t, max_r).T_cam_base
        for name, c in (("with_joints", calibration), ("without_joints", without)):
            if c is not None:
                dt, dr = pose_error(c.T_cam_base, result.truth)
                result.errors[name] = {"translation_mm": 1e3 * dt, "rotation_deg": dr}
    for problem in problems:
        skipped[problem] += 1
    return result


def calibration_document(result: BagCalibration, bag: str | Path, model: str | Path, child_frame_id: str) -> dict:
    """The calibration.yaml content: the pose (translation, quaternion xyzw, matrix) of the robot base in the
    camera frame, its covariance, and how it was made."""
    c = result.calibration
    doc = {"parent_frame_id": result.frame_id, "child_frame_id": child_frame_id,
           "translation_m": [float(v) for v in c.T_cam_base[:3, 3]],
           "quaternion_xyzw": [float(v) for v in matrix_to_quaternion_xyzw(c.T_cam_base[:3, :3])],
           "matrix": [[float(v) for v in row] for row in c.T_cam_base],
           "covariance": {"order": "x y z (m), rotation about x y z (rad); of the average",
                          "matrix": [[float(v) for v in row] for row in c.covariance]},
           "frames": {"images": result.n_images, "estimated": result.n_used, "averaged": c.n_used,
                      "rejected_as_outliers": c.n_rejected, "skipped": dict(result.skipped)},
           "spread": {"translation_mm": 1e3 * c.translation_spread_m, "rotation_deg": c.rotation_spread_deg},
           "made_by": {"bag": str(bag), "model": str(model), "at": time.strftime("%Y-%m-%dT%H:%M:%S%z")}}
    if result.errors:
        doc["error_against_ground_truth"] = result.errors
    return doc


def format_calibration(result: BagCalibration) -> str:
    """A few lines for the terminal."""
    c = result.calibration
    lines = [f"{result.n_images} images: {result.n_used} estimated with the trusted joints, "
             f"{sum(result.skipped.values())} skipped" + (f" ({dict(result.skipped)})" if result.skipped else "")]
    if c is None:
        return "\n".join(lines + ["no calibration: no image could be estimated with trusted joints"])
    t, sigma = c.T_cam_base[:3, 3], np.sqrt(np.diag(c.covariance))
    lines.append(f"T_cam<-base: t = [{t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}] m (sigma {1e3 * sigma[:3].max():.1f} mm), "
                 f"{c.n_used} frames averaged, {c.n_rejected} rejected; spread {1e3 * c.translation_spread_m:.1f} mm, "
                 f"{c.rotation_spread_deg:.2f} deg")
    for name, e in result.errors.items():
        lines.append(f"error against the ground truth, {name.replace('_', ' ')}: {e['translation_mm']:.1f} mm, "
                     f"{e['rotation_deg']:.2f} deg")
    if "with_joints" in result.errors and "without_joints" in result.errors:
        ratio = result.errors["without_joints"]["translation_mm"] / max(result.errors["with_joints"]["translation_mm"], 1e-9)
        lines.append(f"the trusted joints make the calibration {ratio:.1f}x more accurate in translation")
    return "\n".join(lines)
