"""Ship a trained model: score its kept checkpoint on held-out generated test folders (never seen in training or
validation) through the deployed estimator, and write holo_pose_ros/weights/<name>.safetensors (float16) with a
model card that records the training, the metrics and the commands that measured them.

    python scripts/ship_model.py runs/panda_lite_cpu/best.yaml panda --test data/panda_test_dr:randomized \
        --test data/panda_test_photo:photo
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import SETTINGS_FILE
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.evaluation.run import evaluate_folder
from holo_pose_ros.model.weights import load_model, save_model
from holo_pose_ros.resources import weights_dir

KEPT = ("n_frames", "n_not_found", "add_auc", "add_mean_mm", "add_median_mm", "add_below_mm", "joint_error_deg",
        "rotation_error_deg", "depth_error_mm", "reproj_error_px", "fps")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("card", help="the trained model card (runs/<name>/best.yaml)")
    parser.add_argument("name", help="shipped name (holo_pose_ros/weights/<name>.*)")
    parser.add_argument("--test", action="append", required=True, help="DIR:LOOK of a held-out DREAM folder")
    args = parser.parse_args(argv)
    net, robot, card = load_model(args.card)
    metrics = {}
    for item in args.test:
        folder, _, look = item.partition(":")
        reader = DreamReader(folder, robot)
        report, _, _ = evaluate_folder(Estimator(net, robot), reader)
        metrics[look or Path(folder).name] = {
            "data": _provenance(folder, len(reader)),
            "command": f"holo-pose evaluate --model {args.name} --data {folder} --out report.json",
            **{k: report[k] for k in KEPT},
        }
        print(f"{folder}: AUC {report['add_auc']:.1f}, mean ADD {report['add_mean_mm']} mm, "
              f"not found {report['n_not_found']}/{report['n_frames']}")
    shipped = {k: card[k] for k in ("training", "validation") if k in card}
    out = save_model(net, robot.name, weights_dir() / args.name, {**shipped, "test": metrics}, dtype=torch.float16)
    print(f"shipped: {out}")
    return 0


def _provenance(folder: str, frames: int) -> dict:
    """How a generated test folder was made (its _generator_settings.json), for the model card."""
    path = Path(folder) / SETTINGS_FILE
    if not path.exists():
        return {"folder": folder, "frames": frames}
    settings = json.loads(path.read_text())
    return {"frames": frames, "robot": settings["robot"], "seed": settings["seed"], "look": settings["config"],
            "command": settings["command"]}


if __name__ == "__main__":
    sys.exit(main())
