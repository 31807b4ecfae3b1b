"""Fuzzing the estimator node through a real graph: a deterministic stream of Image and CameraInfo messages, valid
ones mixed with every kind of wrongness, each case carrying the outcome the node must report for it; and the
harness that starts the node as its own process (the shared-memory profile, a private domain), sends the stream
paced so that nothing can be lost unnoticed, and checks the node's /diagnostics counters against the stream.

The case generator (`fuzz_stream`) is ROS-free; `NodeGraph` and `run_fuzz` import rclpy when called. Used by
scripts/fuzz_node.py (the long run, a table) and test/test_fuzz_node.py (a few hundred messages); `NodeGraph` also
by test/test_burst_delivery.py.

Outcomes (`Case.expect`), mirroring the node's counters:
  answer          a usable frame: estimated and published (min_confidence 0), answered on every output
  image           errors_image: the Image's fields are inconsistent or its encoding unsupported
  camera_info     errors_camera_info: an image of another size than the current CameraInfo (for images), or
                  intrinsics that cannot be used (for CameraInfo, which also leaves the node without intrinsics)
  no_camera_info  skipped_no_camera_info: an image arriving while the node has no valid CameraInfo
  camera          a valid CameraInfo (counted in camera_info_received only)
  undeliverable   serialized bytes that are no message of the type: DDS drops them, the node never sees them
"""

from __future__ import annotations

import math
import re
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

SUPPORTED = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8")
CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
UNSUPPORTED = ("yuv422", "mono16", "16UC1", "32FC1", "bayer_rggb8", "rgb16", "RGB8", "", "jpeg", "8UC3")
MAX_SEC = 2**31 - 1


@dataclass
class Case:
    """One message to send. topic: 'image' | 'camera_info'; fields: the message's fields (header as stamp
    (sec, nanosec) and frame_id); raw: serialized bytes to publish instead (undeliverable cases)."""

    kind: str
    topic: str
    expect: str
    fields: dict = field(default_factory=dict)
    raw: bytes | None = None

    @property
    def key(self) -> tuple[int, int, str]:
        """What identifies this frame's answer: (sec, nanosec, frame_id) of its header."""
        return (*self.fields["stamp"], self.fields["frame_id"])


