"""ROS 2 node `dream_replay`: publishes a DREAM folder as sensor_msgs/Image (rgb8) + CameraInfo, with its ground
truth, at a fixed rate or in lockstep with the estimator, so that a live graph can be scored like
`holo-pose evaluate` (see evaluation_node.py).

Run: `ros2 run holo_pose_ros dream_replay_node --ros-args -p folder:=/data/panda_synth_test_dr -p lockstep:=true`
(or the console script `holo-pose-replay --ros-args ...`).

Per frame, in this order, all with one header (frame_id, synthetic stamp):
  ~/ground_truth/{joint_states,pose,keypoints,keypoints_2d}   reliable, transient local (depth 100); the layout
                                                              of holo_pose_ros.bags (GROUND_TRUTH_NS)
  camera_info, image                                          relative names, reliable (parameter `reliable`)
and, when every frame has been sent (not looping), `~/done` (std_msgs/UInt32, reliable, transient local: the
number of frames sent).

Stamps are synthetic: start_time_s + k / rate for the k-th frame sent (k counts on across loops), so runs are
reproducible and strictly increasing; `rate` sets them in lockstep mode too.

Lockstep (deterministic: every frame is handled by the estimator before the next is sent). A frame counts as
handled when the first of these happens:
  1. the estimator's `<estimator>/joint_states` arrives with the frame's stamp (the robot was found);
  2. the estimator's /diagnostics status shows its handled-frame count (frames_processed + skipped_no_camera_info
     + frames_dropped + errors_image + errors_estimator + errors_internal) has reached the number of frames this
     node sent it, counted from the value in the first diagnostics received before sending: this is how a frame
     where the robot was not found (no output at all) is detected, within the estimator's diagnostic period (1 s);
     a frame the estimator skipped for lack of a CameraInfo is sent again (up to MAX_RESENDS times);
  3. `lockstep_timeout_s` passes (the frame was lost): a warning, and the count is re-synchronised.
It assumes this node is the estimator's only image source. Before the first image, the first CameraInfo is sent
alone, so that the estimator has intrinsics when the first image arrives.
"""

from __future__ import annotations

import sys
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, JointState, PointCloud2
from std_msgs.msg import UInt32

from holo_pose_ros.nodes.parameters import ParameterSpecs, declare_parameters
from holo_pose_ros.nodes.runner import run_node
from holo_pose_ros.bags import GroundTruth, estimate_messages, frame_stamp_ns
from msg_adapters import camera_info_from_K, make_header, rgb_to_image, stamp_ns

NODE_NAME = "dream_replay"
MAX_RESENDS = 3  # sends of one frame skipped by the estimator for lack of a CameraInfo
PRIME_S = 0.2  # the first CameraInfo goes out alone this long before the first image
HANDLED_KEYS = ("frames_processed", "skipped_no_camera_info", "frames_dropped", "errors_image", "errors_estimator",
                "errors_internal")
GROUND_TRUTH_TYPES = {"joint_states": JointState, "pose": PoseStamped, "keypoints": PoseArray,
                      "keypoints_2d": PointCloud2}
LATCHED = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                     history=HistoryPolicy.KEEP_LAST, depth=1)
GROUND_TRUTH_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                              history=HistoryPolicy.KEEP_LAST, depth=100)

_POSITIVE = dict(floating_point_range=[FloatingPointRange(from_value=1e-3, to_value=1e6)])
# name -> (description, read_only, ranges); defaults live in config/dream_replay.yaml only
PARAMETERS: ParameterSpecs = {
    "folder": ("DREAM folder to replay (required): _camera_settings.json + NNNNNN.json + NNNNNN.rgb.jpg|png.", True, {}),
    "robot": ("Robot YAML name or path: keypoint and joint names and order of the ground truth.", True, {}),
    "units": ("3D units of the folder's files: auto (detected), m or cm.", True, {}),
    "rate": ("Frames per second: the publishing rate (unless lockstep) and the spacing of the "
             "synthetic stamps (always).", True, _POSITIVE),
    "lockstep": ("Send the next frame only when the estimator has handled this one (see the module "
                 "docstring): deterministic evaluation at the estimator's own speed.", True, {}),
    "lockstep_timeout_s": ("Lockstep: seconds to wait for a frame to be handled before moving on.", True, _POSITIVE),
    "estimator": ("Lockstep: fully qualified name of the estimator node; its joint_states and its "
                  "status on /diagnostics acknowledge frames.", True, {}),
    "loop": ("Start again from the first frame after the last (stamps keep increasing); no ~/done.", True, {}),
    "limit": ("Replay only the first N frames of the folder (0: all).",
              True, dict(integer_range=[IntegerRange(from_value=0, to_value=2**31 - 1)])),
    "frame_id": ("header.frame_id of every message (the camera's optical frame).", True, {}),
    "start_time_s": ("Stamp of the first frame, seconds (synthetic, reproducible stamps).",
                     True, dict(floating_point_range=[FloatingPointRange(from_value=0.0, to_value=1e10)])),
    "image_topic": ("Output sensor_msgs/Image topic (rgb8); relative, remappable.", True, {}),
    "camera_info_topic": ("Output sensor_msgs/CameraInfo topic; relative, remappable.", True, {}),
    "reliable": ("Publish images and camera_info RELIABLE (else BEST_EFFORT); depth 5, volatile.", True, {}),
    "wait_for_subscriber": ("Start only once the image topic has a subscriber.", True, {}),
    "exit_when_done": ("main(): exit once ~/done is published (the latched ~/done goes with the node).", True, {}),
}


