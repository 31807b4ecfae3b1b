"""The staged trainer end to end on a tiny real network: stages run, the CSV log and checkpoints are written, the
kept model loads into the estimator, and a resumed run continues where it stopped."""

import csv

import yaml

from holo_pose_ros.estimator import Estimator
from holo_pose_ros.model.network import load_model_config
from holo_pose_ros.train.trainer import Trainer, lr_factor

WEIGHTS = {"joints": 1.0, "rotation": 1.0, "translation": 1.0, "depth": 1.0, "kp2d_reg": 10.0, "kp3d_reg": 10.0,
           "kp2d_fk": 10.0, "kp3d_fk": 10.0, "presence": 0.5}


def tiny_config(out) -> dict:
    model = {**load_model_config("lite").to_dict(), "name": "tiny", "input_size": 64, "heatmap_size": 16,
             "depth_bins": 8, "deconv_channels": 16, "regressor_hidden": 32}
    return {"robot": "panda", "model": model, "generator": "randomized", "out": str(out), "seed": 3, "batch_size": 4,
            "num_workers": 0,
            "stages": [{"name": "depth", "steps": 2, "lr": 1e-3, "warmup_steps": 1, "losses": {"depth": 1.0}},
                       {"name": "full", "steps": 4, "lr": 1e-3, "warmup_steps": 1, "losses": WEIGHTS}],
            "validation": {"every_steps": 2, "frames": 3, "seed": 77}}


def test_lr_schedule_warms_up_then_decays():
    assert lr_factor(0, 100, 10) == 0.1 and lr_factor(9, 100, 10) == 1.0
    assert lr_factor(10, 100, 10) == 1.0 and abs(lr_factor(100, 100, 10) - 0.05) < 1e-9
    assert lr_factor(50, 100, 10) < lr_factor(20, 100, 10)


def test_training_run_logs_checkpoints_keeps_and_resumes(tmp_path):
    cfg = tiny_config(tmp_path / "run")
    kept = Trainer(cfg, device="cpu", progress=False).run()
    assert kept is not None and kept.exists()
    rows = list(csv.DictReader(open(tmp_path / "run" / "log.csv")))
    assert [int(r["step"]) for r in rows] == [2, 4, 6] and [r["stage"] for r in rows] == ["depth", "full", "full"]
    assert all(float(r["loss_loss"]) > 0 for r in rows) and rows[-1]["val_add_auc"] != ""
    card = yaml.safe_load(open(kept))
    assert card["robot"] == "panda" and card["training"]["steps"] in (4, 6)
    estimator = Estimator.from_model(kept, min_confidence=0.0)
    assert estimator.net.cfg.input_size == 64

    # two more steps of the last stage: resuming continues from the checkpoint's step, not from zero
    cfg["stages"][1]["steps"] = 6
    Trainer(cfg, device="cpu", progress=False).run(resume=True)
    rows = list(csv.DictReader(open(tmp_path / "run" / "log.csv")))
    assert [int(r["step"]) for r in rows] == [2, 4, 6, 8]
