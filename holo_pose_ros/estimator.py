"""The inference API every caller uses (CLI, ROS nodes, evaluation, tests): load a model once, then
`estimate(image, K) -> Estimate`. No ground truth of any kind reaches it: the robot is found in the raw image by
a first pass over the whole letterboxed frame (or, when tracking, from the previous frame's keypoints), and its
box feeds a second, accurate pass. That box follows training's crop recipe (geometry/crop.py): DREAM's keypoints,
grown by CROP_MARGIN. Camera frame OpenCV; metres, radians, pixels."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import yaml

from holo_pose_ros.geometry.camera import in_image, project
from holo_pose_ros.geometry.crop import (CROP_MARGIN, MIN_CLOSE_UP_POINTS, crop_affine, crop_box_from_keypoints,
                                         crop_image, full_image_box, grid_to_frame_mask)
from holo_pose_ros.model.network import HolisticNet, Localizer
from holo_pose_ros.robots.kinematics import RobotModel

BACKENDS = ("torch", "onnxruntime")
METHODS = ("feed-forward", "lifter", "fitted")
FIT_QUALITY_SCALE = 0.16  # of the fitted robot's image extent: a fit whose RMS residual is this halves the confidence
LOCALIZE_MIN_KEYPOINT_CONFIDENCE = 0.2  # DREAM keypoints of the full-image pass that bound the crop box
CLOSE_UP_MIN_KEYPOINT_CONFIDENCE = 0.2  # fit keypoints of the crop pass that bound a close-up's box


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
    detected_2d: np.ndarray | None = None  # (M, 2) pixels: the network's fit keypoints (the fit's evidence)
    detected_confidence: np.ndarray | None = None  # (M,) their heatmap confidence, [0, 1]
    fit_rms_px: float | None = None      # weighted RMS reprojection error of the kinematic fit, pixels
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
    mask: np.ndarray | None = None       # (H, W) bool robot foreground in image pixels (a segmentation network, decoded
                                         # when the estimator's decode_mask is on: its silhouette needs it)
    image_size: tuple[int, int] | None = None  # (W, H) pixels of the image it was detected in
    close_up_boxes: dict[str, np.ndarray] = field(default_factory=dict)  # part -> (x0, y0, side) of its close-up


def localize_pass_size(net: HolisticNet, localize_size: int | None) -> int | None:
    """The input (px) of the 2D-only localize pass for `localize_size` (None: the crop's size), or None where the
    whole-image pass is the full network (0, or a network without fit heatmaps, which has no 2D-only pass)."""
    if localize_size == 0 or (localize_size is None and not net.cfg.fit_heatmaps):
        return None
    size = net.cfg.input_size if localize_size is None else int(localize_size)
    if size < 32 or size % 32:
        raise ValueError(f"localize_size must be a positive multiple of 32 px, or 0 (got {localize_size})")
    if not net.cfg.fit_heatmaps:
        raise ValueError(f"localize_size: the network '{net.cfg.name}' has no fit heatmaps, so no 2D-only localize "
                         "pass (leave localize_size unset)")
    return size


class Estimator:
    """Holistic robot pose from raw RGB images. `tracking` reuses the previous frame's fitted keypoints for the
    crop (one network pass a frame) and its pose as one more start of the fit; it re-localizes when the robot is
    lost. `fit` (default) fits the kinematic model to the detected 2D keypoints from every start (paper heads,
    `lifter` hypotheses, previous frame); `fit=False` gives the paper's feed-forward estimate; `fit=None` (auto)
    fits when the network has fit heatmaps and a lifter is loaded (`from_model`: the model card's validated
    choice, `estimator.fit`, when it has one). A keypoint weighs its heatmap confidence to the power
    `keypoint_weight_power` in the fit (sharp peaks are far more often right); a weight below
    `min_keypoint_confidence` counts as 0; the `lifter_starts` lifter hypotheses that best explain the keypoints
    start it (`tracked_lifter_starts` on a tracked frame, which starts from the previous frame's fit: by default
    none, so the lifter does not run there). With `depth_prior`, the depth of the paper heads' estimate (DepthNet)
    pulls the fitted depth (config/fitting.yaml): biased 2D detections otherwise make the fit place the robot too
    far. The estimate's confidence is the presence probability times the fit's quality
    1 / (1 + (rms / (FIT_QUALITY_SCALE * extent))^2), extent the larger side of the fitted fit keypoints' image
    bounds (the robot's apparent size, whatever the crop):
    below `min_confidence` it is 'not found', so a fit that explains nothing (no confident keypoint, rms = inf) finds
    nothing. With `silhouette` (a network that predicts a robot mask; off unless asked or its card's
    `estimator.silhouette` says so), the fit also pulls the robot's projected surface into the predicted mask and
    its outline onto the mask's (fitting/silhouette.py): measured, it costs AUC on every look
    (config/silhouette_sweep.yaml) and 25 ms a frame. Without `off_image_evidence`, fit keypoints detected outside the image (in the
    crop's padding: guessed, not seen) have no confidence: neither the lifter nor the fit uses them. With `parts`
    (off unless asked or its card's `estimator.parts` says so) the fit searches by parts (fitting/parts.py: each
    chain swept two joints at a time, then the whole tree from the best) for the basins that the starts miss; on
    tracked frames too unless `parts_tracked` is off (its card's `estimator.parts_tracked`), there on every
    `parts_tracked_every`-th frame (config/fitting.yaml): a tracked frame also starts from the previous frame's fit,
    which carries the last search's basin. With `close_ups` (off unless asked
    or its card's `estimator.close_ups` says so; a network trained with `close_up` views) each of the robot YAML's
    `close_ups` (an arm, a hand) with enough confident keypoints in the crop pass gets a pass of its own, on a box
    around them at the part's own scale, whose detections of that part's fit keypoints replace the crop pass's.
    After the fit, fit keypoints that it puts outside the image (or within the fit config's `in_view_margin_px`
    of its border) lose their confidence and the frame is fitted again from its fit and its starts: the network
    never learnt where a point it cannot see goes, so on truncated frames those detections are guesses.
    With `static_camera` (off unless asked: only the user knows that neither camera nor base moves) the robust
    average of earlier frames' fitted base poses is a prior on each frame's fit (static_camera.py).
    The whole-image pass is the network's 2D-only `localize` (presence and DREAM's keypoints from their fit heatmaps;
    no depth, joints or 3D volume: the same box and presence as the full pass, for less) at `localize_size` px (a
    multiple of 32; None: the crop's size; `localizer`: what runs it, e.g. its ONNX export); 0, or a network without
    fit heatmaps: the full network pass."""

    def __init__(self, net: HolisticNet, robot: RobotModel, device: str | torch.device = "cpu",
                 min_confidence: float = 0.5, tracking: bool = False, network: Callable | None = None,
                 backend: str = "torch", fit: bool | None = None, lifter=None, fit_config: dict | str | None = None,
                 min_keypoint_confidence: float = 0.1, lifter_starts: int = 2, tracked_lifter_starts: int = 0,
                 keypoint_weight_power: float = 2.0,
                 depth_prior: bool = True, silhouette: bool = False, off_image_evidence: bool = True,
                 parts: bool = False, parts_tracked: bool = True, localize_size: int | None = None,
                 localizer: Callable | None = None, close_ups: bool = False,
                 static_camera: bool | dict | str | Path = False, lifter_graph: Callable | None = None):
        from holo_pose_ros.fitting import Fitter

        self.device = torch.device(device)
        self.net = net.to(self.device).eval()
        self.network = network or self.net  # what runs a pass: the torch module, or an OnnxNetwork standing in
        self.backend = backend
        self.robot = robot if robot.device == self.device else RobotModel(robot.spec, device=self.device)
        self.size = net.cfg.input_size
        self.localize_size = localize_pass_size(net, localize_size)
        self.localizer = None if self.localize_size is None else localizer or Localizer(self.net)
        self.min_confidence, self.tracking = min_confidence, tracking
        self.lifter = lifter
        self.lifter_graph = lifter_graph  # the lifter's ONNX export (onnxruntime backend): the same hypotheses
        self.auto_fit = bool(net.cfg.fit_heatmaps and lifter is not None)
        self.fit = self.auto_fit if fit is None else fit
        self.min_keypoint_confidence, self.lifter_starts = min_keypoint_confidence, lifter_starts
        self.tracked_lifter_starts = tracked_lifter_starts
        self.keypoint_weight_power, self.depth_prior = keypoint_weight_power, depth_prior
        self.off_image_evidence = off_image_evidence
        self.parts, self.parts_tracked, self._parts_fitter = bool(parts), bool(parts_tracked), None
        self.silhouette = bool(silhouette)
        self.decode_mask = self.silhouette  # the mask in image pixels on each Detection (0.4 ms): the silhouette's
        self.close_ups = bool(close_ups)
        self._close_up_points = robot.close_up_fit_indices()
        self.can_close_up = bool(net.cfg.fit_heatmaps and self._close_up_points)
        if self.close_ups and not self.can_close_up:
            raise ValueError(f"close_ups: the network '{net.cfg.name}' has no fit heatmaps or the robot YAML of "
                             f"'{robot.name}' names no close_ups")
        if self.silhouette and not net.cfg.segmentation:
            raise ValueError(f"silhouette: the network '{net.cfg.name}' predicts no robot mask (segmentation: false)")
        fit_robot = RobotModel(robot.spec, dtype=torch.float64)
        meshes = None
        if self.silhouette:
            from holo_pose_ros.data.meshes import load_link_meshes

            meshes = load_link_meshes(fit_robot)
        self.fitter = Fitter(fit_robot, fit_config, meshes=meshes)
        self._previous: Estimate | None = None  # the last found estimate (its keypoints crop the next frame)
        self._plain_since_search = 0  # tracked frames fitted plainly since the last search by parts
        self.static_camera = None
        self.set_static_camera(static_camera)

    @classmethod
    def from_model(cls, model: str | Path, device: str = "cpu", backend: str = "torch", threads: int | None = None,
                   **kwargs) -> "Estimator":
        """Load a shipped model by name ('panda') or a model card / weights path. `backend` 'onnxruntime' runs the
        network's ONNX export (made once, cached) with `threads` intra-op threads. The card's `estimator` section sets
        `fit`, `silhouette`, `parts`, `parts_tracked`, `close_ups` and `localize_size` unless given. A card that names no lifter (a training run's card) fits with the robot's
        shipped lifter, as the run's validation did."""
        from holo_pose_ros.model.weights import load_model

        if backend not in BACKENDS:
            raise ValueError(f"unknown backend '{backend}'; choose one of {', '.join(BACKENDS)}")
        net, robot, card = load_model(model, device)
        for key in ("fit", "silhouette", "parts", "parts_tracked", "close_ups"):  # the card's choice unless given
            validated = (card.get("estimator") or {}).get(key)
            if kwargs.get(key) is None and validated is not None:
                kwargs[key] = bool(validated)
        if kwargs.get("localize_size") is None:
            kwargs["localize_size"] = (card.get("estimator") or {}).get("localize_size")
        card_fit = (card.get("estimator") or {}).get("fit_config")
        if card_fit:  # the fit settings its validation chose (e.g. the depth prior's weight), under any given
            given = kwargs.get("fit_config")
            if given is not None and not isinstance(given, dict):
                given = yaml.safe_load(Path(given).read_text()) or {}
            kwargs["fit_config"] = {**card_fit, **(given or {})}
        lifter_card = None  # the lifter this loads (one given in kwargs runs in torch)
        if "lifter" not in kwargs:  # the card's lifter; a run's card names none: the robot's shipped one
            from holo_pose_ros.model.cards import resolve_model
            from holo_pose_ros.model.lifter import load_lifter, shipped_lifter

            lifter_card = resolve_model(model).parent / card["lifter"] if "lifter" in card else \
                shipped_lifter(robot.name) if net.cfg.fit_heatmaps else None
            if lifter_card is not None:
                kwargs["lifter"] = load_lifter(lifter_card, device).eval()
        network = None
        if backend == "onnxruntime":
            from holo_pose_ros.model.onnx_runtime import OnnxNetwork, cached_export, cached_lifter_export

            network = OnnxNetwork(cached_export(net, model), device, threads)
            if lifter_card is not None:  # one thread: a few small matrix products
                kwargs["lifter_graph"] = OnnxNetwork(cached_lifter_export(kwargs["lifter"], lifter_card), device, 1)
            size = localize_pass_size(net, kwargs["localize_size"])
            if size is not None:
                kwargs["localizer"] = OnnxNetwork(cached_export(net, model, size), device, threads)
        return cls(net, robot, device, network=network, backend=backend, **kwargs)

    def set_static_camera(self, static_camera: bool | dict | str | Path | None) -> None:
        """Turn the static camera on (True, or a configuration: config/static_camera.yaml's keys as a dict or YAML
        path) or off (False, None); either way its running base pose starts afresh."""
        from holo_pose_ros.static_camera import StaticCamera

        self.static_camera = None if static_camera is None or static_camera is False else StaticCamera(
            None if static_camera is True else static_camera)

    def reset(self) -> None:
        """Forget the tracked state and a static camera's base pose (e.g. when the stream jumps)."""
        self._previous = None
        if self.static_camera is not None:
            self.static_camera.reset()

    @torch.inference_mode()
    def _pass(self, run: Callable, image: np.ndarray, box: np.ndarray, size: int, timings: dict[str, float],
              K: np.ndarray | None = None) -> dict:
        """One pass of `run` on the S x S crop `box` of `image` (batch of 1): the network, given the image's K (the
        crop's intrinsics go in with the crop), or the localizer; adds to the 'crop' and 'network' timings."""
        t0 = time.perf_counter()
        # numpy, not torch: a torch op here would wait for cores that ONNX Runtime's threads spin on after a pass
        crop = crop_image(image, box, size).transpose(2, 0, 1)[None].astype(np.float32) * np.float32(1 / 255)
        inputs = [torch.from_numpy(crop).to(self.device)]
        if K is not None:
            inputs.append(torch.from_numpy((crop_affine(box, size) @ K)[None].astype(np.float32)).to(self.device))
        t1 = time.perf_counter()
        out = run(*inputs)
        t2 = time.perf_counter()
        timings["crop"] = timings.get("crop", 0.0) + (t1 - t0) * 1e3
        timings["network"] = timings.get("network", 0.0) + (t2 - t1) * 1e3
        return out

    def _kinematics(self, out: dict, known_joints: np.ndarray | None, timings: dict[str, float]) -> dict[str, np.ndarray]:
        """The paper heads' estimate of the crop pass in numpy (float64): joints (the known ones, if given), the base
        pose T_cam<-base = [R | t] inv(T_base<-root(q)) through the fit's kinematic tree (model/network.py
        add_kinematics without torch: a twentieth of its 1 ms), the root depth (m) and DREAM keypoints' confidences;
        the 'kinematics' timing."""
        t0 = time.perf_counter()
        as64 = lambda key: out[key][0].detach().cpu().double().numpy()  # noqa: E731
        q = as64("joints") if known_joints is None else np.array(known_joints, dtype=np.float64).reshape(-1)
        T_cam_root = np.eye(4)
        T_cam_root[:3, :3], T_cam_root[:3, 3] = as64("R"), as64("t")
        tree = self.fitter.tree
        body, T_body_root = tree.link_frames[self.robot.spec.keypoints[self.robot.root_index].link]
        T_base_root = tree.body_poses(q[None])[0, body] @ T_body_root
        result = {"joints": q, "T_cam_base": T_cam_root @ np.linalg.inv(T_base_root), "depth": as64("depth"),
                  "keypoint_confidence": as64("keypoint_confidence")}
        timings["kinematics"] = (time.perf_counter() - t0) * 1e3
        return result

    def localize(self, image: np.ndarray, K: np.ndarray, timings: dict[str, float] | None = None) -> tuple[float, np.ndarray]:
        """The first pass over the whole letterboxed image: (presence probability, 2D keypoints in image px that
        bound the robot). These are DREAM's keypoints, the confident ones when the network has heatmaps, because
        training crops its views around them: the box of all fit keypoints is larger (they reach the robot's
        surface), which shrinks the robot in the crop and costs 2D accuracy."""
        box = full_image_box(image.shape[1], image.shape[0])
        timings = {} if timings is None else timings
        if self.localizer is not None:
            out = self._pass(self.localizer, image, box, self.localize_size, timings)
            uv = _apply(np.linalg.inv(crop_affine(box, self.localize_size)), out["uv"][0].double().cpu().numpy())
            confidence = out["confidence"][0].double().cpu().numpy()
        else:
            out = self._pass(self.network, image, box, self.size, timings, K)
            uv, confidence = self._keypoints_2d(out, box)
        uv = uv[:self.robot.n_keypoints]  # the fit keypoints list DREAM's first
        if confidence is not None:
            confident = confidence[:self.robot.n_keypoints] >= LOCALIZE_MIN_KEYPOINT_CONFIDENCE
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
            presence, uv_hint = self.localize(image, K)  # all 'localize': 'crop', 'network' are the crop pass's
            timings["localize"] = (time.perf_counter() - start) * 1e3
            if presence < self.min_confidence:
                return None
        box = crop_box_from_keypoints(uv_hint, W, H, CROP_MARGIN)
        out = self._pass(self.network, image, box, self.size, timings, K)
        uv, confidence = self._keypoints_2d(out, box)
        if confidence is None:  # no fit heatmaps: DREAM's keypoints are the only evidence, the rest weigh 0
            M = self.robot.n_fit_keypoints
            uv = np.concatenate([uv, np.zeros((M - len(uv), 2))])
            confidence = np.zeros(M)
            confidence[:self.robot.n_keypoints] = out["keypoint_confidence"][0].double().cpu().numpy()
        close_up_boxes = {}
        if self.close_ups:
            uv, confidence, close_up_boxes = self._close_up_passes(image, K, uv, confidence, timings)
        mask = None
        if self.decode_mask and "mask_logits" in out:
            t0 = time.perf_counter()
            mask = grid_to_frame_mask(out["mask_logits"][0, 0].float().cpu().numpy(), box, self.size, W, H)
            timings["mask"] = (time.perf_counter() - t0) * 1e3
        return Detection(float(torch.sigmoid(out["presence_logit"][0])), box, uv, confidence, out,
                         crop_affine(box, self.size) @ K, mask, (W, H), close_up_boxes)

    def _close_up_passes(self, image: np.ndarray, K: np.ndarray, uv: np.ndarray, confidence: np.ndarray,
                         timings: dict[str, float]) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """One pass per close-up part whose confident fit keypoints of the crop pass (image px) number at least
        MIN_CLOSE_UP_POINTS, on their box (the crop recipe): its detections of the part's points replace the crop
        pass's. Returns the new (M, 2) uv, (M,) confidences and each part's box; the 'close_ups' timing."""
        t0 = time.perf_counter()
        H, W = image.shape[:2]
        uv, confidence, boxes = uv.copy(), confidence.copy(), {}
        for name, idx in self._close_up_points.items():
            seen = idx[(confidence[idx] >= CLOSE_UP_MIN_KEYPOINT_CONFIDENCE) & in_image(uv[idx], W, H)]
            if len(seen) < MIN_CLOSE_UP_POINTS:
                continue
            boxes[name] = crop_box_from_keypoints(uv[seen], W, H, CROP_MARGIN)
            part_uv, part_confidence = self._keypoints_2d(self._pass(self.network, image, boxes[name], self.size,
                                                                     timings, K), boxes[name])
            uv[idx], confidence[idx] = part_uv[idx], part_confidence[idx]
        timings["close_ups"] = (time.perf_counter() - t0) * 1e3
        return uv, confidence, boxes

    def estimate(self, image: np.ndarray, K: np.ndarray, known_joints: np.ndarray | None = None) -> Estimate:
        """Estimate the robot in one RGB image (H, W, 3 uint8) with intrinsics K (3, 3). `known_joints` (J,), when
        the joint states are known and trusted, fixes the joints: only the camera-to-robot pose is estimated
        (calibration mode). The kinematic fit runs unless the estimator was built with `fit=False`."""
        method = self.method(calibrating=False)
        return self.estimate_methods(image, K, known_joints, (method,))[method]

    def calibrate(self, image: np.ndarray, K: np.ndarray, known_joints: np.ndarray) -> Estimate:
        """The camera-to-robot pose with the robot's trusted joints (calibration mode): fitted to the detected 2D
        keypoints when the network has fit heatmaps (the pose is then the only unknown of the geometry), else
        the feed-forward heads with those joints."""
        method = self.method(calibrating=True)
        return self.estimate_methods(image, K, np.asarray(known_joints, dtype=np.float64), (method,))[method]

    def method(self, calibrating: bool) -> str:
        """The method of `estimate` ('fitted' when fitting, else 'feed-forward') or, `calibrating`, of `calibrate`
        ('fitted' whenever the network has fit heatmaps)."""
        fitted = self.net.cfg.fit_heatmaps if calibrating else self.fit
        return "fitted" if fitted else "feed-forward"

    def estimate_methods(self, image: np.ndarray, K: np.ndarray, known_joints: np.ndarray | None = None,
                         methods: tuple[str, ...] = METHODS) -> dict[str, Estimate]:
        """One detection, several ways of turning it into an estimate (the ablation of `holo-pose evaluate`):
        'feed-forward' (the paper's heads), 'lifter' (its best hypothesis by reprojection, no fit) and 'fitted'
        (the kinematic fit from every start). The tracked state follows the last method asked for."""
        _check_methods(methods)
        start = time.perf_counter()
        detection, tracked, timings = self.detect_frame(image, K)
        return self.estimate_detection(detection, K, known_joints, methods, tracked=tracked, timings=timings,
                                       start=start)

    def detect_frame(self, image: np.ndarray, K: np.ndarray) -> tuple[Detection | None, bool, dict[str, float]]:
        """The detection of one frame in a stream, as `estimate` makes it: (detection or None, whether its crop
        came from the previous estimate, timings ms). When tracking and the last estimate found the robot, the crop
        follows its keypoints; a tracked crop that loses the robot forgets it and localizes in the whole image.
        The tracked state is read once, so a pipeline may fit frame t (estimate_detection) while it detects t+1."""
        previous = self._previous
        if self.tracking and previous is not None:
            timings: dict[str, float] = {}
            detection = self.detect(image, K, timings, uv_hint=previous.keypoints_2d)
            if detection is not None and detection.presence >= self.min_confidence:
                return detection, True, timings
            self._previous = None  # lost the robot: look for it in the whole image again
        timings = {}
        return self.detect(image, K, timings), False, timings

    def estimate_detection(self, detection: Detection | None, K: np.ndarray, known_joints: np.ndarray | None = None,
                           methods: tuple[str, ...] = METHODS, tracked: bool = False,
                           timings: dict[str, float] | None = None, start: float | None = None,
                           depth_prior_m: float | None = None, depth_prior: bool | None = None,
                           static_camera_step: bool = True) -> dict[str, Estimate]:
        """The estimates of one given detection (None: nothing detected), one per method; e.g. to compare fit
        settings on cached detections without re-running the network. `tracked` says the crop came from the
        previous frame (its pose is then one more start of the fit); `timings` and `start` (perf_counter seconds)
        carry the detection's timings into the estimates. `depth_prior_m` replaces the heads' depth in the fit's
        depth prior (metres; e.g. the true depth, in an error-budget study); `depth_prior` (None: the estimator's)
        switches that prior on or off for this call (e.g. the evaluation's fit without it). Without
        `static_camera_step` (a second look at a detection already estimated, e.g. a diagnostic) a static camera is
        neither used nor fed. The tracked state follows the last method asked for."""
        _check_methods(methods)
        K = np.asarray(K, dtype=np.float64)
        timings = {} if timings is None else timings
        start = time.perf_counter() if start is None else start
        names = dict(joint_names=self.robot.joint_names, keypoint_names=self.robot.keypoint_names)
        previous = self._previous
        if detection is None or detection.presence < self.min_confidence:
            self._previous = None
            presence = 0.0 if detection is None else detection.presence
            timings["total"] = (time.perf_counter() - start) * 1e3
            box = None if detection is None else detection.box
            return {m: Estimate(False, presence, timings_ms=dict(timings), box=box, **names) for m in methods}
        t0 = time.perf_counter()
        ff = self._kinematics(detection.out, known_joints, timings)
        poses = {"feed-forward": (ff["joints"], ff["T_cam_base"], None)}
        evidence = {}  # method -> the detection as its estimate used it, where that differs from `detection`
        if not self.off_image_evidence and detection.image_size is not None:  # guesses in the crop's padding
            seen = in_image(detection.uv, *detection.image_size)
            detection = dataclasses.replace(detection, confidence=np.where(seen, detection.confidence, 0.0))
        weights = self.fit_weights(detection.confidence)
        from_previous = tracked and previous is not None and previous.joints is not None
        lifter_starts = self.tracked_lifter_starts if from_previous else self.lifter_starts
        hypotheses = self._lifter_hypotheses(detection, K, known_joints, timings) if self.lifter is not None and (
            "lifter" in methods or ("fitted" in methods and lifter_starts > 0)) else None
        if hypotheses is not None:  # best first, by reprojection cost
            order = np.argsort(self.fitter.cost(detection.uv, weights, K, hypotheses[0], hypotheses[1]), kind="stable")
            hypotheses = hypotheses[0][order], hypotheses[1][order]
            poses["lifter"] = (hypotheses[0][0], hypotheses[1][0], None)
        if "fitted" in methods:
            q0, T0 = [ff["joints"][None]], [ff["T_cam_base"][None]]
            if hypotheses is not None:  # the best `lifter_starts`: each start costs about 0.5 ms of fit
                q0.append(hypotheses[0][:lifter_starts]); T0.append(hypotheses[1][:lifter_starts])
            if from_previous:
                q0.append(previous.joints[None]); T0.append(previous.T_cam_base[None])
            t1 = time.perf_counter()
            use_prior = self.depth_prior if depth_prior is None else depth_prior
            if depth_prior_m is None and use_prior:
                depth_prior_m = self.fitter.prior_depth(ff["joints"], ff["T_cam_base"])
            silhouette = None
            if self.silhouette and detection.mask is not None and detection.mask.any():
                silhouette = self.fitter.silhouette(detection.mask)
            q0, T0 = np.concatenate(q0), np.concatenate(T0)
            search = self.search(from_previous, self._plain_since_search)
            self._plain_since_search = self._plain_since_search + 1 if from_previous and search is self.fitter else 0
            fitted = search.fit(detection.uv, weights, K, q0, T0, known_joints, depth_prior_m if use_prior else None,
                                silhouette=silhouette)
            timings["fit"] = (time.perf_counter() - t1) * 1e3
            if detection.image_size is not None and self.fitter.config["in_view_margin_px"] >= 0:
                fitted, evidence["fitted"] = self._in_view_refit(detection, K, weights, fitted, q0, T0, known_joints,
                                                                 depth_prior_m if use_prior else None, silhouette,
                                                                 timings)
            poses["fitted"] = (fitted.q, fitted.T_cam_base, fitted)
            if self.static_camera is not None and known_joints is None and static_camera_step:
                poses["fitted"] = self._static_camera_fit(evidence.get("fitted", detection), K, fitted, ff, tracked,
                                                          timings, names, depth_prior_m if use_prior else None,
                                                          silhouette)
        timings["estimate"] = (time.perf_counter() - t0) * 1e3
        results = {}
        for method in methods:
            if method not in poses:  # no lifter shipped with this model
                results[method] = Estimate(False, 0.0, timings_ms=dict(timings), box=detection.box, **names)
                continue
            results[method] = self._estimate_from_pose(evidence.get(method, detection), K, *poses[method], ff, tracked,
                                                       timings, names)
        for r in results.values():
            r.timings_ms["total"] = (time.perf_counter() - start) * 1e3
        last = results[methods[-1]]
        self._previous = last if last.found else None
        return results

    def _in_view_refit(self, detection: Detection, K: np.ndarray, weights: np.ndarray, fitted, q0: np.ndarray,
                       T0: np.ndarray, known_joints, depth_prior_m: float | None, silhouette, timings: dict) -> tuple:
        """Fit keypoints that the fit puts outside the image, or within the fit config's `in_view_margin_px` of its
        border, are guesses, not evidence: the network never learnt where a point it cannot see goes (trained only
        on points in view, on truncated frames it puts them ~200 px off, many inside the image). They lose their
        confidence (and their fit `weights`) and the frame is fitted again, plainly, from its fit and from its
        starts q0 (S, J), T0 (S, 4, 4). Returns (fit, the detection as that fit used it); the 'in_view' timing."""
        if not np.isfinite(fitted.cost):
            return fitted, detection
        t0 = time.perf_counter()
        uv = self.fitter.project(fitted.q, fitted.T_cam_base, K)
        out = ~in_image(uv, *detection.image_size, margin_px=float(self.fitter.config["in_view_margin_px"]))
        if not (out & (weights > 0)).any():
            return fitted, detection
        in_view = dataclasses.replace(detection, confidence=np.where(out, 0.0, detection.confidence))
        refit = self.fitter.fit(in_view.uv, np.where(out, 0.0, weights), K,
                                np.concatenate([fitted.q[None], q0]), np.concatenate([fitted.T_cam_base[None], T0]),
                                known_joints, depth_prior_m, silhouette=silhouette)
        timings["in_view"] = (time.perf_counter() - t0) * 1e3
        return (refit, in_view) if np.isfinite(refit.cost) else (fitted, detection)

    def _static_camera_fit(self, detection: Detection, K: np.ndarray, fitted, ff: dict, tracked: bool, timings: dict,
                           names: dict, depth_prior_m: float | None, silhouette) -> tuple:
        """With a static camera: where the frame's own fit agrees with the running average of earlier frames' fits,
        it is fitted again (plainly, from its own pose and from the camera's) with that average as a prior on the
        base pose; a frame that disagrees (a wrong basin, or the camera moved) keeps its own fit. The frame's own
        fit joins the average if it is found. Returns (q, T_cam_base, fit); the 'static_camera' timing."""
        t0 = time.perf_counter()
        camera = self.static_camera
        prior = camera.prior() if camera.agrees(fitted.T_cam_base) else None
        if self._estimate_from_pose(detection, K, fitted.q, fitted.T_cam_base, fitted, ff, tracked, timings,
                                    names).found:
            camera.observe(fitted.T_cam_base)
        result = (fitted.q, fitted.T_cam_base, fitted)
        if prior is not None:
            refit = self.fitter.fit(detection.uv, self.fit_weights(detection.confidence), K,
                                    np.stack([fitted.q, fitted.q]), np.stack([fitted.T_cam_base, prior.T_cam_base]),
                                    None, depth_prior_m, silhouette=silhouette, base_prior=prior)
            result = (refit.q, refit.T_cam_base, refit)
        timings["static_camera"] = (time.perf_counter() - t0) * 1e3
        return result

    def search(self, from_previous: bool = False, plain_since_search: int | None = None):
        """What fits: the Fitter, or with `parts` a PartsFitter around it (rebuilt when the Fitter is replaced). A
        tracked frame (`from_previous`: it starts from the previous frame's fit) gets the Fitter unless
        `parts_tracked`, and then also unless the frames fitted plainly since the last search
        (`plain_since_search`; None: a search is due) reach the fit config's `parts_tracked_every` minus one."""
        due = plain_since_search is None or plain_since_search + 1 >= int(self.fitter.config["parts_tracked_every"])
        if not self.parts or (from_previous and not (self.parts_tracked and due)):
            return self.fitter
        if self._parts_fitter is None or self._parts_fitter.fitter is not self.fitter:
            from holo_pose_ros.fitting.parts import PartsFitter

            self._parts_fitter = PartsFitter(self.fitter)
        return self._parts_fitter

    def _lifter_hypotheses(self, detection: Detection, K: np.ndarray, known_joints: np.ndarray | None,
                           timings: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """The lifter's hypotheses (q (H, J), T_cam_base (H, 4, 4)) from the detected 2D keypoints; the 'lifter'
        timing. Known joints replace the hypotheses' joints."""
        t0 = time.perf_counter()
        f32 = lambda a: torch.from_numpy(np.array(a, dtype=np.float32)[None])  # noqa: E731 (a copy: inputs may be read-only)
        inputs = (f32(detection.uv), f32(detection.confidence), f32(detection.box), f32(K))
        if self.lifter_graph is not None:   # the ONNX export: 0.3 ms where torch's small ops take 1.2-2.3
            out = self.lifter_graph(*inputs)
            q, T = out["joints"], out["T_cam_base"]
        else:
            with torch.inference_mode():
                q, T = self.lifter.hypotheses(*inputs)
        q, T = q[0].double().cpu().numpy(), T[0].double().cpu().numpy()
        if known_joints is not None:
            q = np.repeat(np.asarray(known_joints, dtype=np.float64)[None], len(q), 0)
        timings["lifter"] = (time.perf_counter() - t0) * 1e3
        return q, T

    def _estimate_from_pose(self, detection: Detection, K: np.ndarray, q: np.ndarray, T_cam_base: np.ndarray, fit,
                            ff: dict, tracked: bool, timings: dict, names: dict) -> Estimate:
        """An Estimate from joints and base pose. Its confidence is the presence probability times the fit's
        quality (1 without a fit); below `min_confidence` the robot is 'not found'."""
        # one FK call of the fit's numpy kinematic tree (a tenth of a torch call's 0.4 ms); the fit keypoints list
        # DREAM's first
        T = np.asarray(T_cam_base, dtype=np.float64)
        fit_points = self.fitter.tree.points(np.asarray(q, dtype=np.float64)[None])[0] @ T[:3, :3].T + T[:3, 3]
        quality = 1.0 if fit is None else 1.0 / (1.0 + (fit.rms_px / (FIT_QUALITY_SCALE * _image_extent_px(
            fit_points, K))) ** 2)
        confidence = detection.presence * quality
        if confidence < self.min_confidence:
            return Estimate(False, confidence, timings_ms=dict(timings), box=detection.box, fit_rms_px=fit.rms_px,
                            detected_2d=detection.uv, detected_confidence=detection.confidence, **names)
        keypoints_3d = fit_points[:self.robot.n_keypoints]
        root = keypoints_3d[self.robot.root_index, 2] if fit is not None else float(ff["depth"])
        return Estimate(
            True, confidence, joints=np.asarray(q, dtype=np.float64), T_cam_base=np.asarray(T_cam_base, dtype=np.float64),
            keypoints_3d=keypoints_3d, keypoints_2d=project(keypoints_3d, K), keypoint_confidence=ff["keypoint_confidence"],
            root_depth_m=float(root), box=detection.box, tracked=tracked, timings_ms=dict(timings),
            detected_2d=detection.uv, detected_confidence=detection.confidence,
            fit_rms_px=None if fit is None else fit.rms_px, **names)

    def fit_weights(self, confidence: np.ndarray) -> np.ndarray:
        """(M,) fit weights of heatmap confidences (M,): confidence ** keypoint_weight_power, 0 below
        min_keypoint_confidence."""
        weights = np.asarray(confidence, np.float64) ** self.keypoint_weight_power
        return np.where(weights >= self.min_keypoint_confidence, weights, 0.0)


def _image_extent_px(points_cam: np.ndarray, K: np.ndarray) -> float:
    """A robot's apparent size, pixels: the larger side of the image bounds of its points (M, 3, camera frame,
    metres) in front of the camera; 1 px at least."""
    uv = project(points_cam[points_cam[:, 2] > 1e-3], K)
    return max(float(np.ptp(uv, axis=0).max()), 1.0) if len(uv) else 1.0


def _apply(A: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Apply a 3x3 affine map to (N, 2) points."""
    return uv @ A[:2, :2].T + A[:2, 2]


def _check_methods(methods: tuple[str, ...]) -> None:
    """ValueError naming any estimation method not in METHODS."""
    unknown = set(methods) - set(METHODS)
    if unknown:
        raise ValueError(f"unknown estimation methods {sorted(unknown)}; choose from {', '.join(METHODS)}")


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

