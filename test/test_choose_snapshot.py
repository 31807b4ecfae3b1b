"""scripts/choose_snapshot.py on a run folder whose two snapshots hold the shipped Panda weights: every snapshot
and the bar (the shipped model) are scored on the same generated frames of two looks, identical weights score
identically, a tie goes to the earliest step and does not count as beating the bar; a run without snapshots is
refused with the reason; by median ADD (`--criterion median_add`) the untrained model ranks below; a second run
scores only the weights it has not scored (a new snapshot, one overwritten
by a run started afresh), the bar included: scores are keyed by the weights' sha256, not by the snapshot's path;
every model is fitted with the shipped card's fit settings."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from holo_pose_ros.data.generator import generate
from holo_pose_ros.model.cards import read_card
from holo_pose_ros.model.weights import load_model, save_model

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = str(ROOT / "scripts" / "choose_snapshot.py")
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def test_snapshots_are_scored_against_the_bar_and_the_best_mean_is_chosen(tmp_path, small_model_card):
    net, robot, _ = load_model("panda")
    for step in (250, 500):
        save_model(net, robot.name, tmp_path / "run" / "snapshots" / f"step_{step:06d}", {"training": {"steps": step}})
    generate("panda", 3, tmp_path / "unseen", seed=4343, workers=1, progress=False, config="unseen")
    generate("panda", 3, tmp_path / "own", seed=4344, workers=1, progress=False, config="randomized")
    run = subprocess.run([sys.executable, SCRIPT, str(tmp_path / "run"), "--baseline", "panda", "--frames", "3",
                          "--validation", str(tmp_path / "own"), "--validation", str(tmp_path / "unseen")],
                         capture_output=True, text=True, cwd=ROOT, timeout=600, env=ENV)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    choice = json.loads((tmp_path / "run" / "snapshots" / "choice.json").read_text())
    assert [r["step"] for r in choice["snapshots"]] == [250, 500]
    for row in choice["snapshots"]:  # the same weights as the bar: the same figures, folder by folder
        assert row["scores"] == choice["baseline"]["scores"]
        assert all(s["n_frames"] == 3 for s in row["scores"].values())
    assert choice["chosen"].endswith("step_000250.yaml") and choice["beats_baseline"] is False
    # scored as deployed: with the shipped card's fit settings (its depth prior's weight), recorded
    assert choice["fit_config"] == read_card("panda")[1]["estimator"]["fit_config"] != {}
    assert (tmp_path / "run" / "snapshots" / "choice.png").stat().st_size > 10_000
    assert "does NOT beat the bar" in run.stdout

    # a third snapshot appears (another model: the small untrained one); run again: only it is scored
    small = load_model(small_model_card)[0]
    save_model(small, "panda", tmp_path / "run" / "snapshots" / "step_000750", {})
    again = subprocess.run([sys.executable, SCRIPT, str(tmp_path / "run"), "--baseline", "panda", "--frames", "3",
                            "--validation", str(tmp_path / "own"), "--validation", str(tmp_path / "unseen"),
                            "--criterion", "median_add"],
                           capture_output=True, text=True, cwd=ROOT, timeout=600, env=ENV)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    after = json.loads((tmp_path / "run" / "snapshots" / "choice.json").read_text())
    assert [r["step"] for r in after["snapshots"]] == [250, 500, 750]
    assert after["snapshots"][:2] == choice["snapshots"] and after["baseline"] == choice["baseline"]
    assert after["snapshots"][2]["mean_add_auc"] < choice["snapshots"][0]["mean_add_auc"]  # untrained: far worse
    assert not after["snapshots"][2]["mean_median_add_mm"] <= choice["snapshots"][0]["mean_median_add_mm"]  # or NaN
    assert after["criterion"].startswith("median ADD") and choice["criterion"].startswith("mean ADD AUC")
    assert after["chosen"].endswith("step_000250.yaml") and after["beats_baseline"] is False
    bar_line = next(line for line in again.stdout.splitlines() if line.startswith("bar panda"))
    assert bar_line.endswith("(scored before)") and "step_000750: " in again.stdout
    assert again.stdout.count("(scored before)") == 3  # the bar, steps 250 and 500; 750 is new

    # a run started afresh overwrites step 500 with other weights (the small model's, scored as step 750): its
    # figures follow its weights, not its path (the unchanged step 250 is not scored again)
    save_model(small, "panda", tmp_path / "run" / "snapshots" / "step_000500", {})
    (tmp_path / "run" / "snapshots" / "step_000750.yaml").unlink()
    (tmp_path / "run" / "snapshots" / "step_000750.safetensors").unlink()
    fresh = subprocess.run([sys.executable, SCRIPT, str(tmp_path / "run"), "--frames", "3",
                            "--validation", str(tmp_path / "own"), "--validation", str(tmp_path / "unseen")],
                           capture_output=True, text=True, cwd=ROOT, timeout=600, env=ENV)
    assert fresh.returncode == 0, fresh.stdout[-3000:] + fresh.stderr[-3000:]
    last = json.loads((tmp_path / "run" / "snapshots" / "choice.json").read_text())
    assert [r["step"] for r in last["snapshots"]] == [250, 500]
    assert last["snapshots"][1]["scores"] == after["snapshots"][2]["scores"]  # the small model's figures
    assert last["snapshots"][1]["sha256"] != choice["snapshots"][1]["sha256"]
    assert last["snapshots"][0] == choice["snapshots"][0] and "step_000250: " in fresh.stdout
    assert next(line for line in fresh.stdout.splitlines() if line.startswith("step_000250")).endswith("(scored before)")


def test_a_run_without_snapshots_is_refused(tmp_path):
    (tmp_path / "run").mkdir()
    run = subprocess.run([sys.executable, SCRIPT, str(tmp_path / "run"), "--validation", str(tmp_path)],
                         capture_output=True, text=True, cwd=ROOT, timeout=300, env=ENV)
    assert run.returncode == 1 and "validation.snapshots: true" in run.stderr
