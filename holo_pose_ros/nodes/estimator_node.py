"""ROS 2 node `holo_pose_estimator`: sensor_msgs/Image + CameraInfo in; the robot's joint states, its base pose in the
camera frame, keypoints, RViz markers, an annotated image and /diagnostics out. Thin: msg_adapters convert the
messages and the Estimator does the work, on worker threads that always take the newest frame: with `pipeline`
(the default) one thread runs the network of frame t+1 while another fits and publishes frame t.

Run: `ros2 run holo_pose_ros estimator_node --ros-args -p robot:=panda -p model:=panda -r image:=/camera/image_raw
-r camera_info:=/camera/camera_info` (or the console script `holo-pose-estimator --ros-args ...`)."""

from __future__ import annotations

import re
import sys
import threading
import time
from collections import Counter, OrderedDict
from dataclasses import dataclass, field

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped, TransformStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, JointState, PointCloud2
from visualization_msgs.msg import MarkerArray

from holo_pose_ros.calibration import RunningCalibration
from holo_pose_ros.monitoring.stamps import NS, StampBuffer
from holo_pose_ros.nodes.parameters import ParameterSpecs, declare_parameters
from holo_pose_ros.nodes.runner import run_node
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.model.cards import read_card
from holo_pose_ros.visualization import draw_skeleton
from msg_adapters import (CameraInfoError, ImageConversionError, camera_info_to_K, check_image_size, image_to_rgb,
                          rgb_to_image, to_joint_state, to_keypoints_2d, to_keypoints_3d, to_markers, to_pose_stamped,
                          stamp_ns, to_pose_with_covariance, to_transform_stamped)
from msg_adapters.joint_states import joint_positions_by_name

try:
    from tf2_msgs.msg import TFMessage
except ImportError:  # not on PyPI: /tf needs a ROS distribution; ~/transform carries the same data
    TFMessage = None

NODE_NAME = "holo_pose_estimator"
LOG_PERIOD_S = 5.0  # a problem whose reason repeats is logged at most once per period (LogThrottle)
SENSOR_QOS = QoSProfile(reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_LAST, depth=1,
                        durability=DurabilityPolicy.VOLATILE)
