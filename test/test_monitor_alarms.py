"""scripts/monitor_alarms.py on a copy of the shipped Panda model and generated frames: the monitor's thresholds as
the node makes them, the hand's roll compared modulo half a turn (a fault of half a turn there is invisible, as on
the real robot), a fault of half a turn on the shoulder caught."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

from holo_pose_ros.data.generator import generate
from holo_pose_ros.resources import weights_dir

ROOT = Path(__file__).resolve().parent.parent


def _rows(text: str) -> dict[str, list[str]]:
    """Markdown table rows of the output, by their first cell."""
    return {cells[0]: cells[1:] for line in text.splitlines() if line.startswith("| ")
            for cells in [[c.strip() for c in line.strip("|").split("|")]]}


def _percent(cell: str) -> float:
    value = float(cell.rstrip(" %"))
    assert 0.0 <= value <= 100.0
    return value


def test_the_monitor_on_generated_frames_with_a_symmetric_hand(tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    for suffix in (".yaml", ".safetensors", "_lifter.yaml", "_lifter.safetensors"):
        shutil.copy(weights_dir() / f"panda{suffix}", models / f"panda{suffix}")
    card = yaml.safe_load((models / "panda.yaml").read_text())
    for section in card["test"].values():  # as scripts/ship_model.py now measures it: the hand's error modulo half a turn
        section["joint_error_modulo_symmetry_deg"] = {"panda_joint7": 10.0, "period_deg": {"panda_joint7": 180.0}}
    (models / "panda.yaml").write_text(yaml.safe_dump(card, sort_keys=False))
    generate("panda", 6, tmp_path / "frames", seed=5151, workers=1, progress=False)
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "monitor_alarms.py"), "--model",
                          str(models / "panda.yaml"), "--data", str(tmp_path / "frames"), "--fault-deg", "180"],
                         capture_output=True, text=True, cwd=ROOT, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert run.returncode == 0, run.stderr
    rows = _rows(run.stdout)
    hand, shoulder = rows["panda_joint7"], rows["panda_joint1"]
    assert hand[0] == "30.0 deg" and "modulo the symmetry, modulo 180 deg" in hand[1]  # 3 x 10 deg, from the card
    assert re.fullmatch(r"[\d.]+ deg", shoulder[0]) and "modulo" not in shoulder[1]
    assert _percent(hand[4]) == _percent(hand[3])        # half a turn on the hand: the monitor cannot see it
    assert _percent(shoulder[4]) > _percent(shoulder[3])  # half a turn on the shoulder: caught
    assert _percent(rows["any joint"][2]) >= max(_percent(r[2]) for name, r in rows.items() if name.startswith("panda_"))
