"""Pseudo-labels of the user's images: the deployed estimator's own fits, kept only where they are trustworthy.
A fit is kept when the robot is found with a confident estimate and a second look agrees with it: the frame is
cropped again around the first fit's keypoints and fitted again; the two fits' projected keypoints must agree to
a fraction of the robot's image size (crops that differ see the robot at another scale and offset, so a fit
that is right twice is rarely an accident). With the robot's joint states both fits use them (known_joints)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from holo_pose_ros.adaptation.sources import SourceFrame
from holo_pose_ros.geometry.camera import in_image, project


@dataclass
class PseudoLabel:
    """The fitted robot of one source frame: its joints (J,), base pose T_cam<-base (4, 4), fit keypoints
    projected (M, 2) image px with their in-image flags (M,), root depth (metres), the crop box the estimator
    used (x0, y0, side) px, the estimate's confidence and the two looks' disagreement (fraction of the extent)."""

    frame: int
    joints: np.ndarray
    T_cam_base: np.ndarray
    uv_fit_px: np.ndarray
    visible_fit: np.ndarray
    root_depth_m: float
    box: np.ndarray
    confidence: float
    disagreement: float


def _fit_keypoints_px(estimator, q: np.ndarray, T: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(M, 2) image px of the fit keypoints of joints q and pose T (the fit robot's FK, float64)."""
    robot = estimator.fitter.robot
    with torch.inference_mode():
        points = robot.fit_keypoints_in_camera(torch.as_tensor(q[None], dtype=robot.dtype),
                                               torch.as_tensor(T[None], dtype=robot.dtype))[0].cpu().numpy()
    return project(points, K)


def label_frame(estimator, index: int, frame: SourceFrame) -> PseudoLabel | None:
    """The pseudo-label candidate of one frame (before any threshold), None when the robot is not found twice."""
    estimator.reset()
    first = estimator.estimate_methods(frame.image, frame.K, frame.joints, ("fitted",))["fitted"]
    if not first.found:
        return None
    detection = estimator.detect(frame.image, frame.K, uv_hint=first.keypoints_2d)  # the second look
    second = estimator.estimate_detection(detection, frame.K, frame.joints, ("fitted",))["fitted"]
    estimator.reset()
    if not second.found:
        return None
    uv1 = _fit_keypoints_px(estimator, first.joints, first.T_cam_base, frame.K)
    uv2 = _fit_keypoints_px(estimator, second.joints, second.T_cam_base, frame.K)
    H, W = frame.image.shape[:2]
    visible = in_image(uv1, W, H)
    extent = max(float(np.ptp(uv1[visible], axis=0).max()) if visible.sum() >= 2 else 0.0, 1.0)
    disagreement = float(np.median(np.linalg.norm(uv1 - uv2, axis=1))) / extent
    return PseudoLabel(index, first.joints, first.T_cam_base, uv1, visible, float(first.root_depth_m),
                       np.asarray(first.box, dtype=np.float64), float(min(first.confidence, second.confidence)),
                       disagreement)


def select_labels(candidates: list[PseudoLabel], min_confidence: float, max_disagreement: float,
                  min_visible: int) -> list[PseudoLabel]:
    """The candidates confident enough, whose two looks agree and with enough fit keypoints in the image."""
    return [c for c in candidates if c.confidence >= min_confidence and c.disagreement <= max_disagreement
            and int(c.visible_fit.sum()) >= min_visible]