# name -> (description, read_only, ranges); defaults live in config/estimator.yaml only
_PROBABILITY = dict(floating_point_range=[FloatingPointRange(from_value=0.0, to_value=1.0)])
_PIXELS = dict(integer_range=[IntegerRange(from_value=1, to_value=2**31 - 1)])
PARAMETERS: ParameterSpecs = {
    "robot": ("Robot YAML name (config/robots/<robot>.yaml); must be the model's robot.", True, {}),
    "model": ("Shipped model name (e.g. 'panda') or path of a model card (.yaml) or weights (.safetensors).", True, {}),
    "device": ("auto | cpu | cuda | cuda:N. CUDA asked for but unavailable: CPU, with a warning.", True, {}),
    "backend": ("torch | onnxruntime: what runs the network (onnxruntime: exported once, cached).", True, {}),
    "threads": ("CPU threads of the network (0: the backend's default).", True,
                dict(integer_range=[IntegerRange(from_value=0, to_value=256)])),
    "image_topic": ("Input sensor_msgs/Image topic (rgb8, bgr8, rgba8, bgra8 or mono8); relative, remappable.", True, {}),
    "camera_info_topic": ("Input sensor_msgs/CameraInfo topic; the latest valid one is used.", True, {}),
    "use_rectified_p": ("Take K from CameraInfo.p (rectified images) instead of CameraInfo.k.", True, {}),
    "base_frame_id": ("Child frame of ~/transform and /tf (parent: the image's frame_id). Empty: "
                      "<robot>_base_link.", True, {}),
    "pipeline": ("Two stages on two threads: the network of the next frame runs while the fit of this one does "
                 "(outputs in order, each with its own image's header). false: one thread does both.", True, {}),
    "tracking": ("Crop from the previous frame's keypoints: one network pass a frame instead of two.", False, {}),
    "min_confidence": ("Estimate confidence [0, 1] (presence x fit quality) below which nothing is published.", False,
                       _PROBABILITY),
    "fit": ("auto | true | false: fit the kinematic model to the detected 2D keypoints (false: the paper's "
            "feed-forward estimate; auto: the model card's validated choice).", False, {}),
    "parts": ("auto | true | false: search the fit by parts, each chain swept two joints at a time (about 5 ms a "
              "frame more; auto: the model card's validated choice); when tracking, tracked frames search too only "
              "where the card chose it (estimator.parts_tracked).", False, {}),
    "close_ups": ("auto | true | false: a second network pass on a close-up of each of the robot YAML's close_ups "
                  "(an arm, a hand), whose detections of that part replace the crop's (one pass per part more; auto: "
                  "the model card's validated choice).", False, {}),
    "static_camera": ("The camera and the robot's base do not move: the robust average of earlier frames' base poses "
                      "becomes a prior on each frame's fit (config/static_camera.yaml; it restarts when the camera "
                      "is moved). Turning it on or off forgets that pose.", False, {}),
    "localize_size": ("Input size (px, a multiple of 32) of the whole-image pass, run 2D-only (presence and DREAM's "
                      "keypoints); 0: the full network pass; -1: the model card's choice, else the crop's size.", True,
                      dict(integer_range=[IntegerRange(from_value=-1, to_value=1024)])),
    "publish_annotated": ("Publish ~/annotated (skeleton drawn over the image) while someone subscribes.", False, {}),
    "publish_tf": ("Also broadcast the transform on /tf (needs tf2_msgs, i.e. a ROS distribution).", False, {}),
    "max_image_pixels": ("Images with more pixels (width x height) are rejected.", True, _PIXELS),
    "joint_states_topic": ("Calibration mode: the robot's trusted sensor_msgs/JointState (matched by joint name); "
                           "only the camera-to-robot pose is then estimated. Empty: off.", True, {}),
    "joint_states_tolerance_s": ("Calibration mode: the joint state nearest the image stamp must be this close, "
                                 "else the frame is skipped (counted).", True,
                                 dict(floating_point_range=[FloatingPointRange(from_value=0.0, to_value=10.0)])),
    "calibration_window": ("Calibration mode: frames in the running robust average published on ~/calibration.",
                           True, dict(integer_range=[IntegerRange(from_value=1, to_value=100000)])),
    "calibration_max_translation_m": ("Calibration mode: frames farther than this from the window's median are "
                                      "outliers.", True, dict(floating_point_range=[FloatingPointRange(
                                          from_value=0.0, to_value=10.0)])),
    "calibration_max_rotation_deg": ("Calibration mode: frames turned more than this from the window's medoid "
                                     "are outliers.", True, dict(floating_point_range=[FloatingPointRange(
                                         from_value=0.0, to_value=180.0)])),
}
JOINT_STATES_HISTORY_S = 5.0  # calibration mode: joint states kept this long behind the newest

FIT_MODES = {"auto": None, "true": True, "false": False}


def _fit_mode(value: str, name: str = "fit") -> bool | None:
    """The `fit` (or `parts`, `close_ups`) parameter as the estimator's argument (None: auto)."""
    mode = str(value).strip().lower()
    if mode not in FIT_MODES:
        raise ValueError(f"{name} must be one of {', '.join(FIT_MODES)}, got {value!r}")
    return FIT_MODES[mode]


def resolve_device(device: str) -> tuple[str, str | None]:
    """(torch device, warning or None) for 'auto', 'cpu', 'cuda' or 'cuda:N'; CPU when CUDA is unavailable."""
    import torch

    name = device.strip().lower()
    if name == "auto":
        return ("cuda" if torch.cuda.is_available() else "cpu"), None
    if name == "cpu":
        return "cpu", None
    if not re.fullmatch(r"cuda(:\d+)?", name):
        raise ValueError(f"device must be auto, cpu, cuda or cuda:N, got '{device}'")
    if not torch.cuda.is_available():
        return "cpu", f"device '{device}' asked for, but CUDA is not available: running on the CPU"
    index = int(name.partition(":")[2] or 0)
    if index >= torch.cuda.device_count():
        raise ValueError(f"device '{device}': only {torch.cuda.device_count()} CUDA device(s) visible")
    return name, None


def reason_template(text: str) -> str:
    """A problem's reason without its particulars: numbers, quoted values and bracketed lists blanked, so that
    "data is 1000 bytes" and "data is 2000 bytes" are one reason, "unsupported image encoding 'a'" and '...'b''
    another."""
    text = re.sub(r"\[[^\]]*\]", "[...]", re.sub(r"'[^']*'", "'...'", text))
    return re.sub(r"(?<![\w.])[-+]?(\d+(\.\d*)?(e[-+]?\d+)?|nan|inf)(?!\w)", "N", text, flags=re.IGNORECASE)


