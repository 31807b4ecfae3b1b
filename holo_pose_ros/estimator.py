"""The inference API every caller uses (CLI, ROS nodes, evaluation, tests): load a model once, then
`estimate(image, K) -> Estimate`. No ground truth of any kind reaches it: the robot is found in the raw image by
a first pass over the whole letterboxed frame (or, when tracking, from the previous frame's keypoints), and its
box feeds a second, accurate pass. Camera frame OpenCV; metres, radians, pixels."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from holo_pose_ros.geometry.camera import project
from holo_pose_ros.geometry.crop import CROP_MARGIN, crop_affine, crop_box_from_keypoints, crop_image, full_image_box
from holo_pose_ros.model.network import HolisticNet, add_kinematics
from holo_pose_ros.robots.kinematics import RobotModel

BACKENDS = ("torch", "onnxruntime")
LOCALIZE_MIN_KEYPOINT_CONFIDENCE = 0.2  # fit keypoints of the full-image pass that bound the crop box


@dataclass
class Estimate:
    """One frame's result. When `found` is False only `confidence`, `timings_ms` and the names are meaningful."""

    found: bool
    confidence: float                    # probability that the robot is in the crop, [0, 1]
    joint_names: list[str]
    keypoint_names: list[str]
    joints: np.ndarray | None = None     # (J,) radians / metres (prismatic)
    T_cam_base: np.ndarray | None = None  # (4, 4) robot base in the camera frame
    keypoints_3d: np.ndarray | None = None  # (N, 3) metres, camera frame (FK of the estimate)
    keypoints_2d: np.ndarray | None = None  # (N, 2) pixels of the input image
    keypoint_confidence: np.ndarray | None = None  # (N,) heatmap sharpness, [0, 1]
    root_depth_m: float | None = None
    box: np.ndarray | None = None        # (x0, y0, side) of the crop, image pixels (edge coordinates)
    tracked: bool = False                # the crop came from the previous frame
    timings_ms: dict[str, float] = field(default_factory=dict)


@dataclass
class Detection:
    """The 2D evidence of one frame: the crop box and the fit keypoints seen in it (network only, no fit)."""

    presence: float                      # probability that the robot is in the crop, [0, 1]
    box: np.ndarray                      # (x0, y0, side) of the crop, image pixels (edge coordinates)
    uv: np.ndarray                       # (M, 2) fit keypoints, pixels of the input image
    confidence: np.ndarray               # (M,) heatmap confidence, [0, 1]
    out: dict                            # the crop pass's raw network output (batch of 1)
    K_crop: np.ndarray                   # (3, 3) intrinsics of the crop


