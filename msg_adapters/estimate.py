"""Estimate -> ROS messages, each with a copy of the input image's header. Duck-typed on the Estimate's fields
(holo_pose_ros.estimator is never imported here: it pulls in torch; only the numpy geometry is). Metres, radians, pixels; camera frame
OpenCV (x right, y down, z forward).

Outputs and their message types:
- joints: sensor_msgs/JointState, names and order of the robot YAML, radians (metres for prismatic joints);
- the robot base in the camera frame: geometry_msgs/PoseStamped and geometry_msgs/TransformStamped
  (parent = the image's frame_id, child = a configurable frame);
- 3D keypoints: geometry_msgs/PoseArray in the camera frame, metres, identity orientations;
- 2D keypoints: sensor_msgs/PointCloud2 with one float32 point per keypoint and the fields `u`, `v` (pixels of the
  input image, (0, 0) the centre of the top-left pixel) and `confidence` ([0, 1]). Chosen over a PoseArray
  because the fields are named (nobody mistakes pixels for metres; RViz refuses to draw it rather than drawing
  nonsense) and the confidence has a place; read it back with `keypoints_2d_from_msg`;
- both keypoint messages list the keypoints in the robot YAML's order (Estimate.keypoint_names);
- RViz skeleton: visualization_msgs/MarkerArray, a LINE_LIST along the keypoint tree and a SPHERE_LIST of the
  keypoints coloured by confidence (red 0 -> green 1), in the camera frame, with a short lifetime.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import (Point, Pose, PoseArray, PoseStamped, PoseWithCovarianceStamped, Quaternion,
                               TransformStamped, Vector3)
from sensor_msgs.msg import JointState, PointCloud2, PointField
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from holo_pose_ros.geometry.alignment import matrix_to_quaternion_xyzw, quaternion_xyzw_to_matrix
from msg_adapters.header import copy_header

if TYPE_CHECKING:
    from holo_pose_ros.estimator import Estimate

KEYPOINT_2D_FIELDS = ("u", "v", "confidence")


def _require_found(estimate: "Estimate") -> None:
    """ValueError for an estimate without a result (robot not found)."""
    if not estimate.found:
        raise ValueError("the estimate has no result (robot not found); publish nothing for this frame")


def _quaternion(R: np.ndarray) -> Quaternion:
    x, y, z, w = (float(c) for c in matrix_to_quaternion_xyzw(R))
    return Quaternion(x=x, y=y, z=z, w=w)


def _point(p: np.ndarray) -> Point:
    return Point(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def to_joint_state(estimate: "Estimate", header) -> JointState:
    """The estimated joints (radians; metres for prismatic joints), named as in the robot YAML."""
    _require_found(estimate)
    return JointState(header=copy_header(header), name=list(estimate.joint_names),
                      position=[float(q) for q in estimate.joints])


def to_pose_stamped(estimate: "Estimate", header) -> PoseStamped:
    """The robot base's pose in the camera frame (T_cam_base), metres, in the image's frame_id."""
    _require_found(estimate)
    T = np.asarray(estimate.T_cam_base, dtype=np.float64)
    pose = Pose(position=_point(T[:3, 3]), orientation=_quaternion(T[:3, :3]))
    return PoseStamped(header=copy_header(header), pose=pose)


def to_pose_with_covariance(T_cam_base: np.ndarray, covariance: np.ndarray, header) -> PoseWithCovarianceStamped:
    """A pose (4, 4), metres, with its (6, 6) covariance (x, y, z, rotation about x, y, z; row-major, as ROS
    orders it), in the header's frame: the calibration of the camera to the robot base."""
    T = np.asarray(T_cam_base, dtype=np.float64)
    C = np.asarray(covariance, dtype=np.float64)
    if T.shape != (4, 4) or C.shape != (6, 6) or not (np.isfinite(T).all() and np.isfinite(C).all()):
        raise ValueError("a pose with covariance needs a finite 4 x 4 pose and a finite 6 x 6 covariance")
    msg = PoseWithCovarianceStamped(header=copy_header(header))
    msg.pose.pose = Pose(position=_point(T[:3, 3]), orientation=_quaternion(T[:3, :3]))
    msg.pose.covariance = [float(v) for v in C.ravel()]
    return msg


def to_transform_stamped(estimate: "Estimate", header, child_frame_id: str) -> TransformStamped:
    """T_cam_base as a transform from the image's frame_id (parent, the camera optical frame) to `child_frame_id`."""
    _require_found(estimate)
    T = np.asarray(estimate.T_cam_base, dtype=np.float64)
    msg = TransformStamped(header=copy_header(header), child_frame_id=child_frame_id)
    msg.transform.translation = Vector3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3]))
    msg.transform.rotation = _quaternion(T[:3, :3])
    return msg


