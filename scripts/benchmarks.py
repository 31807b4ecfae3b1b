"""Regenerate BENCHMARKS.md: every shipped model end to end (torch and onnxruntime; localize + crop and tracking),
its node-level latency through a real ROS 2 graph, its accuracy on the held-out generated test sets with each
backend, the network-only timings of the `lite` candidates, and the paper's figures beside ours. Everything comes
from config/benchmarks.yaml and the real commands (`holo-pose benchmark`, `holo-pose evaluate`), run one process
each so that memory and thread state do not leak between rows.

    python scripts/benchmarks.py [--device cpu|cuda] [--out BENCHMARKS.md] [--skip-candidates]
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime
import torch
import yaml
from tqdm import tqdm

from holo_pose_ros import __version__
from holo_pose_ros.benchmark import device_name, network_gflops
from holo_pose_ros.data.generator import generate
from holo_pose_ros.model.network import HolisticNet, example_inputs, load_model_config
from holo_pose_ros.model.onnx_runtime import OnnxNetwork, export_onnx
from holo_pose_ros.resources import config_dir, weights_dir
from holo_pose_ros.robots.kinematics import RobotModel

ROOT = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-m", "holo_pose_ros.cli"]


def run_cli(args: list[str]) -> None:
    result = subprocess.run(CLI + args, capture_output=True, text=True)
    if result.returncode:
        raise RuntimeError(f"holo-pose {' '.join(args)} failed:\n{result.stdout[-2000:]}\n{result.stderr[-3000:]}")


def test_set(robot: str, look: str, spec: dict) -> Path:
    """The held-out folder of `robot` and `look` (data/<robot>_test_<look>_seed<seed>), generated once."""
    folder = ROOT / "data" / f"{robot}_test_{look}_seed{spec['seed']}"
    if not (folder / f"{spec['frames'] - 1:06d}.json").exists():
        generate(robot, spec["frames"], folder, seed=spec["seed"], config=spec["config"], progress=False)
    return folder


def end_to_end(model: str, data: Path, backend: str, tracking: bool, device: str, frames: int, node: dict | None,
               work: Path) -> dict:
    """`holo-pose benchmark` (with `--node` when `node` is given) in its own process; its JSON."""
    out = work / f"{model}-{backend}-{'track' if tracking else 'loc'}.json"
    args = ["benchmark", "--model", model, "--data", str(data), "--frames", str(frames), "--device", device,
            "--backend", backend, "--json", str(out)] + (["--tracking"] if tracking else [])
    if node:
        args += ["--node", "--node-rate", str(node["rate_hz"])]
    run_cli(args)
    return json.loads(out.read_text())


def accuracy(model: str, data: Path, backend: str, device: str, work: Path, tracking: bool = False) -> dict:
    """`holo-pose evaluate` of one folder (`tracking`: in order, each frame cropped from the last); its report."""
    out = work / f"{model}-{backend}-{data.name}-{'track' if tracking else 'loc'}-report.json"
    run_cli(["evaluate", "--model", model, "--data", str(data), "--backend", backend, "--device", device, "--out",
             str(out), "--quiet"] + (["--tracking"] if tracking else []))
    return json.loads(out.read_text())


def candidate(entry: dict, runs: int, work: Path) -> dict:
    """Network-only latency (median of `runs` batch-1 passes), GFLOPs and parameters of one configuration (Panda
    heads; pretrained weights are irrelevant to speed, so none are loaded)."""
    fields = {k: v for k, v in entry.items() if k != "label"}
    cfg = load_model_config({"base": "lite", **fields, "pretrained": False, "depth_pretrained": False})
    net = HolisticNet(cfg, RobotModel("panda")).eval()
    x, K = example_inputs(cfg.input_size)
    timings = {}
    with torch.inference_mode():
        timings["torch"] = _median_ms(lambda: net(x, K), runs)
    session = OnnxNetwork(export_onnx(net, work / "candidate.onnx"))
    timings["onnxruntime"] = _median_ms(lambda: session(x, K), runs)
    return {"label": entry["label"], "backbone": cfg.backbone, "depth_backbone": cfg.depth_backbone,
            "input_size": cfg.input_size, "heatmap": f"{cfg.heatmap_size}² × {cfg.depth_bins}",
            "gflops": network_gflops(net),
            "params_m": sum(p.numel() for p in net.parameters()) / 1e6, "ms": timings}


def _median_ms(fn, runs: int, warmup: int = 5) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def plot(rows: list[dict], candidates: list[dict], path: Path) -> None:
    """Left: end-to-end latency (p50 bar, p95 tick) of every shipped configuration against the 33 ms of a 30 Hz
    camera. Right: network-only latency of the candidates against their GFLOPs, per backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2 if candidates else 1, figsize=(13 if candidates else 7, 4.5), squeeze=False)
    ax = axes[0][0]
    labels = [f"{r['model']} {r['bench']['backend']}\n{'tracking' if r['bench']['tracking'] else 'loc+crop'}" for r in rows]
    p50 = [r["bench"]["latency_ms_p50"] for r in rows]
    p95 = [r["bench"]["latency_ms_p95"] for r in rows]
    for backend, color in (("torch", "tab:blue"), ("onnxruntime", "tab:orange")):
        index = [i for i, r in enumerate(rows) if r["bench"]["backend"] == backend]
        ax.bar(index, [p50[i] for i in index], color=color, label=f"p50, {backend}")
    ax.scatter(range(len(rows)), p95, marker="_", s=400, color="black", label="p95", zorder=3)
    ax.axhline(1e3 / 30, color="gray", linestyle="--", label="30 Hz camera (33 ms)")
    ax.set_xticks(range(len(rows)), labels, fontsize=7, rotation=60, ha="right")
    ax.set_ylabel("end-to-end latency, ms")
    ax.set_title("Shipped models: Image in -> all messages out")
    ax.legend(fontsize=8)
    if candidates:
        ax = axes[0][1]
        for backend, marker in (("torch", "o"), ("onnxruntime", "s")):
            ax.scatter([c["gflops"] for c in candidates], [c["ms"][backend] for c in candidates], marker=marker,
                       label=backend)
        for c in candidates:
            ax.annotate(c["label"].split(" (")[0], (c["gflops"], c["ms"]["onnxruntime"]), fontsize=6,
                        xytext=(3, 3), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("GFLOPs per pass")
        ax.set_ylabel("network latency, ms (batch 1)")
        ax.set_title("lite candidates")
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_page(path: Path, cfg: dict, rows: list[dict], candidates: list[dict], device: str, minutes: float) -> None:
    looks = [*cfg["test_sets"], "video"]
    lines = [
        "# Benchmarks",
        "",
        f"Regenerated by `python scripts/benchmarks.py{' --device ' + device if device != 'cpu' else ''}` from "
        f"`config/benchmarks.yaml` ({minutes:.0f} min); do not edit by hand. holo_pose_ros {__version__}, torch "
        f"{torch.__version__}, onnxruntime {onnxruntime.__version__}, {datetime.date.today().isoformat()}.",
        f"Device: **{rows[0]['bench']['device'] if rows else device}**.",
        "",
        "![latency of the shipped configurations and of the lite candidates](docs/benchmarks.png)",
        "",
        "## Shipped models, end to end",
        "",
        "One `sensor_msgs/Image` in, every output message built: image conversion, localization (the whole-image "
        "pass), crop and network (the crop pass), the heads' forward kinematics, the lifter and the kinematic fit when the model's card chose the fitted estimate "
        "(*estimate*), messages (`holo-pose benchmark`). *Localize + crop* runs two network passes a frame "
        "(the whole image, then the robot's box); *tracking* one (the previous frame's box), on a generated video "
        f"played in order (seed {cfg['tracking_video']['seed']}, config/generate/video.yaml). *Node* is the same estimator as a ROS 2 node in its own process, timed from "
        f"`publish()` of the Image to the arrival of its JointState, with a {cfg['node']['rate_hz']} Hz camera "
        "(the node drops frames it cannot take: *answered* is its output rate). AUC (ADD, 0-100 mm) on the "
        "held-out generated sets, seeds "
        + " / ".join(f"{s['seed']} ({look})" for look, s in cfg["test_sets"].items())
        + ", measured with the row's backend; tracking rows: the video's, tracked (*AUC video*).",
        "",
        "| model | backend | mode | estimate | FPS | p50 ms | p95 ms | node: answered FPS | node p50 / p95 ms | "
        "GFLOPs / pass | params (M) | AUC " + " | AUC ".join(looks) + " |",
        "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|" + "---:|" * len(looks),
    ]
    for r in rows:
        b, n = r["bench"], r["bench"].get("node")
        node_cells = (f"{n['fps']:.1f} ({n['dropped']}/{n['sent']} dropped)", f"{n['latency_ms_p50']:.0f} / "
                      f"{n['latency_ms_p95']:.0f}") if n else ("—", "—")
        aucs = [f"{r['auc'][look]['add_auc']:.1f}" if look in r["auc"] else "—" for look in looks]
        lines.append(f"| {r['model']} ({b['config']}, {b['input_size']} px) | {b['backend']} | "
                     f"{'tracking' if b['tracking'] else 'localize + crop'} | "
                     f"{'fitted' if b.get('fit') else 'feed-forward'} | {b['fps']:.1f} | "
                     f"{b['latency_ms_p50']:.0f} | {b['latency_ms_p95']:.0f} | {node_cells[0]} | {node_cells[1]} | "
                     f"{b['gflops']:.2f} | {b['params_m']:.1f} | " + " | ".join(aucs) + " |")
    lines += ["", "Per-stage medians (ms) of the same runs:", "",
              "| model | backend | mode | image | localize | crop | network | kinematics | lifter | fit | in-view refit | messages |",
              "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        b = r["bench"]
        s = {k: v["p50"] for k, v in b["stages_ms"].items()}
        lines.append(f"| {r['model']} | {b['backend']} | {'tracking' if b['tracking'] else 'localize + crop'} | "
                     f"{s['image_conversion']:.1f} | {s['localize']:.1f} | {s['crop']:.1f} | {s['network']:.1f} | "
                     f"{s['kinematics']:.1f} | {s.get('lifter', 0.0):.1f} | {s.get('fit', 0.0):.1f} | "
                     f"{s.get('in_view', 0.0):.1f} | {s['messages']:.1f} |")
    if candidates:
        lines += ["", "## Choosing `lite`: network-only latency of the candidates", "",
                  "Batch 1, one network pass, median of "
                  f"{cfg['candidate_runs']} after 5 warm-up passes; Panda heads. Accuracy is compared only where a candidate "
                  "was trained: 224 against 192 px (docs/campaign.md, Panda's thirteenth run).", "",
                  "| candidate | backbone | DepthNet | input px | heatmap | GFLOPs | params (M) | torch ms | ONNX Runtime ms |",
                  "|---|---|---|---:|---|---:|---:|---:|---:|"]
        for c in candidates:
            lines.append(f"| {c['label']} | {c['backbone']} | {c['depth_backbone']} | {c['input_size']} | {c['heatmap']} | "
                         f"{c['gflops']:.2f} | {c['params_m']:.1f} | {c['ms']['torch']:.1f} | {c['ms']['onnxruntime']:.1f} |")
    lines += ["", "## The paper's figures, for reference", "",
              "From the paper's computation-efficiency table (Panda 3CAM-AK, batch 1). Its timings exclude data "
              "loading, cropping and d_c, and its crops come from ground-truth keypoints; ours are end to end and find "
              "the robot themselves.", "",
              "| method | device | FPS | ms | GFLOPs | AUC |", "|---|---|---:|---:|---:|---|"]
    for p in cfg["paper"]:
        lines.append(f"| {p['method']} | {p['device']} | {p['fps']} | {p['ms']} | {p['gflops']} | {p['auc']} |")
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default=str(config_dir() / "benchmarks.yaml"))
    parser.add_argument("--device", default="cpu", help="cpu or cuda (the node figure is measured on the CPU only)")
    parser.add_argument("--out", default=str(ROOT / "BENCHMARKS.md"))
    parser.add_argument("--skip-candidates", action="store_true", help="only the shipped models")
    args = parser.parse_args(argv)
    cfg = yaml.safe_load(Path(args.config).read_text())
    start = time.monotonic()
    work = Path(tempfile.mkdtemp(prefix="holo_pose_benchmarks_"))
    models = [m for m in cfg["models"] if (weights_dir() / f"{m}.yaml").is_file()]
    jobs = [(m, b, t) for m in models for b in cfg["backends"] for t in (False, True)]
    rows = []
    for model, backend, tracking in tqdm(jobs, desc="shipped models", unit="run"):
        robot = yaml.safe_load((weights_dir() / f"{model}.yaml").read_text())["robot"]
        folders = {look: test_set(robot, look, spec) for look, spec in cfg["test_sets"].items()}
        video = test_set(robot, "video", cfg["tracking_video"])  # tracking plays a video, in order
        node = cfg["node"] if args.device == "cpu" and backend == "onnxruntime" else None
        bench = end_to_end(model, video if tracking else next(iter(folders.values())), backend, tracking,
                           args.device, cfg["node"]["frames"] if node else cfg["frames"], node, work)
        auc = {"video": accuracy(model, video, backend, args.device, work, tracking=True)} if tracking else \
            {look: accuracy(model, folder, backend, args.device, work) for look, folder in folders.items()}
        rows.append({"model": model, "bench": bench, "auc": auc})
    candidates = [] if args.skip_candidates else [
        candidate(c, cfg["candidate_runs"], work) for c in tqdm(cfg["candidates"], desc="lite candidates", unit="net")]
    (work / "all.json").write_text(json.dumps({"rows": rows, "candidates": candidates}, indent=1))
    plot(rows, candidates, ROOT / "docs" / "benchmarks.png")
    write_page(Path(args.out), cfg, rows, candidates, device_name(torch.device(args.device), torch.get_num_threads())
               if args.device != "cpu" else "cpu", (time.monotonic() - start) / 60)
    print(f"wrote {args.out} (raw figures: {work / 'all.json'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
