"""scripts/fit_sweep.py on a few generated frames with the shipped Panda model: one table row per variant of a
sweep file, each with its numbers, the fit settings of each variant really differ in the result, and a variant
whose evidence is the true 2D (or depth) fits the true pose (or depth)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import yaml

from holo_pose_ros.data.generator import generate

ROOT = Path(__file__).resolve().parent.parent


def test_the_sweep_prints_a_row_per_variant(tmp_path):
    generate("panda", 3, tmp_path / "val", seed=777, workers=1, progress=False)
    variants = {"variants": [
        {"name": "no prior", "weight_power": 1, "depth_prior": False, "fit": {"iterations": 3}},
        {"name": "strong prior", "weight_power": 2, "depth_prior": True, "fit": {"depth_prior_weight": 1.0e4}},
        {"name": "true 2D", "weight_power": 2, "depth_prior": False, "fit": {}, "evidence": {"keypoints": "truth"}},
        {"name": "true depth", "weight_power": 2, "depth_prior": True, "fit": {"depth_prior_weight": 1.0e4},
         "evidence": {"depth": "truth"}}]}
    (tmp_path / "v.yaml").write_text(yaml.safe_dump(variants))
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "fit_sweep.py"), "--data", str(tmp_path / "val"),
                          "--variants", str(tmp_path / "v.yaml")], capture_output=True, text=True, cwd=ROOT,
                         timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    rows = [line for line in run.stdout.splitlines() if line.startswith(("| no prior", "| strong", "| true 2D", "| true depth"))]
    assert len(rows) == 4
    cells = [[c.strip() for c in row.strip("|").split("|")] for row in rows]
    assert all(len(c) == 8 for c in cells)  # the last: the truncated frames alone
    assert cells[0][6] == cells[1][6]            # the same detections: the feed-forward AUC is the same
    assert cells[0][2] != cells[1][2]            # the fits differ
    median_add_mm = [float(c[2].split("/")[0]) for c in cells]
    assert median_add_mm[2] < 10.0 and median_add_mm[2] < median_add_mm[0]  # the truth's 2D: the true pose
    depth_error_mm = [float(c[4].split(",")[1]) for c in cells]           # median |root depth error|
    assert depth_error_mm[3] < 5.0 and depth_error_mm[3] < depth_error_mm[1]  # a strong prior at the true depth
