"""Compare settings of the estimator's kinematic fit on a generated validation folder (never a test set): for each
variant of config/fit_sweep.yaml (its `fit` over the model card's `estimator.fit_config`), the fitted ADD AUC,
median and mean ADD, mean joint error, the root keypoint's depth error (signed median and median of its size) and the fit's median time, with the feed-forward AUC for
reference. The same network detections feed every variant. A variant's `evidence` swaps parts of the
detections for the truth (config/error_budget.yaml: what each part of the 2D and depth error costs); its
`silhouette` (default: the model card's, off unless it says so) fits the detection's robot mask too (a model with a mask, or `evidence.mask:
truth`, the render's mask); `parts` (default: the card's) fits by parts (fitting/parts.py); `off_image_evidence: false` gives 0 weight to fit keypoints detected outside the image; `min_keypoint_confidence`
drops fit keypoints whose weight (confidence ** weight_power) is below it.
The last column scores the truncated frames alone (3 or more of DREAM's keypoints out of view).

    python scripts/fit_sweep.py --model panda --data data/panda_val_1012 [--frames 160] [--variants config/fit_sweep.yaml]
    python scripts/fit_sweep.py --model panda --data data/panda_val_1012 --variants config/error_budget.yaml
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
import yaml
from tqdm import tqdm

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.meshes import load_link_meshes
from holo_pose_ros.data.render import robot_foreground
from holo_pose_ros.estimator import Detection, Estimator
from holo_pose_ros.evaluation.detection import ground_truth_fit_keypoints
from holo_pose_ros.evaluation.metrics import add_auc
from holo_pose_ros.fitting import Fitter
from holo_pose_ros.model.cards import read_card

ROOT = Path(__file__).resolve().parent.parent


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default="panda")
    parser.add_argument("--data", required=True, help="generated validation folder")
    parser.add_argument("--frames", type=int, default=None, help="the first N frames (default: all)")
    parser.add_argument("--variants", default=str(ROOT / "config" / "fit_sweep.yaml"))
    args = parser.parse_args(argv)
    variants = yaml.safe_load(open(args.variants))["variants"]
    estimator = Estimator.from_model(args.model, backend="onnxruntime", fit=True)
    estimator.decode_mask = estimator.silhouette or any(v.get("silhouette") for v in variants)
    reader = DreamReader(args.data, estimator.robot)
    frames = list(reader)[:args.frames]
    detections = [(f, estimator.detect(reader.load_image(f), f.K)) for f in tqdm(frames, desc="detect")]
    root = estimator.robot.root_index
    meshes = load_link_meshes(estimator.fitter.robot) if any(v.get("silhouette") for v in variants) else None
    model_silhouette, model_parts = estimator.silhouette, estimator.parts
    model_min_weight = estimator.min_keypoint_confidence
    card_fit = (read_card(args.model)[1].get("estimator") or {}).get("fit_config") or {}  # a variant's `fit` on top
    n_keypoints = estimator.robot.n_keypoints
    truncated = np.array([np.count_nonzero(f.in_image) <= n_keypoints - 3 for f, _ in detections])
    print(f"| variant | fitted AUC | median / mean ADD mm | joints deg | root depth error mm (median, median abs) "
          f"| fit ms | feed-forward AUC | fitted AUC, <= {n_keypoints - 3} of {n_keypoints} keypoints in view "
          f"({truncated.sum()} frames) |\n|---|---:|---:|---:|---:|---:|---:|---:|")
    for v in variants:
        estimator.keypoint_weight_power, estimator.depth_prior = v["weight_power"], v["depth_prior"]
        estimator.min_keypoint_confidence = float(v.get("min_keypoint_confidence", model_min_weight))
        estimator.silhouette = bool(v.get("silhouette", model_silhouette))
        estimator.off_image_evidence = bool(v.get("off_image_evidence", True))
        estimator.parts = bool(v.get("parts", model_parts))
        estimator.fitter = Fitter(estimator.fitter.robot, {**card_fit, **(v.get("fit") or {})},
                                  meshes=meshes if estimator.silhouette else None)
        add, add_ff, joints, depth, ms = [], [], [], [], []
        rng = np.random.default_rng(0)
        for frame, detection in detections:
            detection, depth_prior_m = _evidence(detection, frame, estimator, v.get("evidence") or {}, rng, reader)
            out = estimator.estimate_detection(detection, frame.K, methods=("feed-forward", "fitted"),
                                               depth_prior_m=depth_prior_m)
            fitted, ff = out["fitted"], out["feed-forward"]
            add.append(_add(fitted, frame))
            add_ff.append(_add(ff, frame))
            if fitted.found:
                joints.append(np.degrees(np.abs(fitted.joints - frame.joints)).mean())
                depth.append((fitted.keypoints_3d[root, 2] - frame.keypoints_3d[root, 2]) * 1e3)
                ms.append(fitted.timings_ms.get("fit", np.nan))
        add, depth = np.array(add), np.array(depth)
        print(f"| {v['name']} | {add_auc(add):.1f} | {np.median(add) * 1e3:.0f} / {np.mean(add[np.isfinite(add)]) * 1e3:.0f} | "
              f"{np.mean(joints):.1f} | {np.median(depth):+.0f}, {np.median(np.abs(depth)):.0f} | {np.nanmedian(ms):.1f} | "
              f"{add_auc(np.array(add_ff)):.1f} | {add_auc(add[truncated]) if truncated.any() else float('nan'):.1f} |",
              flush=True)
    return 0


def _evidence(detection: Detection | None, frame, estimator: Estimator, evidence: dict,
              rng: np.random.Generator, reader: DreamReader) -> tuple[Detection | None, float | None]:
    """The detection a variant's fit sees and its depth prior (metres; None: the heads'). `evidence` keys:
    keypoints: detected (default) | truth | shuffled (each frame's detected 2D errors dealt to its keypoints at
    random: the same sizes without their spatial correlation); clip_px: errors longer than this shortened to it;
    noise_px: sigma of Gaussian noise added (pixels); depth: heads (default) | truth; mask: detected (default) |
    truth (the render's robot mask). Confidences stay detected."""
    if detection is None or not evidence:
        return detection, None
    mask = evidence.get("mask", "detected")
    if mask == "truth":
        true_mask = reader.load_mask(frame)
        if true_mask is None:
            raise ValueError(f"evidence.mask: truth, but frame {frame.name} has no mask file")
        detection = dataclasses.replace(detection, mask=robot_foreground(true_mask))
    elif mask != "detected":
        raise ValueError(f"evidence.mask: {mask!r} is not detected or truth")
    truth = ground_truth_fit_keypoints(estimator.robot, frame)
    errors = detection.uv - truth
    source = evidence.get("keypoints", "detected")
    if source == "truth":
        errors = np.zeros_like(errors)
    elif source == "shuffled":
        errors = errors[rng.permutation(len(errors))]
    elif source != "detected":
        raise ValueError(f"evidence.keypoints: {source!r} is not detected, truth or shuffled")
    if "clip_px" in evidence:
        length = np.linalg.norm(errors, axis=1, keepdims=True)
        errors = errors * np.minimum(1.0, float(evidence["clip_px"]) / np.maximum(length, 1e-9))
    errors = errors + rng.normal(0.0, float(evidence.get("noise_px", 0.0)), errors.shape)
    depth = evidence.get("depth", "heads")
    if depth not in ("heads", "truth"):
        raise ValueError(f"evidence.depth: {depth!r} is not heads or truth")
    prior = estimator.fitter.prior_depth(frame.joints, frame.T_cam_base) if depth == "truth" else None
    return dataclasses.replace(detection, uv=truth + errors), prior


def _add(estimate, frame) -> float:
    """ADD (metres) of an estimate against the frame's true keypoints; inf when the robot was not found."""
    return float(np.linalg.norm(estimate.keypoints_3d - frame.keypoints_3d, axis=1).mean()) if estimate.found else np.inf


if __name__ == "__main__":
    sys.exit(main())
