"""sensor_msgs/CameraInfo -> pinhole intrinsics K (3x3, pixels), with the checks that keep a bad calibration
from reaching the estimator. Duck-typed on the fields (k, p, width, height)."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import CameraInfo


class CameraInfoError(ValueError):
    """A CameraInfo whose intrinsics cannot be used; the message says why."""


def camera_info_to_K(msg, use_rectified_p: bool = False) -> np.ndarray:
    """K (3, 3) float64 from `k`, or from `p[:, :3]` for rectified images. CameraInfoError when it is all zeros
    (an uncalibrated camera), not finite, has fx or fy <= 0, or a last row other than (0, 0, 1)."""
    field, values, size = ("p", msg.p, 12) if use_rectified_p else ("k", msg.k, 9)
    values = np.asarray(values, dtype=np.float64).ravel()
    if values.size != size:
        raise CameraInfoError(f"CameraInfo.{field} has {values.size} values, expected {size}")
    K = values.reshape(3, -1)[:, :3].copy()
    if not np.isfinite(K).all():
        raise CameraInfoError(f"CameraInfo.{field} is not finite: {K.ravel().tolist()}")
    if not K.any():
        raise CameraInfoError(f"CameraInfo.{field} is all zeros (is the camera calibrated?)")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CameraInfoError(f"CameraInfo.{field} has fx = {K[0, 0]}, fy = {K[1, 1]}; both must be > 0")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise CameraInfoError(f"CameraInfo.{field} has last row {K[2].tolist()}, expected [0, 0, 1]")
    return K


def check_image_size(msg, width: int, height: int) -> None:
    """CameraInfoError when the CameraInfo states a size (non-zero) other than the image's width x height px."""
    if msg.width and msg.height and (int(msg.width), int(msg.height)) != (width, height):
        raise CameraInfoError(f"CameraInfo is for {msg.width} x {msg.height} px but the image is {width} x "
                              f"{height} px (wrong camera_info topic?)")


def camera_info_from_K(K: np.ndarray, width: int, height: int, header) -> CameraInfo:
    """A CameraInfo of an undistorted pinhole camera (plumb_bob, zero distortion), K and P = [K | 0], R = I."""
    K = np.asarray(K, dtype=np.float64)
    P = np.zeros((3, 4))
    P[:, :3] = K
    msg = CameraInfo(header=header, width=int(width), height=int(height), distortion_model="plumb_bob")
    msg.d = [0.0] * 5
    msg.k = K.ravel().tolist()
    msg.r = np.eye(3).ravel().tolist()
    msg.p = P.ravel().tolist()
    return msg
