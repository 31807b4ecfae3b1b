"""The corruption sweep (scripts/corruption_sweep.py) on a small generated folder and its bags, with the small
test model: every damaged DREAM frame is named (file + field) and skipped while every good one is evaluated; a
missing or wrong settings file, and bags that cannot be read, end in one clear error naming the file; damaged
bag contents are reported and skipped; no case ends in a traceback."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_every_corruption_is_named_skipped_or_refused_without_a_traceback(small_model_card, tmp_path):
    out = tmp_path / "sweep.json"
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "corruption_sweep.py"), "--frames", "4",
                          "--model", str(small_model_card), "--out", str(tmp_path / "work"), "--in-process",
                          "--json", str(out)], capture_output=True, text=True, cwd=ROOT, timeout=600,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-4000:]
    outcomes = {o["case"]: o for o in json.loads(out.read_text())}
    assert len(outcomes) == 16 and all(o["ok"] and not o["traceback"] for o in outcomes.values()), outcomes
    # the reader's account names the file and the field of each damaged frame
    assert "000001.json: field 'objects[0].keypoints': missing key" in outcomes["missing key"]["message"]
    assert "field 'objects[0].keypoints[2].location': contains NaN" in outcomes["NaN values"]["message"]
    assert "000001.rgb.jpg: field 'image'" in outcomes["image truncated"]["message"]
    assert "truncated" in outcomes["image truncated"]["message"]
    for case in ("truncated JSON", "wrong type", "image zero bytes", "image wrong size", "names do not pair"):
        assert outcomes[case]["frames_read"] == 3 and outcomes[case]["skipped"] == 1, outcomes[case]
    assert outcomes["settings file missing"]["exit_status"] == 2
    assert "cannot read bag" in outcomes["mcap truncated"]["message"]
    assert outcomes["CameraInfo missing for the first frames"]["skipped"] == 2
    assert "| another type on the image topic | bag-eval |" in run.stdout
