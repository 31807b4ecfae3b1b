"""scripts/learning_curve.py on training logs written here: it draws the figure, rewrites only its page's
learning-curve block, and its power law through the current recipe's runs recovers the exponent and the views to
the target that the logs were made with (runs of an older recipe left out)."""

from __future__ import annotations

import csv
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FIELDS = ["step", "images_per_s", "views", "train_hours", "val_add_auc", "val_kp2d_dream_median_px",
          "val_kp2d_fit_median_px", "val_fitted_add_auc"]


def write_run(folder: Path, name: str, views: list[float], px: list[float]) -> None:
    """One run's log.csv: a validation row per (views, fit-keypoint px), DREAM's error half of it, 20 views/s."""
    with open(folder / f"{name}.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, FIELDS)
        writer.writeheader()
        for step, (v, p) in enumerate(zip(views, px), 1):
            writer.writerow({"step": step * 250, "images_per_s": 20.0, "views": v, "train_hours": v / 20 / 3600,
                             "val_add_auc": 10.0, "val_kp2d_dream_median_px": p / 2, "val_kp2d_fit_median_px": p,
                             "val_fitted_add_auc": 30.0})


def test_curve_table_and_power_law(tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    # the recipe's first run starts at 90 k views (a warm start): its first row, 120 k at step 250 at 120 views a step
    origin = 9e4
    law = lambda v: 20.0 * ((v - origin) / 1e5) ** -0.5  # noqa: E731  3 px at 1e5 * (20 / 3)^2 = 4.44 M recipe views
    write_run(logs, "kuka_old_cpu", [5e4, 6e4], [90.0, 80.0])            # an older recipe: not on the trend
    for run, start in enumerate((1e5, 2e5, 4e5, 8e5), 1):
        views = [start * 1.2, start * 1.5, start * 1.8]
        px = [law(v) * 1.1 for v in views[:-1]] + [law(views[-1])]     # each run's kept point is its last
        write_run(logs, f"kuka_new_cpu{run}", views, px)
    page = tmp_path / "campaign.md"
    page.write_text("# title\n<!-- learning-curve:begin -->\nold table\n<!-- learning-curve:end -->\nafter\n")
    out = tmp_path / "curve.png"
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "learning_curve.py"), "--logs", str(logs),
                          "--out", str(out), "--page", str(page), "--trend-runs", "3"],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert out.stat().st_size > 10_000 and out.read_bytes()[:4] == b"\x89PNG"
    text = page.read_text()
    assert text.startswith("# title\n<!-- learning-curve:begin -->\n| run |") and text.endswith("-->\nafter\n")
    assert "old table" not in text and text.count("| kuka_new_cpu") == 8     # best and last row of each run
    trend = next(line for line in text.splitlines() if line.startswith("- kuka"))
    assert "kuka_new_cpu2, kuka_new_cpu3, kuka_new_cpu4" in trend and "old" not in trend
    alpha = float(re.search(r"views\^-([0-9.]+)", trend).group(1))
    views_m = float(re.search(r"3 px: ([0-9.]+) M views", trend).group(1))
    assert alpha == 0.50 and abs(views_m - 4.4) < 0.15
    hours = float(re.search(r"([0-9,]+) more training hours", trend).group(1).replace(",", ""))
    assert abs(hours - (4.44e6 - (1.44e6 - origin)) / 20 / 3600) < 2       # from the last kept point, at 20 views/s