def test_frame(width: int = 320, height: int = 240) -> tuple[np.ndarray, np.ndarray]:
    """A deterministic RGB image (smooth colour ramps and a checker, no rendering) and a pinhole K for it."""
    v, u = np.mgrid[0:height, 0:width]
    rgb = np.stack([u * 255 // max(width - 1, 1), v * 255 // max(height - 1, 1),
                    ((u // 16 + v // 16) % 2) * 200 + 20], axis=-1).astype(np.uint8)
    K = np.array([[1.2 * width, 0.0, width / 2], [0.0, 1.2 * width, height / 2], [0.0, 0.0, 1.0]])
    return rgb, K


def _pixels(rgb: np.ndarray, encoding: str) -> np.ndarray:
    """The RGB frame in `encoding` (H, W, C)."""
    if encoding == "mono8":
        return rgb.mean(axis=2, keepdims=True).astype(np.uint8)
    pixels = rgb[..., ::-1] if encoding.startswith("bgr") else rgb
    if encoding.endswith("a8"):
        pixels = np.concatenate([pixels, np.full(rgb.shape[:2] + (1,), 255, np.uint8)], axis=2)
    return np.ascontiguousarray(pixels)


def _rows(pixels: np.ndarray, step: int) -> bytes:
    """Row-major bytes of `pixels`, each row padded (with 0x5a) or cut to `step` bytes."""
    height = pixels.shape[0]
    flat = pixels.reshape(height, -1)
    out = np.full((height, step), 0x5A, np.uint8)
    n = min(step, flat.shape[1])
    out[:, :n] = flat[:, :n]
    return out.tobytes()


class _Stream:
    """Builds cases, tracking the node's state (does it hold valid intrinsics, for what size) and keeping every
    expected answer's (stamp, frame_id) unique."""

    def __init__(self, seed: int, rgb: np.ndarray, K: np.ndarray):
        self.rng = np.random.default_rng(seed)
        self.rgb, self.K = rgb, K
        self.height, self.width = rgb.shape[:2]
        self.camera: tuple[int, int] | None = None  # (width, height) of the node's current CameraInfo; (0, 0): any
        self.sec, self.frame_index = 1000, 0
        self.answer_keys: set[tuple[int, int, str]] = set()
        self.cases: list[Case] = []

    # -- headers ------------------------------------------------------------------------------------------
    def _header(self, stamp_kind: str = "next", frame_kind: str = "same") -> tuple[tuple[int, int], str]:
        frame_id = {"same": "camera_optical_frame", "changing": f"camera_{self.frame_index % 7}_optical_frame",
                    "empty": "", "long": "f" * 300, "odd": "cam/ü ütf8 \t frame"}[frame_kind]
        self.frame_index += 1
        if stamp_kind == "next":
            self.sec += 1
            stamp = (self.sec, 123)
        elif stamp_kind == "equal":
            stamp = (self.sec, 123)
        elif stamp_kind == "backwards":
            stamp = (self.sec - 500, 7)
        elif stamp_kind == "zero":
            stamp = (0, 0)
        elif stamp_kind == "future":
            stamp = (MAX_SEC, 999_999_999)
        elif stamp_kind == "negative":
            stamp = (-int(self.rng.integers(1, 10**6)), 5)
        else:
            raise ValueError(stamp_kind)
        return stamp, frame_id

    def _unique(self, stamp: tuple[int, int], frame_id: str) -> tuple[tuple[int, int], str]:
        """Make (stamp, frame_id) unique among expected answers by moving the nanoseconds (stays a valid stamp)."""
        sec, nsec = stamp
        while (sec, nsec, frame_id) in self.answer_keys:
            nsec = (nsec + 1) % 1_000_000_000
        return (sec, nsec), frame_id

    # -- images --------------------------------------------------------------------------------------------
    def image(self, kind: str, encoding: str = "rgb8", height: int | None = None, width: int | None = None,
              step: int | None = None, data: bytes | None = None, is_bigendian: int = 0, layout_ok: bool = True,
              stamp_kind: str = "next", frame_kind: str = "same") -> None:
        """Append an Image case; `layout_ok` says whether the fields are consistent (the node's own rules)."""
        height = self.height if height is None else height
        width = self.width if width is None else width
        if data is None:
            pixels = _pixels(self.rgb, encoding if encoding in CHANNELS else "rgb8")
            step = width * pixels.shape[2] if step is None else step
            data = _rows(pixels, step)
        step = 0 if step is None else step
        if self.camera is None:
            expect = "no_camera_info"
        elif not layout_ok:
            expect = "image"
        elif self.camera != (0, 0) and self.camera != (width, height):
            expect = "camera_info"
        else:
            expect = "answer"
        stamp, frame_id = self._header(stamp_kind, frame_kind)
        if expect == "answer":
            stamp, frame_id = self._unique(stamp, frame_id)
            self.answer_keys.add((*stamp, frame_id))
        self.cases.append(Case(f"Image: {kind}", "image", expect, dict(
            height=height, width=width, encoding=encoding, step=step, is_bigendian=is_bigendian, data=data,
            stamp=stamp, frame_id=frame_id)))

    def valid_image(self, kind: str = "valid frame (closes a round)", **header) -> None:
        self.image(kind, **header)

    def bad_image(self) -> None:
        """One image of a randomly chosen kind of wrongness (or of an unusual but valid form)."""
        h, w = self.height, self.width
        rgb_row = w * 3
        full = _rows(_pixels(self.rgb, "rgb8"), rgb_row)
        choice = int(self.rng.integers(0, 19))
        if choice == 0:
            enc = UNSUPPORTED[int(self.rng.integers(0, len(UNSUPPORTED)))]
            self.image("unsupported encoding", encoding=enc, step=rgb_row, data=full, layout_ok=False)
        elif choice == 1:
            enc = SUPPORTED[int(self.rng.integers(0, len(SUPPORTED)))]
            self.image(f"valid {enc}", encoding=enc)
        elif choice == 2:
            self.image("step too short", step=rgb_row - 3, data=bytes((rgb_row - 3) * h), layout_ok=False)
        elif choice == 3:
            self.image("step padded (valid)", step=rgb_row + 64)
        elif choice == 4:
            self.image("step not a multiple (valid padding)", step=rgb_row + 1)
        elif choice == 5:
            self.image("step too long for data", step=rgb_row + 64, data=full, layout_ok=False)
        elif choice == 6:
            n = int(self.rng.integers(0, len(full)))
            self.image("data shorter", step=rgb_row, data=full[:n], layout_ok=False)
        elif choice == 7:
            n = int(self.rng.integers(1, 5000))
            self.image("data longer", step=rgb_row, data=full + bytes(n), layout_ok=False)
        elif choice == 8:
            self.image("width 0", width=0, step=0, data=b"", layout_ok=False)
        elif choice == 9:
            self.image("height 0", height=0, step=rgb_row, data=b"", layout_ok=False)
        elif choice == 10:
            side = int(self.rng.choice([5000, 65536, 2**31 - 1, 2**32 - 1]))
            self.image("huge width/height", height=side, width=side, step=rgb_row, data=full[:4096],
                       layout_ok=False)
        elif choice == 11:
            self.image("is_bigendian 1 (valid for 8 bit)", is_bigendian=1)
        elif choice == 12:
            self.image("is_bigendian 2..255", is_bigendian=int(self.rng.integers(2, 256)), layout_ok=False)
        elif choice == 13:
            noise = self.rng.integers(0, 256, h * rgb_row, dtype=np.uint8).tobytes()
            self.image("random pixel bytes (valid)", step=rgb_row, data=noise)
        elif choice == 14:
            self.image("random field values", encoding="rgb8", height=int(self.rng.integers(0, 2**32)),
                       width=int(self.rng.integers(0, 2**32)), step=int(self.rng.integers(0, 2**32)),
                       data=self.rng.integers(0, 256, int(self.rng.integers(0, 2000)), dtype=np.uint8).tobytes(),
                       is_bigendian=int(self.rng.integers(0, 256)), layout_ok=False)
        elif choice == 15:
            self.image("stamp backwards", stamp_kind="backwards")
        elif choice == 16:
            self.image("stamp equal", stamp_kind="equal", frame_kind="changing")
        elif choice == 17:
            kind = ["zero", "future", "negative"][int(self.rng.integers(0, 3))]
            self.image("stamp far past/future/negative", stamp_kind=kind)
        else:
            kind = ["changing", "empty", "long", "odd"][int(self.rng.integers(0, 4))]
            self.image("frame_id changing/empty/odd", frame_kind=kind)

    def garbage(self, topic: str) -> None:
        """Serialized bytes no subscriber can decode: random, cut short, or a 4-byte header alone."""
        n = int(self.rng.integers(0, 600))
        body = self.rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        raw = [b"\x00\x01\x00\x00" + body, b"\x00\x01\x00\x00", b"\x00\x01\x00\x00" + b"\xff" * 64][n % 3]
        self.cases.append(Case(f"{'Image' if topic == 'image' else 'CameraInfo'}: undecodable bytes", topic,
                               "undeliverable", raw=raw))

    # -- camera info -------------------------------------------------------------------------------------
    def camera_info(self, kind: str, K: np.ndarray | None = None, width: int | None = None, height: int | None = None,
                    p: list[float] | None = None, usable: bool = True, stamp_kind: str = "next",
                    frame_kind: str = "same") -> None:
        K = self.K if K is None else K
        width = self.width if width is None else width
        height = self.height if height is None else height
        P = np.zeros((3, 4))
        P[:, :3] = np.nan_to_num(K)
        stamp, frame_id = self._header(stamp_kind, frame_kind)
        self.cases.append(Case(f"CameraInfo: {kind}", "camera_info", "camera" if usable else "camera_info", dict(
            width=width, height=height, k=[float(x) for x in np.asarray(K, float).ravel()],
            p=[float(x) for x in (P.ravel() if p is None else p)], stamp=stamp, frame_id=frame_id)))
        self.camera = (width, height) if usable else None

    def valid_camera_info(self) -> None:
        self.camera_info("valid")

    def bad_camera_info(self) -> None:
        choice = int(self.rng.integers(0, 12))
        K = self.K.copy()
        if choice == 0:
            K[0, 0] = math.nan
            self.camera_info("fx NaN", K, usable=False)
        elif choice == 1:
            K[1, 1] = math.inf
            self.camera_info("fy inf", K, usable=False)
        elif choice == 2:
            self.camera_info("K all zeros", np.zeros((3, 3)), usable=False)
        elif choice == 3:
            K[0, 0] = -abs(K[0, 0])
            self.camera_info("fx negative", K, usable=False)
        elif choice == 4:
            K[1, 1] = 0.0
            self.camera_info("fy zero", K, usable=False)
        elif choice == 5:
            K[2] = [0.0, 1.0, 1.0]
            self.camera_info("last row not 0 0 1", K, usable=False)
        elif choice == 6:
            self.camera_info("size of another camera", width=self.width * 2, height=self.height * 2)
        elif choice == 7:
            self.camera_info("size 0 x 0 (unknown: accepted)", width=0, height=0)
        elif choice == 8:
            self.camera_info("p NaN (unused: accepted)", p=[math.nan] * 12)
        elif choice == 9:
            self.camera_info("frame_id changing", frame_kind="changing")
        elif choice == 10:
            self.camera_info("stamp backwards/equal", stamp_kind=["backwards", "equal"][int(self.rng.integers(2))])
        else:
            self.camera_info("stamp far past/future", stamp_kind=["zero", "future"][int(self.rng.integers(2))])


def fuzz_stream(messages: int, seed: int = 0, frame: tuple[np.ndarray, np.ndarray] | None = None) -> list[Case]:
    """The first `messages` cases: images before any CameraInfo, then rounds of 1 to 3 wrong images (or
    undecodable bytes) while the intrinsics are valid, sometimes a wrong CameraInfo (and an image meanwhile), each
    round closed by a valid CameraInfo and a valid frame: every valid frame comes right after something wrong.
    Deterministic in (messages, seed, frame)."""
    rgb, K = test_frame() if frame is None else frame
    s = _Stream(seed, rgb, K)
    s.valid_image("before any CameraInfo")
    s.bad_image()
    s.valid_camera_info()
    s.valid_image()
    while len(s.cases) < messages:
        start = len(s.cases)
        for _ in range(int(s.rng.integers(1, 4))):  # wrong images (or bytes) while the intrinsics are valid
            if s.rng.random() < 0.85:
                s.bad_image()
            else:
                s.garbage("image" if s.rng.random() < 0.5 else "camera_info")
        if s.rng.random() < 0.4:  # then wrong intrinsics, sometimes an image while the node has none
            s.bad_camera_info()
            if s.rng.random() < 0.3:
                s.bad_image()
        while all(c.expect in ("answer", "camera") for c in s.cases[start:]):  # only unusual but valid so far
            s.bad_image()
        s.valid_camera_info()
        s.valid_image()
    return s.cases[:max(messages, 0)]


def to_message(case: Case):
    """The rclpy message of `case` (or its raw bytes)."""
    if case.raw is not None:
        return case.raw
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import CameraInfo, Image
    from std_msgs.msg import Header

    f = case.fields
    header = Header(stamp=Time(sec=f["stamp"][0], nanosec=f["stamp"][1]), frame_id=f["frame_id"])
    if case.topic == "image":
        msg = Image(header=header, height=f["height"], width=f["width"], encoding=f["encoding"],
                    is_bigendian=f["is_bigendian"], step=f["step"])
        msg.data = f["data"]
        return msg
    msg = CameraInfo(header=header, width=f["width"], height=f["height"], distortion_model="plumb_bob")
    msg.d = [0.0] * 5
    msg.k, msg.p = f["k"], f["p"]
    msg.r = np.eye(3).ravel().tolist()
    return msg


def expected_counters(cases: list[Case]) -> dict[str, int]:
    """What the node's /diagnostics must count for `cases` (all delivered, none dropped)."""
    images = [c for c in cases if c.topic == "image" and c.expect != "undeliverable"]
    infos = [c for c in cases if c.topic == "camera_info" and c.expect != "undeliverable"]
    e = Counter(c.expect for c in images)
    return {"frames_received": len(images), "frames_processed": e["answer"], "frames_dropped": 0,
            "robot_not_found": 0, "skipped_no_camera_info": e["no_camera_info"], "errors_image": e["image"],
            "errors_camera_info": e["camera_info"] + sum(c.expect == "camera_info" for c in infos),
            "errors_estimator": 0, "errors_internal": 0, "camera_info_received": len(infos),
            "camera_info_rejected": sum(c.expect == "camera_info" for c in infos)}


# -- log analysis ----------------------------------------------------------------------------------------------
_LOG_LINE = re.compile(r"^\[(DEBUG|INFO|WARN|ERROR|FATAL)\] \[(\d+\.\d+)\] \[[^\]]+\]: (.*)$")


def log_stats(text: str, since: float = 0.0) -> dict:
    """The node's log lines stamped at or after `since` (s, wall clock): count, reasons (the node's
    reason_template), the most lines one reason wrote in any LOG_PERIOD_S window, and other output lines (not from
    the node's logger, e.g. rcutils' error-state notices, counted over the whole file)."""
    from holo_pose_ros.nodes.estimator_node import LOG_PERIOD_S, reason_template

    by_reason: dict[str, list[float]] = {}
    other = 0
    for line in text.splitlines():
        m = _LOG_LINE.match(line)
        if m is None:
            other += bool(line.strip())
        elif float(m.group(2)) >= since:
            by_reason.setdefault(reason_template(m.group(3)), []).append(float(m.group(2)))
    worst = 0
    for stamps in by_reason.values():
        stamps.sort()
        j = 0
        for i, t in enumerate(stamps):
            while stamps[j] <= t - LOG_PERIOD_S:
                j += 1
            worst = max(worst, i - j + 1)
    return {"lines": sum(map(len, by_reason.values())), "reasons": len(by_reason),
            "max_per_reason_per_period": worst, "other_lines": other}


# -- the graph (rclpy) ---------------------------------------------------------------------------------------
class NodeGraph:
    """The estimator node as its own process and a probe node here (its own context, spun on a thread), on a
    private domain with the shared-memory profile: publishes Image (reliable, depth 10, as camera drivers do) and
    CameraInfo, records answers by (stamp, frame_id) and the latest /diagnostics of the node. An answer is the
    frame's ~/markers, the last output the node publishes for a frame (annotated images and /tf are off): once it
    has arrived the node's worker is free for the next image."""

    def __init__(self, model: str | Path, log: Path, robot: str = "panda", backend: str = "torch", threads: int = 1,
                 **params):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import CameraInfo, Image
        from visualization_msgs.msg import MarkerArray

        from holo_pose_ros.nodes.processes import private_graph_env, start_node

        self.env = private_graph_env()
        self.env.setdefault("OMP_NUM_THREADS", str(max(threads, 1)))
        self.log = Path(log)
        self.process = start_node("estimator_node", {
            "robot": robot, "model": str(model), "backend": backend, "threads": threads, "min_confidence": 0.0,
            "publish_annotated": False, "publish_tf": False, **params}, self.log, self.env)
        self.context = Context()
        rclpy.init(context=self.context, domain_id=int(self.env["ROS_DOMAIN_ID"]))
        self.node = rclpy.create_node("holo_pose_fuzz_probe", context=self.context)
        self.image_pub = self.node.create_publisher(Image, "image", 10)
        self.info_pub = self.node.create_publisher(CameraInfo, "camera_info", 10)
        self.answers: dict[tuple[int, int, str], float] = {}
        self.diagnostics: dict[str, str] = {}
        self.diagnostics_count = 0
        self.node.create_subscription(MarkerArray, "/holo_pose_estimator/markers", self._on_answer, 100)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._spinner = threading.Thread(target=self._spin, daemon=True)
        self._spinner.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self.executor.spin()
        except (ExternalShutdownException, Exception):  # shutting down
            pass

    def _on_answer(self, msg) -> None:
        if not msg.markers:
            return
        header = msg.markers[0].header
        key = (int(header.stamp.sec), int(header.stamp.nanosec), str(header.frame_id))
        self.answers.setdefault(key, time.monotonic())

    def _on_diagnostics(self, msg) -> None:
        for status in msg.status:
            if status.name.split(":")[0].endswith("holo_pose_estimator"):
                self.diagnostics = {kv.key: kv.value for kv in status.values}
                self.diagnostics["level"], self.diagnostics["message"] = str(status.level), status.message
                self.diagnostics_count += 1

    def alive(self) -> bool:
        return self.process.poll() is None

    def counter(self, key: str) -> int:
        return int(self.diagnostics.get(key, 0))

    def wait(self, predicate, timeout_s: float, period_s: float = 0.005) -> bool:
        """Wait until `predicate()` or `timeout_s`; False as soon as the node process has died."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate():
                return True
            if not self.alive():
                return False
            time.sleep(period_s)
        return predicate()

    def fresh_diagnostics(self, timeout_s: float = 3.0) -> dict[str, str]:
        """The first /diagnostics published after this call (the counters as of now)."""
        seen = self.diagnostics_count
        self.wait(lambda: self.diagnostics_count > seen + 1, timeout_s, 0.02)
        return dict(self.diagnostics)

    def wait_ready(self, image, info, timeout_s: float = 300.0) -> bool:
        """Send `info` + `image` every 0.3 s until the node answers `image` (it loads its model meanwhile)."""
        key = (image.header.stamp.sec, image.header.stamp.nanosec, image.header.frame_id)

        def poke():
            if key not in self.answers:
                self.info_pub.publish(info)
                self.image_pub.publish(image)
            return key in self.answers

        deadline = time.monotonic() + timeout_s
        while self.alive() and time.monotonic() < deadline and not poke():
            time.sleep(0.3)
        return key in self.answers

    def publish(self, case: Case) -> None:
        (self.image_pub if case.topic == "image" else self.info_pub).publish(to_message(case))

    def peak_rss_mb(self) -> float:
        """The node process's peak resident memory (VmHWM), MB."""
        for line in Path(f"/proc/{self.process.pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
        return float("nan")

    def close(self) -> None:
        import rclpy

        from holo_pose_ros.nodes.processes import stop_nodes

        stop_nodes([self.process])
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._spinner.join(timeout=5)


# -- the run ---------------------------------------------------------------------------------------------------
def run_fuzz(model: str | Path, messages: int, seed: int, log: Path, backend: str = "torch", threads: int = 1,
             gap_s: float = 0.05, answer_timeout_s: float = 10.0, startup_timeout_s: float = 300.0,
             progress=None) -> dict:
    """Start the node, send `fuzz_stream(messages, seed)`, paced: `gap_s` after each message, and each frame that
    must be answered waited for (up to `answer_timeout_s`) before the next message. Returns what was sent, what
    the node answered and counted, whether it is alive, its log statistics and its peak RSS."""
    rgb, K = test_frame()
    cases = fuzz_stream(messages, seed, (rgb, K))
    graph = NodeGraph(model, log, backend=backend, threads=threads)
    t0 = time.monotonic()
    try:
        from msg_adapters import camera_info_from_K, make_header, rgb_to_image

        warm = make_header(1, "warm_up")
        if not graph.wait_ready(rgb_to_image(rgb, warm), camera_info_from_K(K, rgb.shape[1], rgb.shape[0], warm),
                                startup_timeout_s):
            raise RuntimeError(f"the estimator node did not answer; its log ({log}):\n{log.read_text()[-3000:]}")
        startup_s = time.monotonic() - t0
        # counters before the stream (the warm-up's), and the node's clock at the start (for its log lines)
        before = graph.fresh_diagnostics()
        ros_start = time.time()
        # the warm-up left valid intrinsics; the stream starts as if the node had none, so drop them first
        graph.publish(Case("reset", "camera_info", "camera_info", dict(
            width=rgb.shape[1], height=rgb.shape[0], k=[0.0] * 9, p=[0.0] * 12, stamp=(1, 1), frame_id="reset")))
        time.sleep(gap_s)
        t_stream = time.monotonic()
        unanswered: list[Case] = []
        for i, case in enumerate(cases):
            if not graph.alive():
                break
            graph.publish(case)
            if case.expect == "answer":
                if not graph.wait(lambda: case.key in graph.answers, answer_timeout_s):
                    unanswered.append(case)
            time.sleep(gap_s)
            if progress is not None and (i + 1) % 500 == 0:
                progress(i + 1, len(cases), time.monotonic() - t_stream)
        stream_s = time.monotonic() - t_stream
        expected = expected_counters(cases)
        expected["errors_camera_info"] += 1  # the reset above
        expected["camera_info_received"] += 1
        expected["camera_info_rejected"] += 1
        # wait until the node has counted everything it received (or a few seconds)
        target = int(before.get("frames_received", 0)) + expected["frames_received"]
        graph.wait(lambda: graph.counter("frames_received") >= target, 5.0, 0.05)
        after = graph.fresh_diagnostics()
        alive = graph.alive()
        rss = graph.peak_rss_mb() if alive else float("nan")
    finally:
        graph.close()
    counted = {k: int(after.get(k, 0)) - int(before.get(k, 0)) for k in expected}
    answer_cases = [c for c in cases if c.expect == "answer"]
    by_kind: dict[str, Counter] = {}
    for c in cases:
        row = by_kind.setdefault(c.kind, Counter())
        row["sent"] += 1
        row[c.expect] += 1
        if c.expect == "answer":
            row["answered"] += c.key in graph.answers
    return {"messages": len(cases), "seed": seed, "by_kind": by_kind, "alive": alive, "restarts": 0,
            "answers_expected": len(answer_cases), "answered": sum(c.key in graph.answers for c in answer_cases),
            "unanswered": [(c.kind, c.key) for c in unanswered], "expected": expected, "counted": counted,
            "log": log_stats(log.read_text(), since=ros_start), "stream_s": stream_s, "startup_s": startup_s,
            "peak_rss_mb": rss}


def format_fuzz(r: dict) -> str:
    """The run as a text table."""
    lines = [f"fuzz: {r['messages']} messages, seed {r['seed']}, stream {r['stream_s']:.0f} s "
             f"(node start-up {r['startup_s']:.0f} s)", "",
             f"{'kind':44s} {'sent':>6s}  {'expected outcome':44s} {'answered':>9s}"]
    for kind, row in sorted(r["by_kind"].items(), key=lambda kv: -kv[1]["sent"]):
        outcomes = ", ".join(f"{k} {v}" for k, v in sorted(row.items()) if k not in ("sent", "answered"))
        answered = f"{row['answered']}/{row['answer']}" if row["answer"] else ""
        lines.append(f"{kind:44s} {row['sent']:6d}  {outcomes:44s} {answered:>9s}")
    lines += ["", f"{'/diagnostics counter':28s} {'expected':>9s} {'counted':>9s}"]
    for key, value in r["expected"].items():
        mark = "" if r["counted"].get(key) == value else "   <-- differs"
        lines.append(f"{key:28s} {value:9d} {r['counted'].get(key, 0):9d}{mark}")
    log = r["log"]
    rate = log["lines"] / max(r["stream_s"], 1e-9)
    lines += ["", f"node alive at the end      {'yes' if r['alive'] else 'NO'}",
              f"node restarts              {r['restarts']}",
              f"valid frames answered      {r['answered']} / {r['answers_expected']}"
              f"{'  unanswered: ' + str(r['unanswered'][:5]) if r['unanswered'] else ''}",
              f"images not received        {r['expected']['frames_received'] - r['counted']['frames_received']}"
              " (replaced in the node's best-effort depth-1 queue before it took them: pacing too tight)",
              f"received, in no counter    {unaccounted(r['counted'])}",
              f"log lines                  {log['lines']} ({rate:.2f}/s), {log['reasons']} reasons, at most "
              f"{log['max_per_reason_per_period']} lines of one reason in 5 s; {log['other_lines']} other output lines",
              f"node peak RSS              {r['peak_rss_mb']:.0f} MB"]
    return "\n".join(lines)


def unaccounted(c: dict) -> int:
    """Images the node received but counted in no outcome (negative: counted twice). Each image ends in exactly
    one of processed, dropped, skipped, or an error; camera_info errors not from a rejected CameraInfo are images
    of the wrong size."""
    outcomes = (c["frames_processed"] + c["frames_dropped"] + c["skipped_no_camera_info"] + c["errors_image"]
                + c["errors_estimator"] + c["errors_internal"] + c["errors_camera_info"] - c["camera_info_rejected"])
    return c["frames_received"] - outcomes
