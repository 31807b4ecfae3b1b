#!/usr/bin/env python3
"""Fuzz the estimator node through a real graph (holo_pose_ros/nodes/fuzz.py): the node runs as its own process
(the shared-memory profile, a private domain) and this process sends a deterministic stream of Image and
CameraInfo messages, valid frames mixed with every kind of wrongness (each supported and unsupported encoding,
step and data sizes that disagree, empty and huge images, is_bigendian, random bytes and undecodable payloads;
CameraInfo with NaN / inf / zero / negative focal lengths, the size of another camera, changing frame ids, stamps
going backwards, equal or far in the past and future). Every valid frame is waited for; every other message is
followed by `--gap-ms`, so that nothing can be lost unnoticed. Prints messages by kind, the node's /diagnostics
counters against what the stream must produce, whether the node is alive, valid frames answered, log lines per
second and the node's peak RSS.

    OMP_NUM_THREADS=1 nice -n 19 python scripts/fuzz_node.py --messages 10000 --seed 1

`--model small` (the default) is the small untrained network of the tests (test/small_model.py, built in a
temporary folder): the machinery is what is fuzzed, not the model. Not a timed test: it reports.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--messages", type=int, default=10000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--model", default="small", help="'small' (the tests' network), a shipped name or a card")
    parser.add_argument("--backend", default="torch", choices=["torch", "onnxruntime"])
    parser.add_argument("--threads", type=int, default=1, help="the node's network threads")
    parser.add_argument("--gap-ms", type=float, default=50.0, help="pause after each message that is not answered")
    parser.add_argument("--out", type=Path, default=None, help="folder for the node's log and result.json")
    args = parser.parse_args()

    from holo_pose_ros.nodes.fuzz import format_fuzz, run_fuzz

    out = args.out or Path(tempfile.mkdtemp(prefix="holo_pose_fuzz_"))
    out.mkdir(parents=True, exist_ok=True)
    model = args.model
    if model == "small":
        sys.path.insert(0, str(ROOT / "test"))
        from small_model import save_small_model

        model = str(save_small_model(out / "small_model"))
    t0 = time.monotonic()
    result = run_fuzz(model, args.messages, args.seed, out / "estimator.log", backend=args.backend,
                      threads=args.threads, gap_s=args.gap_ms / 1e3,
                      progress=lambda i, n, s: print(f"  {i}/{n} messages, {s:.0f} s", flush=True))
    print(format_fuzz(result))
    print(f"\nwall time {time.monotonic() - t0:.0f} s; node log {out / 'estimator.log'}")
    result["by_kind"] = {k: dict(v) for k, v in result["by_kind"].items()}
    (out / "result.json").write_text(json.dumps(result, indent=1, default=str))
    failed = (not result["alive"] or result["answered"] != result["answers_expected"]
              or result["counted"] != result["expected"])
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
