"""scripts/joint_observability.py on the real Kuka description: the bare flange's joint 7 is flagged weak and half-turn
symmetric, the shoulder is not; with --data it scores a model's estimates on real generated frames, joint by joint."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from holo_pose_ros.data.generator import generate

ROOT = Path(__file__).resolve().parent.parent


def _rows(text: str) -> dict[str, list[str]]:
    """Markdown table rows of the output, by their first cell."""
    return {cells[0]: cells[1:] for line in text.splitlines() if line.startswith("| ")
            for cells in [[c.strip() for c in line.strip("|").split("|")]]}


def test_the_flange_is_flagged_and_a_model_is_scored(tmp_path):
    generate("kuka", 3, tmp_path / "val", seed=778, workers=1, progress=False)
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "joint_observability.py"), "--robot", "kuka",
                          "--views", "8", "--surface-points", "1000", "--data", str(tmp_path / "val")],
                         capture_output=True, text=True, cwd=ROOT, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert run.returncode == 0, run.stderr
    predicted, _, measured = run.stdout.partition("frames found")
    assert measured, run.stdout
    rows = _rows(predicted)
    flange, shoulder = rows["iiwa7_joint_7"], rows["iiwa7_joint_2"]
    assert "weak" in flange[3] and "half-turn symmetric" in flange[3]
    assert flange[4] == "180" and shoulder[4] == "-"             # the robot YAML declares what the geometry says
    assert shoulder[3] == "ok" and float(shoulder[1]) > 4 * float(flange[1]) and float(shoulder[2]) > 10 * float(flange[2])
    assert int(flange[0]) < int(shoulder[0])                     # fewer fit keypoints ride on the flange
    scored = {name: r for name, r in _rows(measured).items() if name.startswith("iiwa7_joint_")}
    assert len(scored) == 7
    for mean, median, over, half in scored.values():
        assert 0.0 <= float(half) <= 90.0 and 0.0 <= float(median) and 0.0 <= float(over.rstrip(" %")) <= 100.0
