"""Calibrate the fit's depth prior on a generated validation folder (never a test set): the median ratio of the true
root-keypoint depth to DepthNet's, through the deployed localize + crop. A network that sees the robot a little
small (its heatmap peaks pulled towards the crop centre) reads it a little far; this one factor, stored in the model
card (estimator.depth_prior_scale), removes that bias from the prior without touching the 2D evidence."""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.estimator import Estimator


def depth_prior_scale(estimator: Estimator, reader: DreamReader, progress: bool = True) -> tuple[float, int]:
    """(median of true / DepthNet's root depth over the frames where the estimator's default method found the robot,
    that number of frames); (1.0, 0) when it found none. The gate keeps out detections the fit rejects (e.g. the
    paper heads' guess on a black frame)."""
    root = estimator.robot.root_index
    ratios = []
    frames = list(reader)
    for frame, image in tqdm(reader.images(frames), total=len(frames), desc="depth calibration", unit="frame",
                             disable=not progress):
        estimator.reset()
        detection = estimator.detect(image, frame.K)
        methods = ("feed-forward", "fitted") if estimator.fit else ("feed-forward",)
        estimates = estimator.estimate_detection(detection, frame.K, None, methods)
        depth = estimates["feed-forward"].keypoints_3d[root, 2] if estimates["feed-forward"].found else 0.0
        if estimates[methods[-1]].found and depth > 0:
            ratios.append(frame.keypoints_3d[root, 2] / depth)
    return (float(np.median(ratios)), len(ratios)) if ratios else (1.0, 0)