def _handled(values: dict[str, str]) -> int | None:
    """The estimator's count of frames it is done with (answered or skipped), from its diagnostic values."""
    try:
        return sum(int(values[key]) for key in HANDLED_KEYS)
    except (KeyError, ValueError):
        return None


class DreamReplayNode(Node):
    """Publishes a DREAM folder; see the module docstring."""

    def __init__(self, **node_kwargs):
        super().__init__(NODE_NAME, **node_kwargs)
        p = declare_parameters(self, "dream_replay.yaml", PARAMETERS)
        if not p["folder"]:
            raise ValueError("parameter 'folder' (the DREAM folder to replay) is required")
        from holo_pose_ros.data.dream import DreamReader

        self.reader = DreamReader(p["folder"], p["robot"], units=p["units"])
        self.frames = list(self.reader)[:p["limit"] or None]
        self.joint_names = self.reader.robot.joint_names
        self.rate, self.start_time_s, self.frame_id = p["rate"], p["start_time_s"], p["frame_id"]
        self.lockstep, self.loop, self.timeout_s = p["lockstep"], p["loop"], p["lockstep_timeout_s"]
        self.wait_for_subscriber, self.exit_when_done = p["wait_for_subscriber"], p["exit_when_done"]
        frame_stamp_ns(0, self.start_time_s, self.rate)  # validates rate and start time

        reliability = ReliabilityPolicy.RELIABLE if p["reliable"] else ReliabilityPolicy.BEST_EFFORT
        stream = QoSProfile(reliability=reliability, durability=DurabilityPolicy.VOLATILE,
                            history=HistoryPolicy.KEEP_LAST, depth=5)
        self._image_pub = self.create_publisher(Image, p["image_topic"], stream)
        self._info_pub = self.create_publisher(CameraInfo, p["camera_info_topic"], stream)
        self._truth_pubs = {name: self.create_publisher(cls, f"~/ground_truth/{name}", GROUND_TRUTH_QOS)
                            for name, cls in GROUND_TRUTH_TYPES.items()}
        self._done_pub = self.create_publisher(UInt32, "~/done", LATCHED)

        self.sent = 0  # frames sent (each frame once; re-sends not counted)
        self.stamps: list[int] = []  # stamp (ns) of each frame sent
        self.unanswered = 0  # lockstep: frames given up after lockstep_timeout_s
        self.finished = False
        self._state = "waiting"  # waiting -> priming -> running -> done
        self._since = time.monotonic()
        # lockstep bookkeeping
        self._estimator_name = "/" + p["estimator"].strip("/")  # its diagnostics are named by its full name
        self._handled: int | None = None  # the estimator's latest handled count
        self._no_camera_info: int | None = None
        self._expected: int | None = None  # its handled count once it has handled every frame sent so far
        self._pending: dict | None = None  # the frame awaiting its acknowledgement
        if self.lockstep:
            ack_topic = p["estimator"].rstrip("/") + "/joint_states"
            self.create_subscription(JointState, ack_topic, self._on_ack, 10)
            self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)
            self._timer = self.create_timer(0.01, self._tick)
        else:
            self._timer = self.create_timer(1.0 / self.rate, self._tick)
        mode = f"lockstep with {p['estimator']}" if self.lockstep else f"at {self.rate:g} Hz"
        self.get_logger().info(
            f"replaying {len(self.frames)} frames of {self.reader.folder} ({self.reader.robot.name}) {mode} on "
            f"{self._image_pub.topic_name} and {self._info_pub.topic_name}" + (", looping" if self.loop else ""))

    # -- publishing ------------------------------------------------------------------------------------------------
    def _header(self, k: int):
        return make_header(frame_stamp_ns(k, self.start_time_s, self.rate), self.frame_id)

    def _publish_camera_info(self, k: int) -> None:
        frame = self.frames[k % len(self.frames)]
        self._info_pub.publish(camera_info_from_K(frame.K, frame.width, frame.height, self._header(k)))

    def _publish_frame(self, k: int) -> None:
        """Ground truth, CameraInfo and Image of the k-th frame sent (folder frame k mod n)."""
        frame = self.frames[k % len(self.frames)]
        header = self._header(k)
        truth = GroundTruth.from_frame(frame, self.joint_names)
        for name, msg in estimate_messages(truth, header).items():
            self._truth_pubs[name].publish(msg)
        self._info_pub.publish(camera_info_from_K(frame.K, frame.width, frame.height, header))
        self._image_pub.publish(rgb_to_image(self.reader.load_image(frame), header))

    def _send_next(self) -> None:
        """Send frame number `self.sent`, or finish when every frame has been sent (not looping)."""
        if self.sent >= len(self.frames) and not self.loop:
            return self._finish()
        k = self.sent
        self._publish_frame(k)
        self.stamps.append(stamp_ns(self._header(k).stamp))
        self.sent += 1
        if self.lockstep:
            if self._expected is not None:
                self._expected += 1
            self._pending = {"k": k, "stamp": self.stamps[-1], "sent_at": time.monotonic(), "resends": 0,
                             "no_camera_info": self._no_camera_info, "target": self._expected}

    def _finish(self) -> None:
        self._state, self.finished = "done", True
        self._timer.cancel()
        self._done_pub.publish(UInt32(data=self.sent))
        lost = f", {self.unanswered} not acknowledged within {self.timeout_s:g} s" if self.unanswered else ""
        self.get_logger().info(f"done: {self.sent} frames sent{lost}; published {self._done_pub.topic_name}")

    # -- state machine -----------------------------------------------------------------------------------------------
    def _tick(self) -> None:
        now = time.monotonic()
        if self._state == "waiting":
            if self.wait_for_subscriber and self._image_pub.get_subscription_count() == 0:
                self._since = now  # the wait for the estimator's diagnostics starts with its subscription
                return
            if self.lockstep and self._handled is None and now - self._since < self.timeout_s:
                return  # wait for the estimator's first diagnostics (its handled count)
            if self.lockstep and self._handled is None:
                self.get_logger().warning(f"no diagnostics from '{self._estimator_name}' within {self.timeout_s:g} s: "
                                          "frames where the robot is not found will wait for the timeout")
            self._expected = self._handled
            self._publish_camera_info(0)
            self._state, self._since = "priming", now
        elif self._state == "priming":
            if now - self._since >= PRIME_S:
                self._state = "running"
                self._send_next()
        elif self._state == "running":
            if not self.lockstep:
                self._send_next()
            elif self._pending is not None and now - self._pending["sent_at"] > self.timeout_s:
                self.unanswered += 1
                self.get_logger().warning(f"frame {self._pending['k']} (stamp {self._pending['stamp']} ns) not "
                                          f"acknowledged within {self.timeout_s:g} s: moving on")
                self._expected = self._handled
                self._advance()

    def _advance(self) -> None:
        self._pending = None
        self._send_next()

    # -- lockstep acknowledgements -------------------------------------------------------------------------------
    def _on_ack(self, msg: JointState) -> None:
        if self._pending is not None and stamp_ns(msg.header.stamp) == self._pending["stamp"]:
            self._advance()

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name.split(":", 1)[0] != self._estimator_name:
                continue
            values = {kv.key: kv.value for kv in status.values}
            handled = _handled(values)
            if handled is None:
                continue
            self._handled = handled
            self._no_camera_info = int(values["skipped_no_camera_info"])
            pending = self._pending
            if pending is None or pending["target"] is None or handled < pending["target"]:
                continue
            skipped = pending["no_camera_info"] is not None and self._no_camera_info > pending["no_camera_info"]
            if skipped and pending["resends"] < MAX_RESENDS:
                self.get_logger().info(f"frame {pending['k']} reached the estimator before a CameraInfo: sending it "
                                       "again")
                self._publish_frame(pending["k"])
                self._expected += 1
                pending.update(sent_at=time.monotonic(), resends=pending["resends"] + 1,
                               no_camera_info=self._no_camera_info, target=self._expected)
            else:
                self._advance()


def main(args: list[str] | None = None) -> int:
    """Console-script entry point: replay until Ctrl-C (or until done, with exit_when_done); 1 on a bad start."""
    return run_node(DreamReplayNode, NODE_NAME, args, done=lambda node: node.finished and node.exit_when_done)


if __name__ == "__main__":
    sys.exit(main())
