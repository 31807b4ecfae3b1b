"""Soak test of the node graph: the DREAM replay node loops a generated folder at `--rate` Hz into the estimator
node (shipped weights, ONNX Runtime) and the live evaluation node, each its own process over the shared-memory
profile, for `--minutes`. Every 10 s it samples each process's RSS, open file descriptors and threads; every
minute it reports the end-to-end latency (image arrival -> joint_states arrival, both seen by this process) p50 /
p95, frames sent, answered and dropped. Prints a table and writes a PNG (RSS and latency over time).

    python scripts/soak_node.py --minutes 10 --rate 30 [--plot docs/soak.png] [--json runs/soak/soak.json]

Goals (issue "reliability"): estimator RSS growth from minute 1 to the end < 5 %, no upward latency drift, no
growth of descriptors or threads, no process restarts. The script reports; it does not judge timing.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

SAMPLE_PERIOD_S = 10.0


def process_sample(pid: int) -> dict:
    """RSS (MB), open file descriptors and threads of a live process, from /proc."""
    status = Path(f"/proc/{pid}/status").read_text().splitlines()
    fields = {line.split(":", 1)[0]: line.split(":", 1)[1].split() for line in status if ":" in line}
    return {"rss_mb": int(fields["VmRSS"][0]) / 1024, "threads": int(fields["Threads"][0]),
            "fds": len(list(Path(f"/proc/{pid}/fd").iterdir()))}


def run_soak(model: str, robot: str, minutes: float, rate: float, frames: int, out: Path, threads: int,
             estimator_params: dict | None = None) -> dict:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image, JointState

    from holo_pose_ros.bags import ESTIMATOR_NS
    from holo_pose_ros.data.generator import generate
    from holo_pose_ros.nodes.processes import private_graph_env, start_node, stop_nodes
    from msg_adapters import stamp_ns

    data, logs = out / "data", out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    if not (data / f"{frames - 1:06d}.json").exists():
        generate(robot, frames, data, seed=5, progress=True)
    env = private_graph_env()
    processes = {
        "estimator": start_node("estimator_node", {"robot": robot, "model": model, "threads": threads,
                                                   **(estimator_params or {})}, logs / "estimator.log", env),
        "evaluation": start_node("evaluation_node", {"robot": robot, "report_path": "", "idle_timeout_s": 0.0,
                                                     "exit_when_done": False}, logs / "evaluation.log", env),
    }
    rclpy.init()
    node = rclpy.create_node("holo_pose_soak")
    image_arrival: dict[int, float] = {}
    latencies: list[tuple[float, float]] = []   # (time since start s, latency ms)
    diagnostics: dict[str, str] = {}
    sensor = QoSProfile(reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_LAST, depth=5)

    def on_image(msg: Image) -> None:
        image_arrival[stamp_ns(msg.header.stamp)] = time.monotonic()

    def on_joints(msg: JointState) -> None:
        sent = image_arrival.pop(stamp_ns(msg.header.stamp), None)
        if sent is not None:
            latencies.append((time.monotonic() - start, (time.monotonic() - sent) * 1e3))

    def on_diagnostics(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name.split(":")[0].endswith("holo_pose_estimator"):
                diagnostics.update({kv.key: kv.value for kv in status.values})

    node.create_subscription(Image, "/image", on_image, sensor)
    node.create_subscription(JointState, f"{ESTIMATOR_NS}/joint_states", on_joints, 10)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
    deadline = time.monotonic() + 120
    while node.count_publishers(f"{ESTIMATOR_NS}/joint_states") == 0 and time.monotonic() < deadline \
            and processes["estimator"].poll() is None:
        rclpy.spin_once(node, timeout_sec=0.1)
    processes["replay"] = start_node("dream_replay_node", {"folder": str(data.resolve()), "robot": robot,
                                                          "rate": rate, "loop": True}, logs / "replay.log", env)
    pids = {name: p.pid for name, p in processes.items()}
    print(f"soak: {minutes:g} min at {rate:g} Hz; pids {pids}; logs in {logs}", flush=True)
    start = time.monotonic()
    samples, next_sample, alive = [], 0.0, True
    try:
        while (now := time.monotonic() - start) < minutes * 60:
            rclpy.spin_once(node, timeout_sec=0.05)
            if any(p.poll() is not None for p in processes.values()):
                alive = False
                break
            if now >= next_sample:
                samples.append({"t_s": now, **{name: process_sample(pid) for name, pid in pids.items()},
                                "frames_received": int(diagnostics.get("frames_received", 0)),
                                "frames_processed": int(diagnostics.get("frames_processed", 0)),
                                "frames_dropped": int(diagnostics.get("frames_dropped", 0)),
                                "errors": sum(int(v) for k, v in diagnostics.items() if k.startswith("errors_"))})
                next_sample += SAMPLE_PERIOD_S
            cutoff = time.monotonic() - 5.0  # images never answered (dropped by the newest-frame policy)
            for stamp in [s for s, t in image_arrival.items() if t < cutoff]:
                del image_arrival[stamp]
    finally:
        exit_codes = {name: p.poll() for name, p in processes.items()}
        node.destroy_node()
        rclpy.try_shutdown()
        stop_nodes(processes)
    return {"minutes": minutes, "rate_hz": rate, "model": model, "alive": alive, "exit_codes_before_stop": exit_codes,
            "samples": samples, "latencies": latencies}


def summarize(result: dict) -> dict:
    """Per-minute latency and throughput, and the growth figures of the estimator process."""
    samples, lat = result["samples"], np.array(result["latencies"]).reshape(-1, 2)
    minutes = []
    n_min = int(np.ceil(result["minutes"]))
    by_time = {s["t_s"]: s for s in samples}
    times = np.array(sorted(by_time))
    for m in range(n_min):
        sel = lat[(lat[:, 0] >= 60 * m) & (lat[:, 0] < 60 * (m + 1)), 1]
        inside = [by_time[t] for t in times if 60 * m <= t < 60 * (m + 1)] or [by_time[times[-1]]]
        last = inside[-1]
        minutes.append({"minute": m + 1, "answered": int(sel.size),
                        "p50_ms": float(np.percentile(sel, 50)) if sel.size else None,
                        "p95_ms": float(np.percentile(sel, 95)) if sel.size else None,
                        "received": last["frames_received"], "dropped": last["frames_dropped"],
                        "rss_mb": last["estimator"]["rss_mb"], "fds": last["estimator"]["fds"],
                        "threads": last["estimator"]["threads"], "errors": last["errors"]})
    after_1 = [s for s in samples if s["t_s"] >= 60] or samples
    rss0, rss1 = after_1[0]["estimator"]["rss_mb"], samples[-1]["estimator"]["rss_mb"]
    return {"alive": result["alive"], "minutes": minutes,
            "estimator_rss_growth_pct": 100 * (rss1 - rss0) / rss0,
            "fds": (samples[0]["estimator"]["fds"], samples[-1]["estimator"]["fds"]),
            "threads": (samples[0]["estimator"]["threads"], samples[-1]["estimator"]["threads"]),
            "peak_rss_mb": {name: max(s[name]["rss_mb"] for s in samples) for name in ("estimator", "evaluation", "replay")},
            "frames_received": samples[-1]["frames_received"], "frames_processed": samples[-1]["frames_processed"],
            "frames_dropped": samples[-1]["frames_dropped"], "answered": int(lat.shape[0]),
            "errors": samples[-1]["errors"]}


def format_summary(result: dict, summary: dict) -> str:
    f = lambda v, d=1: "-" if v is None else f"{v:.{d}f}"  # noqa: E731
    lines = [f"soak: {result['minutes']:g} min at {result['rate_hz']:g} Hz, model {result['model']}; "
             f"all processes alive: {'yes' if summary['alive'] else 'NO'}",
             "| minute | answered | latency p50 ms | latency p95 ms | frames received | dropped | estimator RSS MB "
             "| fds | threads | errors |", "|---|---|---|---|---|---|---|---|---|---|"]
    for m in summary["minutes"]:
        lines.append(f"| {m['minute']} | {m['answered']} | {f(m['p50_ms'])} | {f(m['p95_ms'])} | {m['received']} | "
                     f"{m['dropped']} | {f(m['rss_mb'])} | {m['fds']} | {m['threads']} | {m['errors']} |")
    lines.append(f"estimator RSS growth from minute 1 to the end: {summary['estimator_rss_growth_pct']:+.2f} % "
                 f"(goal < 5 %); fds {summary['fds'][0]} -> {summary['fds'][1]}, threads {summary['threads'][0]} -> "
                 f"{summary['threads'][1]}; peak RSS MB " + ", ".join(f"{k} {v:.0f}" for k, v in summary["peak_rss_mb"].items()))
    lines.append(f"frames: {summary['frames_received']} received by the estimator, {summary['frames_processed']} "
                 f"estimated, {summary['frames_dropped']} dropped as stale (newest-frame policy), "
                 f"{summary['answered']} answers timed end to end; errors {summary['errors']}")
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    samples, lat = result["samples"], np.array(result["latencies"]).reshape(-1, 2)
    fig, (a, b) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    t = np.array([s["t_s"] for s in samples]) / 60
    for name in ("estimator", "evaluation", "replay"):
        a.plot(t, [s[name]["rss_mb"] for s in samples], marker=".", label=name)
    a.set_ylabel("RSS (MB)")
    a.legend()
    a.set_title(f"soak: {result['minutes']:g} min at {result['rate_hz']:g} Hz ({result['model']})")
    if lat.size:
        edges = np.arange(0, lat[:, 0].max() + 10, 10.0)
        mids, p50, p95 = [], [], []
        for lo in edges:
            sel = lat[(lat[:, 0] >= lo) & (lat[:, 0] < lo + 10), 1]
            if sel.size:
                mids.append((lo + 5) / 60)
                p50.append(np.percentile(sel, 50))
                p95.append(np.percentile(sel, 95))
        b.plot(mids, p50, label="p50")
        b.plot(mids, p95, label="p95")
        b.legend()
    b.set_ylabel("latency, image -> joint_states (ms)")
    b.set_xlabel("minutes")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--rate", type=float, default=30.0, help="replay rate, frames/s")
    parser.add_argument("--model", default="panda")
    parser.add_argument("--robot", default="panda")
    parser.add_argument("--frames", type=int, default=30, help="frames of the looped folder")
    parser.add_argument("--threads", type=int, default=0, help="the estimator's network threads (0: default)")
    parser.add_argument("--backend", default="onnxruntime", choices=["onnxruntime", "torch"])
    parser.add_argument("--min-confidence", type=float, default=None, help="the estimator's (default: its YAML's)")
    parser.add_argument("--out", default="runs/soak", help="work folder (data, logs)")
    parser.add_argument("--plot", default="docs/soak.png", help="PNG of RSS and latency over time")
    parser.add_argument("--json", default=None, help="also write samples and summary as JSON")
    args = parser.parse_args(argv)
    params = {"backend": args.backend, **({} if args.min_confidence is None else {"min_confidence": args.min_confidence})}
    result = run_soak(args.model, args.robot, args.minutes, args.rate, args.frames, Path(args.out), args.threads,
                      params)
    if not result["samples"]:
        print("soak: no sample taken (a process stopped at once); see the logs", file=sys.stderr)
        return 1
    summary = summarize(result)
    print(format_summary(result, summary))
    plot(result, Path(args.plot))
    print(f"plot: {args.plot}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"summary": summary, **result}, indent=1))
    return 0 if summary["alive"] else 1


if __name__ == "__main__":
    sys.exit(main())