class Estimator:
    """Holistic robot pose from raw RGB images. `tracking` reuses the previous frame's keypoints for the crop (one
    network pass a frame) and re-localizes when the confidence drops below `min_confidence`."""

    def __init__(self, net: HolisticNet, robot: RobotModel, device: str | torch.device = "cpu",
                 min_confidence: float = 0.5, tracking: bool = False, network: Callable | None = None,
                 backend: str = "torch"):
        self.device = torch.device(device)
        self.net = net.to(self.device).eval()
        self.network = network or self.net  # what runs a pass: the torch module, or an OnnxNetwork standing in
        self.backend = backend
        self.robot = robot if robot.device == self.device else RobotModel(robot.spec, device=self.device)
        self.size = net.cfg.input_size
        self.min_confidence, self.tracking = min_confidence, tracking
        self._previous: Estimate | None = None

    @classmethod
    def from_model(cls, model: str | Path, device: str = "cpu", backend: str = "torch", threads: int | None = None,
                   **kwargs) -> "Estimator":
        """Load a shipped model by name ('panda') or a model card / weights path. `backend` 'onnxruntime' runs the
        network's ONNX export (made once, cached) with `threads` intra-op threads."""
        from holo_pose_ros.model.weights import load_model

        if backend not in BACKENDS:
            raise ValueError(f"unknown backend '{backend}'; choose one of {', '.join(BACKENDS)}")
        net, robot, _ = load_model(model, device)
        network = None
        if backend == "onnxruntime":
            from holo_pose_ros.model.onnx_runtime import OnnxNetwork, cached_export

            network = OnnxNetwork(cached_export(net, model), device, threads)
        return cls(net, robot, device, network=network, backend=backend, **kwargs)

    def reset(self) -> None:
        """Forget the tracked state (e.g. when the stream jumps)."""
        self._previous = None

    @torch.inference_mode()
    def _network(self, image: np.ndarray, K: np.ndarray, box: np.ndarray, timings: dict[str, float]) -> dict:
        """One network pass on the crop `box` of `image` (batch of 1); adds to the 'crop' and 'network' timings."""
        t0 = time.perf_counter()
        K_crop = crop_affine(box, self.size) @ K
        # numpy, not torch: a torch op here would wait for cores that ONNX Runtime's threads spin on after a pass
        crop = crop_image(image, box, self.size).transpose(2, 0, 1)[None].astype(np.float32) * np.float32(1 / 255)
        x = torch.from_numpy(crop).to(self.device)
        t1 = time.perf_counter()
        out = self.network(x, torch.from_numpy(K_crop[None].astype(np.float32)).to(self.device))
        t2 = time.perf_counter()
        timings["crop"] = timings.get("crop", 0.0) + (t1 - t0) * 1e3
        timings["network"] = timings.get("network", 0.0) + (t2 - t1) * 1e3
        return out

    @torch.inference_mode()
    def _kinematics(self, out: dict, known_joints: np.ndarray | None, timings: dict[str, float]) -> dict[str, np.ndarray]:
        """FK of the crop pass (with the known joints, if given) -> numpy outputs; the 'kinematics' timing."""
        t0 = time.perf_counter()
        if known_joints is not None:
            out["joints"] = torch.as_tensor(known_joints, dtype=out["joints"].dtype, device=self.device).reshape(1, -1)
        out = {k: v.to(self.device) for k, v in out.items()}
        result = {k: v[0].detach().cpu().double().numpy() for k, v in add_kinematics(self.robot, out).items()}
        timings["kinematics"] = (time.perf_counter() - t0) * 1e3
        return result

    def localize(self, image: np.ndarray, K: np.ndarray, timings: dict[str, float] | None = None) -> tuple[float, np.ndarray]:
        """The first pass over the whole letterboxed image: (presence probability, 2D keypoints in image px that
        bound the robot: the confident fit keypoints when the network has heatmaps, else DREAM's)."""
        box = full_image_box(image.shape[1], image.shape[0])
        out = self._network(image, K, box, {} if timings is None else timings)
        uv, confidence = self._keypoints_2d(out, box)
        if confidence is not None:
            confident = confidence >= LOCALIZE_MIN_KEYPOINT_CONFIDENCE
            if confident.sum() >= 2:
                uv = uv[confident]
        return float(torch.sigmoid(out["presence_logit"][0])), uv

    def _keypoints_2d(self, out: dict, box: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Image-pixel 2D keypoints of one pass on `box`: the fit keypoints' heatmap peaks and confidences (M,),
        or DREAM's keypoints and None for a network without fit heatmaps."""
        to_image = np.linalg.inv(crop_affine(box, self.size))
        if "fit_uv" in out:
            return (_apply(to_image, out["fit_uv"][0].double().cpu().numpy()),
                    out["fit_confidence"][0].double().cpu().numpy())
        return _apply(to_image, out["uv"][0].double().cpu().numpy()), None

    def detect(self, image: np.ndarray, K: np.ndarray, timings: dict[str, float] | None = None,
               uv_hint: np.ndarray | None = None) -> Detection | None:
        """The network's 2D evidence: localize (or crop around `uv_hint`, image px), then the crop pass. None when
        the localizer finds no robot."""
        _check_inputs(image, K)
        K = np.asarray(K, dtype=np.float64)
        timings = {} if timings is None else timings
        H, W = image.shape[:2]
        if uv_hint is None:
            start = time.perf_counter()
            presence, uv_hint = self.localize(image, K, timings)
            timings["localize"] = (time.perf_counter() - start) * 1e3
            if presence < self.min_confidence:
                return None
        box = crop_box_from_keypoints(uv_hint, W, H, CROP_MARGIN)
        out = self._network(image, K, box, timings)
        uv, confidence = self._keypoints_2d(out, box)
        if confidence is None:
            confidence = out["keypoint_confidence"][0].double().cpu().numpy()
        return Detection(float(torch.sigmoid(out["presence_logit"][0])), box, uv, confidence, out,
                         crop_affine(box, self.size) @ K)

    def estimate(self, image: np.ndarray, K: np.ndarray, known_joints: np.ndarray | None = None) -> Estimate:
        """Estimate the robot in one RGB image (H, W, 3 uint8) with intrinsics K (3, 3). `known_joints` (J,), when
        the joint states are known and trusted, replaces the estimated ones (camera-to-robot calibration mode)."""
        _check_inputs(image, K)
        K = np.asarray(K, dtype=np.float64)
        H, W = image.shape[:2]
        timings, start = {}, time.perf_counter()
        names = dict(joint_names=self.robot.joint_names, keypoint_names=self.robot.keypoint_names)
        tracked = self.tracking and self._previous is not None and self._previous.found
        if tracked:
            uv = self._previous.keypoints_2d
        else:
            presence, uv = self.localize(image, K, timings)
            timings["localize"] = (time.perf_counter() - start) * 1e3
            if presence < self.min_confidence:
                self._previous = None
                return Estimate(False, presence, timings_ms={**timings, "total": timings["localize"]}, **names)
        box = crop_box_from_keypoints(uv, W, H, CROP_MARGIN)
        t0 = time.perf_counter()
        out = self._kinematics(self._network(image, K, box, timings), known_joints, timings)
        timings["estimate"] = (time.perf_counter() - t0) * 1e3
        confidence = float(1 / (1 + np.exp(-out["presence_logit"])))
        if confidence < self.min_confidence:
            self._previous = None
            if tracked:  # lost the robot: look for it in the whole image again
                return self.estimate(image, K, known_joints)
            timings["total"] = (time.perf_counter() - start) * 1e3
            return Estimate(False, confidence, timings_ms=timings, box=box, **names)
        keypoints_3d = out["keypoints_fk"]
        result = Estimate(
            True, confidence, joints=out["joints"], T_cam_base=out["T_cam_base"], keypoints_3d=keypoints_3d,
            keypoints_2d=project(keypoints_3d, K), keypoint_confidence=out["keypoint_confidence"],
            root_depth_m=float(out["depth"]), box=box, tracked=tracked, timings_ms=timings, **names)
        result.timings_ms["total"] = (time.perf_counter() - start) * 1e3
        self._previous = result
        return result


def _apply(A: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Apply a 3x3 affine map to (N, 2) points."""
    return uv @ A[:2, :2].T + A[:2, 2]


def _check_inputs(image: np.ndarray, K: np.ndarray) -> None:
    """Reject what cannot be estimated, with a message that says why."""
    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"image must be an (H, W, 3) uint8 RGB array, got {getattr(image, 'shape', type(image))} "
                         f"{getattr(image, 'dtype', '')}")
    if image.shape[0] < 8 or image.shape[1] < 8:
        raise ValueError(f"image too small: {image.shape[1]} x {image.shape[0]} px")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError("K must be a finite 3x3 intrinsics matrix with positive focal lengths")