class LogThrottle:
    """When to log a recurring problem: each reason (reason_template of its detail) under a key at once the first
    time, then at most once per `period_s`, with the count of lines held back meanwhile. Remembers the
    `max_reasons` most recent reasons of each key. Thread-safe."""

    def __init__(self, period_s: float = LOG_PERIOD_S, max_reasons: int = 32):
        self.period_s, self.max_reasons = period_s, max_reasons
        self._reasons: dict[str, OrderedDict[str, list]] = {}  # key -> reason -> [time of last line, held back]
        self._lock = threading.Lock()

    def check(self, key: str, detail: str, now: float) -> int | None:
        """None: do not log now; else log, and the int is how many lines of this reason were held back."""
        reason = reason_template(detail)
        with self._lock:
            reasons = self._reasons.setdefault(key, OrderedDict())
            entry = reasons.get(reason)
            if entry is not None and now - entry[0] < self.period_s:
                entry[1] += 1
                return None
            held_back = entry[1] if entry is not None else 0
            reasons[reason] = [now, 0]
            reasons.move_to_end(reason)
            while len(reasons) > self.max_reasons:
                reasons.popitem(last=False)
            return held_back


class LatestFrame:
    """A one-slot buffer between the subscription and the worker: a new frame replaces an unprocessed one."""

    def __init__(self):
        self._cond = threading.Condition()
        self._item = None
        self._closed = False

    def put(self, item) -> bool:
        """Store `item`; True when it replaced (dropped) a frame the worker had not taken yet."""
        with self._cond:
            dropped = self._item is not None
            self._item = item
            self._cond.notify()
            return dropped

    def take(self):
        """The newest frame, waiting for one; None once closed."""
        with self._cond:
            while self._item is None and not self._closed:
                self._cond.wait()
            item, self._item = self._item, None
            return None if self._closed else item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


@dataclass
class Stats:
    """Counters since start, and the last processed frame's numbers (ms, probability)."""

    received: int = 0
    processed: int = 0
    dropped: int = 0
    not_found: int = 0
    no_camera_info: int = 0
    camera_info_received: int = 0
    camera_info_rejected: int = 0  # CameraInfo messages with unusable intrinsics (also in errors['camera_info'])
    no_joint_state: int = 0       # calibration mode: no joint state within the tolerance of the image stamp
    joint_state_incomplete: int = 0  # calibration mode: the nearest joint state lacks joints (or has NaN ones)
    calibration_frames: int = 0   # calibration mode: frames in the running calibration so far
    errors: Counter = field(default_factory=Counter)  # 'image', 'camera_info', 'estimator', 'internal'
    found: bool | None = None  # the last processed frame's
    confidence: float = float("nan")
    inference_ms: float = float("nan")
    latency_ms: float = float("nan")  # message received -> results published


@dataclass
class _Job:
    """One frame between the network stage and the fit stage."""

    msg: Image
    received: float              # time.monotonic() of its arrival
    image: np.ndarray            # (H, W, 3) uint8 RGB
    K: np.ndarray                # (3, 3) intrinsics
    known: np.ndarray | None     # calibration mode: the robot's joints for this image
    detection: object            # Detection | None
    tracked: bool                # its crop came from the previous estimate
    timings: dict                # ms so far
    start: float                 # time.perf_counter() when its estimation began


