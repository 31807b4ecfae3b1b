"""Speed of the deployed pipeline on generated frames, stage by stage: Image message -> RGB, localization (the
whole first pass), crop and network (the crop pass, and the close-ups' when on), the heads' forward kinematics, the
lifter, the fit, output messages. Latencies in milliseconds (p50 / p95 / max), frames per second, GFLOPs of one
network pass (torch's FlopCounterMode), parameters, peak resident memory. ROS-free
(message types only, through msg_adapters)."""

from __future__ import annotations

import platform
import resource
import time
from pathlib import Path

import numpy as np
import torch
from std_msgs.msg import Header

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.model.network import HolisticNet, example_inputs
from msg_adapters import (image_to_rgb, rgb_to_image, to_joint_state, to_keypoints_2d, to_keypoints_3d, to_markers,
                          to_pose_stamped, to_transform_stamped)

TRACKING_HOLD = 10  # frames per scene when tracking independent frames (a video plays in order instead)
STAGES = ("image_conversion", "localize", "crop", "network", "kinematics", "lifter", "fit", "in_view", "messages",
          "total")


def network_gflops(net: HolisticNet) -> float:
    """GFLOPs of one network pass at the model's input size (multiply-adds counted as 2 FLOPs)."""
    from torch.utils.flop_counter import FlopCounterMode

    inputs = example_inputs(net.cfg.input_size, device=next(net.parameters()).device)
    with torch.inference_mode(), FlopCounterMode(display=False) as counter:
        net(*inputs)
    return counter.get_total_flops() / 1e9


def stream_frames(reader: DreamReader, needed: int, tracking: bool, cap: int) -> tuple[list, int]:
    """What a timed run cycles over, and how many times in a row each frame is sent: a generated video plays in
    order, each frame once, as its camera would deliver it (up to `needed` frames); a folder of independent scenes
    gives its first `cap` frames, each held TRACKING_HOLD times when tracking (a camera watching a slow arm), else
    once."""
    from holo_pose_ros.data.generator import is_video_folder

    frames = list(reader)
    if is_video_folder(reader.folder):
        return frames[:needed], 1
    return frames[:cap], TRACKING_HOLD if tracking else 1


def _messages(estimate, header: Header, parents: list[int]) -> None:
    """Build every output message of the estimator node for one estimate."""
    to_joint_state(estimate, header)
    to_pose_stamped(estimate, header)
    to_transform_stamped(estimate, header, "robot_base_link")
    to_keypoints_3d(estimate, header)
    to_keypoints_2d(estimate, header)
    to_markers(estimate, header, parents)


def benchmark(model: str | Path, data: str | Path, frames: int = 100, device: str = "cpu", tracking: bool = False,
              threads: int | None = None, warmup: int = 5, backend: str = "torch", fit: bool | None = None,
              parts: bool | None = None, localize_size: int | None = None, close_ups: bool | None = None,
              static_camera: bool = False) -> dict:
    """Time `frames` estimates (cycling over the folder's frames after `warmup` untimed ones); returns the figures.
    Tracking needs a stream: a generated video plays in order; independent frames are each held for TRACKING_HOLD
    frames (stream_frames). With `static_camera` (play a generated video: one camera per clip) its refit is the
    'static_camera' stage."""
    if threads:
        torch.set_num_threads(threads)
    estimator = Estimator.from_model(model, device=device, backend=backend, threads=threads, tracking=tracking,
                                     min_confidence=0.0, fit=fit, parts=parts, localize_size=localize_size,
                                     close_ups=close_ups, static_camera=static_camera)
    reader = DreamReader(data, estimator.robot)
    chosen, hold = stream_frames(reader, warmup + frames, tracking, cap=50)
    pool = [(rgb_to_image(reader.load_image(f), Header(frame_id="camera")), f.K) for f in chosen]
    parents = estimator.robot.keypoint_parents
    stages = (*STAGES[:-2], "static_camera", *STAGES[-2:]) if static_camera else STAGES
    samples = {stage: [] for stage in stages}
    for i in range(warmup + frames):
        msg, K = pool[(i // hold) % len(pool)]
        t0 = time.perf_counter()
        image = image_to_rgb(msg)
        t1 = time.perf_counter()
        estimate = estimator.estimate(image, K)
        t2 = time.perf_counter()
        if estimate.found:
            _messages(estimate, msg.header, parents)
        t3 = time.perf_counter()
        if i < warmup:
            continue
        timings = estimate.timings_ms
        samples["image_conversion"].append((t1 - t0) * 1e3)
        for stage in stages[1:-2]:  # the estimator's own stages: localize ... fit (and the static camera's)
            samples[stage].append(timings.get(stage, 0.0))
        samples["messages"].append((t3 - t2) * 1e3)
        samples["total"].append((t3 - t0) * 1e3)
    stats = {stage: _summary(np.array(v)) for stage, v in samples.items()}
    total = np.array(samples["total"])
    return {
        "model": str(model), "robot": estimator.robot.name, "config": estimator.net.cfg.name,
        "input_size": estimator.size, "tracking": tracking, "frames": frames,
        "fps": float(1e3 / total.mean()), "latency_ms_p50": stats["total"]["p50"],
        "latency_ms_p95": stats["total"]["p95"], "latency_ms_max": stats["total"]["max"],
        "stages_ms": stats, "gflops": network_gflops(estimator.net), "passes_per_frame": 1 if tracking else 2,
        "params_m": sum(p.numel() for p in estimator.net.parameters()) / 1e6,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "device": device_name(estimator.device, threads or torch.get_num_threads()),
        "backend": backend, "fit": estimator.fit, "parts": estimator.parts, "close_ups": estimator.close_ups,
        "static_camera": static_camera,
        "localize_size": estimator.localize_size,
    }


def device_name(device: torch.device, threads: int) -> str:
    """What the figures were measured on, in words: the GPU's name, or the CPU's model, its vector instructions as
    torch uses them (AVX2 or AVX512: the same model name hides hosts whose network passes differ by a third) and
    the thread count."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            model = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"cpu ({model}, {torch.backends.cpu.get_cpu_capability()}, {threads} threads)"


def _summary(values: np.ndarray) -> dict[str, float]:
    return {"mean": float(values.mean()), "p50": float(np.percentile(values, 50)),
            "p95": float(np.percentile(values, 95)), "max": float(values.max())}


def format_benchmark(result: dict) -> str:
    """A terminal table of a benchmark result."""
    lines = [f"{result['model']} ({result['config']}, {result['input_size']} px, "
             f"{'tracking: 1 pass' if result['tracking'] else 'localize + crop: 2 passes'}) on {result['device']}, "
             f"backend {result['backend']}, {'fitted' if result['fit'] else 'feed-forward'}"
             f"{' by parts' if result['fit'] and result.get('parts') else ''}"
             f"{', static camera' if result.get('static_camera') else ''}"
             f"{', localizer at ' + str(result['localize_size']) + ' px' if result.get('localize_size') else ''}",
             f"{'stage':<18}{'mean':>8}{'p50':>8}{'p95':>8}{'max':>8}  ms"]
    for stage, s in result["stages_ms"].items():
        lines.append(f"{stage:<18}{s['mean']:8.1f}{s['p50']:8.1f}{s['p95']:8.1f}{s['max']:8.1f}")
    lines.append(f"{result['fps']:.1f} frames/s; {result['gflops']:.2f} GFLOPs a pass; {result['params_m']:.1f} M "
                 f"parameters; peak RSS {result['peak_rss_mb']:.0f} MB")
    return "\n".join(lines)
