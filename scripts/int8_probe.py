"""Whether static int8 quantization of the ONNX graph pays (the speed issue's item 3): calibrate QDQ int8 weights
(per channel) and activations on the deployed estimator's own network inputs (both passes) of generated validation
frames of every look, then score the quantized graph against the float one on other frames of the same folders:
how far the keypoints move (image pixels, median and p90), the fitted AUC of both, and the network's latency
(batch 1, median of 50; quote it only from a quiet CPU).

    python scripts/int8_probe.py --model panda --data data/panda_val_1012 data/panda_val_unseen_1013 \
        [--calibration-frames 24] [--frames 60] [--ops Conv]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.evaluation.run import evaluate_folder
from holo_pose_ros.model.onnx_runtime import OnnxNetwork, cached_export, session


class Recorder:
    """Stands in for the estimator's network and keeps every input it is given (the calibration feeds)."""

    def __init__(self, network):
        self.network, self.feeds = network, []

    def __call__(self, image, K_crop):
        self.feeds.append({"image": image.numpy().copy(), "K_crop": K_crop.numpy().copy()})
        return self.network(image, K_crop)


def quantize(float_path: Path, feeds: list[dict], ops: list[str], out: Path) -> Path:
    """Static QDQ int8 (per-channel weights, uint8 activations) of `ops`, calibrated on `feeds`."""
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Feeds(CalibrationDataReader):
        def __init__(self):
            self.it = iter(feeds)

        def get_next(self):
            return next(self.it, None)

    pre = out.with_name("pre.onnx")
    quant_pre_process(str(float_path), str(pre), skip_symbolic_shape=True)
    quantize_static(str(pre), str(out), Feeds(), quant_format=QuantFormat.QDQ, per_channel=True,
                    op_types_to_quantize=ops, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8)
    return out


def network_ms(path: Path, feed: dict, runs: int = 50) -> float:
    """Median latency of one pass, ms (after 5 warm-up passes)."""
    s = session(path)
    for _ in range(5):
        s.run(None, feed)
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        s.run(None, feed)
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="panda")
    parser.add_argument("--data", nargs="+", required=True, help="generated validation folders (never a test set)")
    parser.add_argument("--calibration-frames", type=int, default=24, help="first frames of each folder: calibration")
    parser.add_argument("--frames", type=int, default=60, help="the next frames of each folder: the comparison")
    parser.add_argument("--ops", nargs="+", default=["Conv"], help="ONNX op types quantized")
    args = parser.parse_args(argv)

    estimator = Estimator.from_model(args.model, backend="onnxruntime")
    float_network = estimator.network
    recorder = Recorder(float_network)
    estimator.network = recorder
    readers = [DreamReader(folder, estimator.robot.name) for folder in args.data]
    for reader in readers:
        for frame, image in reader.images(list(reader)[:args.calibration_frames]):
            estimator.reset()
            estimator.estimate(image, frame.K)
    work = Path(tempfile.mkdtemp(prefix="holo_pose_int8_"))
    float_path = cached_export(estimator.net, args.model)
    int8_path = quantize(float_path, recorder.feeds, args.ops, work / "int8.onnx")
    int8_network = OnnxNetwork(int8_path)
    print(f"calibrated on {len(recorder.feeds)} network inputs; ops {args.ops}; {int8_path}")

    print(f"network ms (batch 1): float {network_ms(float_path, recorder.feeds[0]):.1f}, "
          f"int8 {network_ms(int8_path, recorder.feeds[0]):.1f}")
    for reader in readers:
        frames = list(reader)[args.calibration_frames:args.calibration_frames + args.frames]
        recorder.feeds, moved = [], []
        estimator.network = recorder  # the float pipeline's own crops; both graphs see the same crop pass
        for frame, image in reader.images(frames):
            estimator.reset()
            if estimator.detect(image, frame.K) is None:
                recorder.feeds.clear()
                continue
            feed = recorder.feeds[-1]  # the crop pass
            a, b = float_network.session.run(None, feed), int8_network.session.run(None, feed)
            named_a, named_b = dict(zip(float_network.names, a)), dict(zip(int8_network.names, b))
            px = frame.K[0][0] / feed["K_crop"][0, 0, 0]  # image pixels per crop pixel
            confident = (named_a["fit_confidence"][0] >= 0.3) & (named_b["fit_confidence"][0] >= 0.3)
            moved.append(px * np.linalg.norm(named_a["fit_uv"][0] - named_b["fit_uv"][0], axis=1)[confident])
            recorder.feeds.clear()
        moved = np.concatenate(moved) if moved else np.full(1, np.nan)
        aucs = []
        for network in (float_network, int8_network):
            estimator.network = network
            report = evaluate_folder(estimator, _Subset(reader, frames), progress=False, depth_diagnostics=False)[0]
            aucs.append(report["add_auc"])
        print(f"{reader.folder}: {len(frames)} frames; fit keypoints moved median {np.median(moved):.2f} / p90 "
              f"{np.percentile(moved, 90):.2f} px (same crop, confident); fitted AUC float {aucs[0]:.1f}, "
              f"int8 {aucs[1]:.1f}")
    return 0


class _Subset:
    """A DreamReader restricted to some of its frames (evaluate_folder reads `list(reader)` and `images`)."""

    def __init__(self, reader: DreamReader, frames: list):
        self.reader, self.frames = reader, frames

    def __iter__(self):
        return iter(self.frames)

    def __getattr__(self, name: str):
        return getattr(self.reader, name)


if __name__ == "__main__":
    sys.exit(main())
