"""A short soak (scripts/soak_node.py) of the real graph: replay looping a generated folder -> estimator (small
test model) -> live evaluation, each its own process. Every process stays alive, the estimator answers, the
samples of RSS, descriptors and threads are taken, and the table and the plot are written. Growth and latency
goals are figures of the 10-minute run (README, Reliability), not assertions here."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_a_short_soak_keeps_every_process_alive_and_reports(small_model_card, tmp_path):
    out = tmp_path / "soak.json"
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "soak_node.py"), "--minutes", "0.4", "--rate", "10",
                          "--frames", "3", "--model", str(small_model_card), "--backend", "torch", "--threads", "1",
                          "--min-confidence", "0.0", "--out", str(tmp_path / "work"), "--plot", str(tmp_path / "soak.png"),
                          "--json", str(out)], capture_output=True, text=True, cwd=ROOT, timeout=600,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    result = json.loads(out.read_text())
    summary = result["summary"]
    assert summary["alive"] and all(code is None for code in result["exit_codes_before_stop"].values())
    assert len(result["samples"]) >= 2
    assert summary["answered"] > 0 and summary["frames_processed"] > 0 and summary["errors"] == 0
    assert summary["frames_processed"] + summary["frames_dropped"] <= summary["frames_received"]
    assert all(s["estimator"]["fds"] > 0 and s["estimator"]["threads"] > 0 for s in result["samples"])
    assert (tmp_path / "soak.png").stat().st_size > 10_000
    assert "| minute | answered | latency p50 ms |" in run.stdout and "RSS growth" in run.stdout
