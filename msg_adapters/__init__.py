"""ROS message <-> numpy / Estimate conversions for holo_pose_ros. Imports message types and numpy only, never
torch or the estimator, so bag tools and light clients can use it. Every converted output carries the input
image's header (stamp and frame_id), never the current time."""

from msg_adapters.camera_info import CameraInfoError, camera_info_from_K, camera_info_to_K, check_image_size
from msg_adapters.estimate import (joint_positions, keypoints_2d_from_msg, pose_array_points, pose_to_matrix,
                                   to_joint_state, to_keypoints_2d, to_keypoints_3d, to_markers, to_pose_stamped,
                                   to_pose_with_covariance, to_transform_stamped)
from msg_adapters.header import copy_header, make_header, stamp_ns
from msg_adapters.image import (DEFAULT_MAX_PIXELS, ENCODINGS, ImageConversionError, image_to_rgb,
                                rgb_to_image)
from msg_adapters.joint_states import (joint_positions_by_name, joint_state_arrays, joint_state_from_arrays,
                                       to_diagnostic_status)

__all__ = [
    "CameraInfoError", "camera_info_from_K", "camera_info_to_K", "check_image_size",
    "joint_positions", "keypoints_2d_from_msg", "pose_array_points", "pose_to_matrix", "to_joint_state",
    "to_keypoints_2d", "to_keypoints_3d", "to_markers", "to_pose_stamped", "to_pose_with_covariance",
    "to_transform_stamped",
    "copy_header", "make_header", "stamp_ns",
    "DEFAULT_MAX_PIXELS", "ENCODINGS", "ImageConversionError", "image_to_rgb", "rgb_to_image",
    "joint_positions_by_name", "joint_state_arrays", "joint_state_from_arrays", "to_diagnostic_status",
]