class EstimatorNode(Node):
    """Estimates the robot in the newest image with the latest valid CameraInfo; see the module docstring."""

    def __init__(self, **node_kwargs):
        super().__init__(NODE_NAME, **node_kwargs)
        p = declare_parameters(self, "estimator.yaml", PARAMETERS)
        device, warning = resolve_device(p["device"])
        if warning:
            self.get_logger().warning(warning)
        backend = p["backend"]
        if backend == "onnxruntime" and device.startswith("cuda"):
            from holo_pose_ros.model.onnx_runtime import has_cuda_provider

            if not has_cuda_provider():
                self.get_logger().warning("this onnxruntime has no CUDA provider: the network runs in torch on "
                                          f"{device} (install onnxruntime-gpu for ONNX Runtime on the GPU)")
                backend = "torch"
        if backend == "onnxruntime":
            from holo_pose_ros.model.onnx_runtime import cache_dir

            self.get_logger().info(f"preparing the ONNX Runtime graph: exported once per weights file (about 20 s), "
                                   f"then reused from {cache_dir()}")
        self.estimator = Estimator.from_model(p["model"], device, backend=backend, threads=p["threads"] or None,
                                              tracking=p["tracking"], min_confidence=p["min_confidence"],
                                              fit=_fit_mode(p["fit"]), parts=_fit_mode(p["parts"], "parts"),
                                              close_ups=_fit_mode(p["close_ups"], "close_ups"),
                                              static_camera=p["static_camera"],
                                              localize_size=None if p["localize_size"] < 0 else p["localize_size"])
        robot = self.estimator.robot
        if robot.name != p["robot"]:
            raise ValueError(f"model '{p['model']}' estimates robot '{robot.name}', but robot:={p['robot']}")
        self.parents = robot.keypoint_parents
        self.base_frame_id = p["base_frame_id"] or f"{robot.name}_base_link"
        self.use_rectified_p, self.max_pixels = p["use_rectified_p"], p["max_image_pixels"]
        self.publish_annotated, self.publish_tf = p["publish_annotated"], p["publish_tf"]
        self.device, self.model = device, p["model"]
        for name, value, outputs in [("joint_names", robot.joint_names, "~/joint_states"),
                                     ("keypoint_names", robot.keypoint_names, "~/keypoints and ~/keypoints_2d")]:
            descriptor = ParameterDescriptor(description=f"Order of {outputs} (from the robot YAML).", read_only=True)
            self.declare_parameter(name, value, descriptor, ignore_override=True)
        validated = read_card(p["model"])[1].get("estimator") or {}   # what `auto` goes back to
        self._validated_fit = self.estimator.fit if _fit_mode(p["fit"]) is None else bool(
            validated.get("fit", self.estimator.auto_fit))
        self._validated_parts = bool(validated.get("parts", False))
        self._validated_close_ups = bool(validated.get("close_ups", False))
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self.stats = Stats()
        self._lock = threading.Lock()
        self._throttle = LogThrottle()
        self._camera: tuple[CameraInfo, np.ndarray] | None = None  # (message, K) of the latest valid CameraInfo
        self._period_start, self._period_processed, self._period_errors = time.monotonic(), 0, 0

        self._pubs = {
            "joint_states": self.create_publisher(JointState, "~/joint_states", 10),
            "pose": self.create_publisher(PoseStamped, "~/pose", 10),
            "transform": self.create_publisher(TransformStamped, "~/transform", 10),
            "keypoints": self.create_publisher(PoseArray, "~/keypoints", 10),
            "keypoints_2d": self.create_publisher(PointCloud2, "~/keypoints_2d", 10),
            "markers": self.create_publisher(MarkerArray, "~/markers", 10),
            "annotated": self.create_publisher(Image, "~/annotated", 10),
        }
        # /tf as tf2_ros.TransformBroadcaster does it: a TFMessage publisher, depth 100
        self._tf = self.create_publisher(TFMessage, "/tf", 100) if TFMessage is not None else None
        if self._tf is None and self.publish_tf:
            self.get_logger().info("tf2_msgs is not installed: no /tf; the transform is on ~/transform")
        self._diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._joint_states: StampBuffer | None = None  # calibration mode: the robot's trusted joint states
        if p["joint_states_topic"]:
            self._joint_states = StampBuffer(JOINT_STATES_HISTORY_S)
            self._tolerance_ns = int(p["joint_states_tolerance_s"] * NS)
            self._calibration = RunningCalibration(p["calibration_window"], p["calibration_max_translation_m"],
                                                   p["calibration_max_rotation_deg"])
            self._pubs["calibration"] = self.create_publisher(PoseWithCovarianceStamped, "~/calibration", 10)
            self._joints_sub = self.create_subscription(JointState, p["joint_states_topic"], self._on_joint_state,
                                                        QoSProfile(reliability=ReliabilityPolicy.BEST_EFFORT,
                                                                   history=HistoryPolicy.KEEP_LAST, depth=100))
        self._image_sub = self.create_subscription(Image, p["image_topic"], self._on_image, SENSOR_QOS)
        self._info_sub = self.create_subscription(CameraInfo, p["camera_info_topic"], self._on_camera_info, SENSOR_QOS)
        self.create_timer(1.0, self._publish_diagnostics)

        self._frames = LatestFrame()  # subscription -> network stage
        self._detections = LatestFrame() if p["pipeline"] else None  # network stage -> fit stage
        self._workers = [threading.Thread(target=self._work, name="holo_pose_estimator_network", daemon=True)]
        if self._detections is not None:
            if backend == "onnxruntime":  # the fit stage's torch ops (lifter, FK) are tiny: one thread, not the network's
                import torch

                torch.set_num_threads(1)
            self._workers.append(threading.Thread(target=self._fit_work, name="holo_pose_estimator_fit", daemon=True))
        for worker in self._workers:
            worker.start()
        self.get_logger().info(
            f"robot '{robot.name}', model '{self.model}' on {device} ({self.estimator.backend}); listening on {self._image_sub.topic_name} and "
            f"{self._info_sub.topic_name} (best effort, depth 1); publishing under {self.get_fully_qualified_name()}/")

    # -- parameters and logging ------------------------------------------------------------------------------
    def _check_parameters(self, parameters: list) -> SetParametersResult:
        """Refuse values the descriptors cannot express (the `fit`, `parts` and `close_ups` modes), and close-ups
        for a robot or network that has none."""
        for param in parameters:
            if param.name in ("fit", "parts", "close_ups"):
                try:
                    mode = _fit_mode(param.value, param.name)
                except ValueError as e:
                    return SetParametersResult(successful=False, reason=str(e))
                if param.name == "close_ups" and mode and not self.estimator.can_close_up:
                    return SetParametersResult(successful=False, reason=f"close_ups: robot '{self.estimator.robot.name}'"
                                               " names no close_ups or its network has no fit heatmaps")
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list) -> None:
        """Apply the live parameters (the others are read-only; ranges are checked by their descriptors)."""
        for param in parameters:
            if param.name == "min_confidence":
                self.estimator.min_confidence = param.value
            elif param.name == "tracking":
                self.estimator.tracking = param.value
                self.estimator.reset()
            elif param.name == "fit":
                mode = _fit_mode(param.value)
                self.estimator.fit = self._validated_fit if mode is None else mode
            elif param.name == "parts":
                mode = _fit_mode(param.value, "parts")
                self.estimator.parts = self._validated_parts if mode is None else mode
            elif param.name == "close_ups":
                mode = _fit_mode(param.value, "close_ups")
                self.estimator.close_ups = self._validated_close_ups if mode is None else mode
            elif param.name == "static_camera":
                self.estimator.set_static_camera(param.value)
            elif param.name in ("publish_annotated", "publish_tf"):
                setattr(self, param.name, param.value)

    def _log_throttled(self, key: str, text: str, level: str = "warning", detail: str = "") -> None:
        """Log `text` at `level` (info | warning): a new reason (`detail` without its numbers) of `key` at once,
        a repeated one at most every LOG_PERIOD_S (LogThrottle)."""
        if level not in ("info", "warning"):
            raise ValueError(f"unknown log level {level!r}")
        held_back = self._throttle.check(key, detail, time.monotonic())
        if held_back is None:
            return
        if held_back:
            text += f" ({held_back} more like it not logged in the last {LOG_PERIOD_S:.0f} s)"
        # one call site per severity: rclpy refuses a call site whose severity changes between calls
        if level == "info":
            self.get_logger().info(text)
        else:
            self.get_logger().warning(text)

    def _error(self, kind: str, error: Exception) -> None:
        """Count an error of `kind` and log it (a new reason at once, a repeated one throttled); skip the input."""
        with self._lock:
            self.stats.errors[kind] += 1
            count = self.stats.errors[kind]
        reason = f"{type(error).__name__}: {error}"
        self._log_throttled(kind, f"{kind} error #{count}, skipped: {reason}", detail=reason)

    # -- callbacks (executor thread) -------------------------------------------------------------------------
    def _on_image(self, msg: Image) -> None:
        dropped = self._frames.put((msg, time.monotonic()))
        with self._lock:
            self.stats.received += 1
            self.stats.dropped += int(dropped)

    def _on_joint_state(self, msg: JointState) -> None:
        """Calibration mode: keep the robot's joints (the robot YAML's, picked by name) by stamp."""
        try:
            selection, stamp = joint_positions_by_name(msg, self.estimator.robot.joint_names)
        except ValueError as e:
            return self._error("joint_state", e)
        with self._lock:
            self._joint_states.add(stamp, selection)

    def _known_joints(self, msg: Image):
        """Calibration mode: the trusted joints (J,) for this image, or None (counted and logged) to skip it."""
        stamp = stamp_ns(msg.header.stamp)
        with self._lock:
            nearest = self._joint_states.nearest(stamp, self._tolerance_ns)
        if nearest is None:
            with self._lock:
                self.stats.no_joint_state += 1
            self._log_throttled("no_joint_state", f"no joint state on {self._joints_sub.topic_name} within "
                                                  f"{self._tolerance_ns / 1e6:g} ms of the image stamp: frame skipped")
            return None
        selection = nearest[1]
        if selection.missing or selection.nonfinite:
            with self._lock:
                self.stats.joint_state_incomplete += 1
            lacking = ", ".join(selection.missing + selection.nonfinite)
            self._log_throttled("joint_state_incomplete", f"the joint state lacks {lacking}: frame skipped",
                                detail=lacking)
            return None
        return selection.values

    def _on_camera_info(self, msg: CameraInfo) -> None:
        with self._lock:
            self.stats.camera_info_received += 1
        try:
            self._camera = (msg, camera_info_to_K(msg, self.use_rectified_p))
        except CameraInfoError as e:
            self._camera = None  # never estimate with intrinsics that are known to be wrong
            with self._lock:
                self.stats.camera_info_rejected += 1
            self._error("camera_info", e)

    # -- inference (worker threads) --------------------------------------------------------------------------
    def _work(self) -> None:
        """The network stage: detect the newest frame, then fit it here or hand it to the fit stage."""
        while (frame := self._frames.take()) is not None:
            try:
                job = self._detect(*frame)
                if job is None:
                    continue
                if self._detections is None:
                    self._finish(job)
                elif self._detections.put(job):  # the fit stage had not taken the previous one: it is stale
                    with self._lock:
                        self.stats.dropped += 1
            except Exception as e:  # the worker must outlive any single frame
                self._error("internal", e)

    def _fit_work(self) -> None:
        """The fit stage of the pipeline: fit and publish detections in the order they were made."""
        while (job := self._detections.take()) is not None:
            try:
                self._finish(job)
            except Exception as e:
                self._error("internal", e)

    def _detect(self, msg: Image, received: float) -> _Job | None:
        """Convert one frame and run the network on it, or count why not (None)."""
        camera = self._camera
        if camera is None:
            with self._lock:
                self.stats.no_camera_info += 1
            self._log_throttled("no_camera_info", f"no valid CameraInfo on {self._info_sub.topic_name} yet: "
                                                  "skipping images until one arrives")
            return None
        info, K = camera
        try:
            image = image_to_rgb(msg, self.max_pixels)
        except ImageConversionError as e:
            return self._error("image", e)
        try:
            check_image_size(info, image.shape[1], image.shape[0])
        except CameraInfoError as e:
            return self._error("camera_info", e)
        known = None
        if self._joint_states is not None and (known := self._known_joints(msg)) is None:
            return None
        start = time.perf_counter()
        try:
            detection, tracked, timings = self.estimator.detect_frame(image, K)
        except Exception as e:  # a model failure skips the frame, never the node
            return self._error("estimator", e)
        return _Job(msg, received, image, K, known, detection, tracked, timings, start)

    def _finish(self, job: _Job) -> None:
        """Estimate from one frame's detection (the fit) and publish it, or count why not."""
        method = self.estimator.method(calibrating=job.known is not None)
        try:  # calibration (known joints): only the pose is estimated, with the robot's own joints
            estimate = self.estimator.estimate_detection(job.detection, job.K, job.known, (method,), job.tracked,
                                                         job.timings, job.start)[method]
        except Exception as e:  # a model failure skips the frame, never the node
            return self._error("estimator", e)
        msg = job.msg
        with self._lock:
            self.stats.processed += 1
            self.stats.found, self.stats.confidence = estimate.found, estimate.confidence
            self.stats.inference_ms = estimate.timings_ms.get("total", float("nan"))
            self.stats.not_found += int(not estimate.found)
        if not estimate.found:
            self._log_throttled("not_found", f"robot not found (confidence {estimate.confidence:.2f} < "
                                             f"{self.estimator.min_confidence:.2f})", "info")
            return
        self._publish(msg, job.image, estimate)
        if job.known is not None:
            self._calibration.add(estimate.T_cam_base)
            calibration = self._calibration.estimate()
            with self._lock:
                self.stats.calibration_frames = calibration.n_used
            self._pubs["calibration"].publish(to_pose_with_covariance(calibration.T_cam_base, calibration.covariance,
                                                                      msg.header))
        with self._lock:
            self.stats.latency_ms = (time.monotonic() - job.received) * 1e3

    def _publish(self, msg: Image, image, estimate) -> None:
        """Every output of a found robot, each with the image's header."""
        header = msg.header
        if not header.frame_id:
            self._log_throttled("frame_id", "images have an empty header.frame_id: poses and transforms have no frame")
        transform = to_transform_stamped(estimate, header, self.base_frame_id)
        self._pubs["joint_states"].publish(to_joint_state(estimate, header))
        self._pubs["pose"].publish(to_pose_stamped(estimate, header))
        self._pubs["transform"].publish(transform)
        self._pubs["keypoints"].publish(to_keypoints_3d(estimate, header))
        self._pubs["keypoints_2d"].publish(to_keypoints_2d(estimate, header))
        self._pubs["markers"].publish(to_markers(estimate, header, self.parents))
        if self._tf is not None and self.publish_tf:
            self._tf.publish(TFMessage(transforms=[transform]))
        if self.publish_annotated and self._pubs["annotated"].get_subscription_count() > 0:
            drawn = draw_skeleton(image, estimate.keypoints_2d, self.parents)
            self._pubs["annotated"].publish(rgb_to_image(drawn, header))

    # -- diagnostics (timer) ---------------------------------------------------------------------------------
    def _publish_diagnostics(self) -> None:
        """One DiagnosticStatus: level and message from the last period, counters since start."""
        now = time.monotonic()
        with self._lock:
            s = self.stats
            rate = (s.processed - self._period_processed) / max(now - self._period_start, 1e-9)
            new_errors = sum(s.errors.values()) - self._period_errors
            self._period_start, self._period_processed, self._period_errors = now, s.processed, sum(s.errors.values())
            level, message = DiagnosticStatus.OK, f"estimating at {rate:.1f} Hz"
            if s.received == 0:
                level, message = DiagnosticStatus.WARN, f"no images on {self._image_sub.topic_name} yet"
            elif self._camera is None:
                level, message = DiagnosticStatus.WARN, f"no valid CameraInfo on {self._info_sub.topic_name}"
            elif rate == 0 and new_errors:
                level, message = DiagnosticStatus.ERROR, "frames are failing: " + ", ".join(
                    f"{k} {v}" for k, v in sorted(s.errors.items()))
            elif s.found is False:
                level, message = DiagnosticStatus.WARN, "robot not found in the last frame"
            values = {
                "rate_hz": f"{rate:.2f}", "latency_ms": f"{s.latency_ms:.1f}", "inference_ms": f"{s.inference_ms:.1f}",
                "confidence": f"{s.confidence:.3f}", "frames_received": s.received, "frames_processed": s.processed,
                "frames_dropped": s.dropped, "robot_not_found": s.not_found, "skipped_no_camera_info": s.no_camera_info,
                "camera_info_received": s.camera_info_received, "camera_info_rejected": s.camera_info_rejected,
                **{f"errors_{k}": s.errors[k] for k in ("image", "camera_info", "estimator", "internal")},
                **({"calibration_frames": s.calibration_frames, "skipped_no_joint_state": s.no_joint_state,
                    "skipped_joint_state_incomplete": s.joint_state_incomplete, "errors_joint_state":
                    s.errors["joint_state"]} if self._joint_states is not None else {}),
                **({"static_camera_frames": len(camera.poses), "static_camera_restarts": camera.restarts}
                   if (camera := self.estimator.static_camera) is not None else {}),
                "device": self.device, "model": self.model, "pipeline": self._detections is not None,
                "image_topic": self._image_sub.topic_name,
            }
        status = DiagnosticStatus(level=level, name=f"{self.get_fully_qualified_name()}: pose estimation", message=message,
                                  hardware_id=self.device,
                                  values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()  # about the node, not about a frame
        self._diagnostics.publish(array)

    def destroy_node(self) -> None:
        """Stop the workers (each finishes its frame first), then the node."""
        self._frames.close()
        self._workers[0].join()
        if self._detections is not None:
            self._detections.close()
        for worker in self._workers[1:]:
            worker.join()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Console-script entry point: run the node until Ctrl-C; 1 when it cannot start (bad model, device...)."""
    return run_node(EstimatorNode, NODE_NAME, args)


if __name__ == "__main__":
    sys.exit(main())