def to_keypoints_3d(estimate: "Estimate", header) -> PoseArray:
    """The 3D keypoints (camera frame, metres) as poses with identity orientation, in the robot YAML's order."""
    _require_found(estimate)
    poses = [Pose(position=_point(p), orientation=Quaternion(w=1.0)) for p in np.asarray(estimate.keypoints_3d)]
    return PoseArray(header=copy_header(header), poses=poses)


def to_keypoints_2d(estimate: "Estimate", header) -> PointCloud2:
    """The 2D keypoints as a PointCloud2 of float32 (u, v, confidence): pixels of the input image and [0, 1]."""
    _require_found(estimate)
    uv = np.asarray(estimate.keypoints_2d, dtype=np.float32).reshape(-1, 2)
    confidence = np.asarray(estimate.keypoint_confidence, dtype=np.float32).reshape(-1, 1)
    points = np.ascontiguousarray(np.hstack([uv, confidence]), dtype="<f4")
    fields = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
              for i, name in enumerate(KEYPOINT_2D_FIELDS)]
    msg = PointCloud2(header=copy_header(header), height=1, width=len(points), fields=fields, is_bigendian=False,
                      point_step=12, row_step=12 * len(points), is_dense=bool(np.isfinite(points).all()))
    msg.data = points.tobytes()
    return msg


def keypoints_2d_from_msg(msg) -> np.ndarray:
    """(N, 3) float32 rows (u px, v px, confidence) from a PointCloud2 written by `to_keypoints_2d`."""
    offsets = {f.name: int(f.offset) for f in msg.fields if int(f.datatype) == PointField.FLOAT32}
    missing = [name for name in KEYPOINT_2D_FIELDS if name not in offsets]
    if missing or msg.is_bigendian:
        raise ValueError(f"not a 2D keypoint cloud: missing float32 fields {missing} or big-endian")
    dtype = np.dtype({"names": list(KEYPOINT_2D_FIELDS), "formats": ["<f4"] * 3,
                      "offsets": [offsets[n] for n in KEYPOINT_2D_FIELDS], "itemsize": int(msg.point_step)})
    points = np.frombuffer(msg.data, dtype=dtype, count=int(msg.width) * int(msg.height))
    return np.stack([points[n] for n in KEYPOINT_2D_FIELDS], axis=1)


def to_markers(estimate: "Estimate", header, parents: list[int], lifetime_s: float = 0.5,
               ns: str = "holo_pose") -> MarkerArray:
    """RViz skeleton in the camera frame: a LINE_LIST (id 0) joining each keypoint to its parent (`parents`, -1
    for none) and a SPHERE_LIST (id 1) of the keypoints coloured by confidence; both expire after `lifetime_s`."""
    _require_found(estimate)
    points = [_point(p) for p in np.asarray(estimate.keypoints_3d)]
    lifetime = Duration(sec=int(lifetime_s), nanosec=int(round((lifetime_s % 1.0) * 1e9)))
    common = dict(ns=ns, action=Marker.ADD, lifetime=lifetime, pose=Pose(orientation=Quaternion(w=1.0)))
    lines = Marker(header=copy_header(header), id=0, type=Marker.LINE_LIST, scale=Vector3(x=0.01),
                   color=ColorRGBA(r=0.1, g=0.9, b=0.2, a=1.0), **common)
    lines.points = [p for i, parent in enumerate(parents) if parent >= 0 for p in (points[parent], points[i])]
    confidence = np.clip(np.nan_to_num(np.asarray(estimate.keypoint_confidence, dtype=np.float64)), 0.0, 1.0)
    spheres = Marker(header=copy_header(header), id=1, type=Marker.SPHERE_LIST,
                     scale=Vector3(x=0.03, y=0.03, z=0.03), color=ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0), **common)
    spheres.points = points
    spheres.colors = [ColorRGBA(r=float(1.0 - c), g=float(c), b=0.0, a=1.0) for c in confidence]
    return MarkerArray(markers=[lines, spheres])


# -- messages -> numpy (readers of what the converters above write) -----------------------------------------

def pose_array_points(msg) -> np.ndarray:
    """(N, 3) float64 positions of a geometry_msgs/PoseArray (3D keypoints), metres."""
    return np.array([[p.position.x, p.position.y, p.position.z] for p in msg.poses], dtype=np.float64).reshape(-1, 3)


def pose_to_matrix(pose) -> np.ndarray:
    """(4, 4) transform of a geometry_msgs/Pose."""
    q = pose.orientation
    T = np.eye(4)
    T[:3, :3] = quaternion_xyzw_to_matrix([q.x, q.y, q.z, q.w])
    T[:3, 3] = [pose.position.x, pose.position.y, pose.position.z]
    return T


def joint_positions(msg, names: list[str]) -> np.ndarray | None:
    """(J,) positions of a sensor_msgs/JointState in `names` order (matched by name), None if any is missing."""
    by_name = dict(zip(msg.name, np.asarray(msg.position, dtype=np.float64)))
    if not all(n in by_name for n in names):
        return None
    return np.array([by_name[n] for n in names], dtype=np.float64)
