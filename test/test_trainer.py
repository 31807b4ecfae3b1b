"""The staged trainer end to end on a tiny real network: stages run, the CSV log and checkpoints are written, the
kept model loads into the estimator, and a resumed run continues where it stopped."""

import csv
import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch
import yaml

from holo_pose_ros.estimator import Estimator
from holo_pose_ros.model.network import load_model_config
from holo_pose_ros.train.trainer import Trainer, _append_row, lr_factor

WEIGHTS = {"joints": 1.0, "rotation": 1.0, "translation": 1.0, "depth": 1.0, "kp2d_reg": 10.0, "kp3d_reg": 10.0,
           "kp2d_fk": 10.0, "kp3d_fk": 10.0, "presence": 0.5}


def tiny_config(out) -> dict:
    model = {**load_model_config("lite").to_dict(), "name": "tiny", "input_size": 64, "heatmap_size": 16,
             "depth_bins": 8, "deconv_channels": 16, "regressor_hidden": 32}
    return {"robot": "panda", "model": model, "generator": "randomized", "out": str(out), "seed": 3, "batch_size": 4,
            "num_workers": 0, "depth_calibration_views": 16,
            "stages": [{"name": "depth", "steps": 2, "lr": 1e-3, "warmup_steps": 1, "losses": {"depth": 1.0}},
                       {"name": "full", "steps": 4, "lr": 1e-3, "warmup_steps": 1, "losses": WEIGHTS}],
            "validation": {"every_steps": 2, "frames": 3, "seed": 77}}


def test_lr_schedule_warms_up_then_decays():
    assert lr_factor(0, 100, 10) == 0.1 and lr_factor(9, 100, 10) == 1.0
    assert lr_factor(10, 100, 10) == 1.0 and abs(lr_factor(100, 100, 10) - 0.05) < 1e-9
    assert lr_factor(50, 100, 10) < lr_factor(20, 100, 10)


def test_training_run_logs_checkpoints_keeps_and_resumes(tmp_path):
    cfg = tiny_config(tmp_path / "run")
    cfg["validation"]["snapshots"] = True
    kept = Trainer(cfg, device="cpu", progress=False).run()
    assert kept is not None and kept.exists()
    rows = list(csv.DictReader(open(tmp_path / "run" / "log.csv")))
    assert [int(r["step"]) for r in rows] == [2, 4, 6] and [r["stage"] for r in rows] == ["depth", "full", "full"]
    # every validated model is kept as a snapshot card, whether or not it was the best
    snapshots = sorted((tmp_path / "run" / "snapshots").glob("step_*.yaml"))
    assert [p.stem for p in snapshots] == ["step_000002", "step_000004", "step_000006"]
    assert [yaml.safe_load(open(p))["training"]["steps"] for p in snapshots] == [2, 4, 6]
    assert Estimator.from_model(snapshots[-1], min_confidence=0.0).net.cfg.input_size == 64
    assert all(float(r["loss_loss"]) > 0 for r in rows) and rows[-1]["val_add_auc"] != ""
    # a network with fit heatmaps is also validated fitted, with the robot's shipped lifter
    assert 0.0 <= float(rows[-1]["val_fitted_add_auc"]) <= 100.0 and "val_fitted_add_mean_mm" in rows[-1]
    card = yaml.safe_load(open(kept))
    assert card["robot"] == "panda" and card["training"]["steps"] in (4, 6)
    estimator = Estimator.from_model(kept, min_confidence=0.0)
    assert estimator.net.cfg.input_size == 64

    # two more steps of the last stage: resuming continues from the checkpoint's step, not from zero
    cfg["stages"][1]["steps"] = 6
    Trainer(cfg, device="cpu", progress=False).run(resume=True)
    rows = list(csv.DictReader(open(tmp_path / "run" / "log.csv")))
    assert [int(r["step"]) for r in rows] == [2, 4, 6, 8]


def test_warm_start_copies_shared_layers_but_not_the_donor_robot(tmp_path, small_model_card):
    from small_model import SMALL

    from holo_pose_ros.model.network import HolisticNet
    from holo_pose_ros.model.weights import load_model, transfer_weights
    from holo_pose_ros.robots.kinematics import RobotModel

    donor, _, _ = load_model(small_model_card)
    kuka = HolisticNet(load_model_config(SMALL), RobotModel("kuka"))
    before = {k: v.clone() for k, v in kuka.state_dict().items()}
    copied, fresh = transfer_weights(kuka, small_model_card)
    state, donor_state = kuka.state_dict(), donor.state_dict()
    assert copied > 100 and fresh > 0
    name = next(k for k in state if k.startswith("backbone.") and k.endswith("weight"))
    assert torch.equal(state[name], donor_state[name])                       # shared trunk: copied
    assert torch.equal(state["keypoint_head.out.weight"], before["keypoint_head.out.weight"])  # 8 vs 7 keypoints
    for key in ("joint_mid", "joint_half", "depth_head.log_lambda0"):        # the Kuka's own
        assert torch.equal(state[key], before[key]), key

    other = HolisticNet(load_model_config({**SMALL, "depth_backbone": "efficientnet_lite0", "pretrained": False,
                                           "depth_pretrained": False}), RobotModel("kuka"))
    with pytest.raises(ValueError, match="backbones"):
        transfer_weights(other, small_model_card)


def test_two_process_ddp_run_with_torchrun(tmp_path):
    """The multi-GPU path (torchrun, DDP) on two CPU processes with the gloo backend: both ranks train, rank 0
    alone validates, logs and keeps the model."""
    cfg = tiny_config(tmp_path / "ddp")
    cfg["stages"] = cfg["stages"][1:]
    cfg["stages"][0]["steps"] = 2
    path = tmp_path / "ddp.yaml"
    path.write_text(yaml.safe_dump(cfg))
    torchrun = Path(sys.executable).with_name("torchrun")
    result = subprocess.run([str(torchrun), "--standalone", "--nproc_per_node", "2", "-m", "holo_pose_ros.cli",
                             "train", "--config", str(path), "--device", "cpu", "--quiet"],
                            capture_output=True, text=True, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert result.returncode == 0, result.stderr[-3000:]
    rows = list(csv.DictReader(open(tmp_path / "ddp" / "log.csv")))
    assert [int(r["step"]) for r in rows] == [2]                              # one writer
    assert (tmp_path / "ddp" / "best.yaml").exists() and result.stdout.count("kept model:") == 1


def test_cumulative_views_continue_the_campaign_and_survive_a_resume(tmp_path):
    """A run warm-started from a card counts that card's views; resuming it does not count them again, even when
    the card it started from has since been replaced (a campaign ships each run over its own warm-start card)."""
    first = Trainer(tiny_config(tmp_path / "first"), device="cpu", progress=False).run()
    before = yaml.safe_load(open(first))["training"]["cumulative_views"]
    cfg = {**tiny_config(tmp_path / "second"), "init_from": str(first)}
    cfg["stages"][1] = {**cfg["stages"][1], "steps": 2}
    Trainer(cfg, device="cpu", progress=False).run()
    card = yaml.safe_load(open(first))
    card["training"]["cumulative_views"] = 10**6  # the shipped card now says more
    yaml.safe_dump(card, open(first, "w"))
    cfg["stages"][1]["steps"] = 4
    Trainer(cfg, device="cpu", progress=False).run(resume=True)
    rows = list(csv.DictReader(open(tmp_path / "second" / "log.csv")))
    assert [int(float(r["views"])) for r in rows] == [before + int(r["step"]) * 4 for r in rows]
    hours = [float(r["train_hours"]) for r in rows]
    assert hours == sorted(hours) and hours[-1] < 1.0


def test_a_warm_started_run_draws_views_its_donor_never_saw(tmp_path):
    """Views are indexed by the campaign's view count, so a new run from a shipped card does not replay the views
    that trained it (every run of a recipe has the same seed)."""
    first = Trainer(tiny_config(tmp_path / "first"), device="cpu", progress=False).run()
    seen = yaml.safe_load(open(first))["training"]["cumulative_views"]
    second = Trainer({**tiny_config(tmp_path / "second"), "init_from": str(first)}, device="cpu", progress=False)
    loader = second._loader(8)
    assert list(loader.dataset.indices) == list(range(seen, seen + 8))
    fresh = Trainer(tiny_config(tmp_path / "fresh"), device="cpu", progress=False)._loader(4)
    assert list(fresh.dataset.indices) == [0, 1, 2, 3]
    assert not torch.equal(next(iter(fresh))["image"], next(iter(loader))["image"])


def test_a_donor_of_another_robot_starts_the_robots_campaign_at_zero_views(tmp_path):
    """A run warm-started from another robot's card (Kuka from Panda's network) copies its weights but not its view
    count: those views were of the donor's robot, and this robot's learning curve starts here."""
    first = Trainer(tiny_config(tmp_path / "first"), device="cpu", progress=False).run()
    assert yaml.safe_load(open(first))["training"]["cumulative_views"] > 0
    kuka = Trainer({**tiny_config(tmp_path / "kuka"), "robot": "kuka", "init_from": str(first)}, device="cpu",
                   progress=False)
    assert (kuka.views_before, kuka.hours_before) == (0, 0.0)
    assert list(kuka._loader(4).dataset.indices) == [0, 1, 2, 3]


def test_a_cpu_run_with_frozen_blocks_runs_them_in_onnx_runtime(tmp_path):
    """`freeze_blocks` on the CPU: the frozen stem and blocks run in ONNX Runtime (exported once per run), the
    run trains, and the frozen weights stay exactly as loaded; `frozen_backend: torch` keeps them in PyTorch."""
    cfg = {**tiny_config(tmp_path / "ort"), "freeze_blocks": 3}
    trainer = Trainer(cfg, device="cpu", progress=False)
    before = {k: v.clone() for k, v in trainer.net.backbone.net._blocks[:3].state_dict().items()}
    card = trainer.run()
    assert (tmp_path / "ort" / "frozen_prefix_rank0.onnx").is_file() and card.is_file()
    assert trainer.net.backbone.frozen_prefix is not None
    after = trainer.net.backbone.net._blocks[:3].state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)
    rows = list(csv.DictReader(open(tmp_path / "ort" / "log.csv")))
    assert rows and all(float(r["loss_loss"]) == float(r["loss_loss"]) for r in rows)  # finite, not NaN
    torch_run = Trainer({**tiny_config(tmp_path / "torch"), "freeze_blocks": 3, "frozen_backend": "torch"},
                        device="cpu", progress=False)
    torch_run._attach_frozen_prefix()
    assert torch_run.net.backbone.frozen_prefix is None
    with pytest.raises(ValueError, match="frozen_backend"):
        Trainer({**tiny_config(tmp_path / "bad"), "frozen_backend": "tvm"}, device="cpu", progress=False)._attach_frozen_prefix()


def test_bf16_runs_the_training_forward_in_bfloat16_on_the_cpu(tmp_path):
    """`bf16: true` on a CPU with native bfloat16 (AVX-512 BF16, AMX): the training forward runs under bfloat16
    autocast (a convolution's output is bfloat16), the losses stay finite and the weights train; on one without
    (AVX2 only, where emulation made a step 25 times slower) it says so and trains in float32; by default the CPU
    forward is float32."""
    native = torch.ops.mkldnn._is_mkldnn_bf16_supported()
    dtypes = {}
    for bf16 in (True, False):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            trainer = Trainer({**tiny_config(tmp_path / str(bf16)), "bf16": bf16}, device="cpu", progress=False)
        assert any("no native bfloat16" in str(w.message) for w in caught) == (bf16 and not native)
        seen = dtypes.setdefault(bf16, set())
        conv = next(m for m in trainer.net.keypoint_head.modules() if isinstance(m, torch.nn.Conv2d))
        conv.register_forward_hook(lambda module, inputs, output: seen.add(output.dtype) if module.training else None)
        before = conv.weight.detach().clone()
        trainer.run()
        assert not torch.equal(before, conv.weight.detach())
        rows = list(csv.DictReader(open(tmp_path / str(bf16) / "log.csv")))
        assert rows and all(float(r["loss_loss"]) == float(r["loss_loss"]) for r in rows)  # finite, not NaN
    assert dtypes[True] == ({torch.bfloat16} if native else {torch.float32}) and dtypes[False] == {torch.float32}
    assert not Trainer(tiny_config(tmp_path / "default"), device="cpu", progress=False).bf16


def test_a_log_of_an_older_version_gains_the_new_columns_without_misaligning(tmp_path):
    log = tmp_path / "log.csv"
    _append_row(log, {"step": 250, "val_add_auc": 3.4})
    _append_row(log, {"step": 500, "val_add_auc": 9.2, "val_fitted_add_auc": 20.1})
    _append_row(log, {"step": 750, "val_add_auc": 7.1, "val_fitted_add_auc": 21.5})
    rows = list(csv.DictReader(open(log)))
    assert [(r["step"], r["val_add_auc"], r["val_fitted_add_auc"]) for r in rows] == [
        ("250", "3.4", ""), ("500", "9.2", "20.1"), ("750", "7.1", "21.5")]


def test_a_train_only_run_adds_a_mask_layer_and_changes_nothing_else(tmp_path, small_model_card):
    """train_only on a shipped card (here the small test model): only the new mask layer learns; every tensor the
    donor had, its DepthNet scale and BatchNorm statistics included, comes out bit-identical."""
    from small_model import SMALL

    from holo_pose_ros.model.weights import load_model

    cfg = {**tiny_config(tmp_path / "mask"), "model": {**SMALL, "segmentation": True}, "init_from": str(small_model_card),
           "train_only": ["keypoint_head.mask_out"], "weight_decay": 0.0,
           "stages": [{"name": "mask", "steps": 4, "lr": 1e-2, "warmup_steps": 1, "losses": {"mask": 1.0}}],
           "validation": {"every_steps": 4, "frames": 3, "seed": 77}}
    kept = Trainer(cfg, device="cpu", progress=False).run()
    donor = load_model(small_model_card)[0].state_dict()
    trained = load_model(kept)[0].state_dict()
    assert all(torch.equal(trained[k], v) for k, v in donor.items() if v.dtype.is_floating_point)
    assert set(trained) - set(donor) == {"keypoint_head.mask_out.weight", "keypoint_head.mask_out.bias"}
    assert trained["keypoint_head.mask_out.bias"].abs().sum() > 0
    rows = list(csv.DictReader(open(tmp_path / "mask" / "log.csv")))
    assert float(rows[-1]["loss_mask"]) > 0
    with pytest.raises(ValueError, match="no parameter"):
        Trainer({**cfg, "train_only": ["nothing.here"], "out": str(tmp_path / "bad")}, device="cpu", progress=False)


def test_style_noise_restyles_the_frozen_blocks_output_and_needs_them(tmp_path):
    """`style_noise` attaches feature-statistics noise after the last frozen block and trains; without frozen
    blocks there is no boundary to restyle, and the run is refused by name."""
    cfg = {**tiny_config(tmp_path / "noise"), "freeze_blocks": 3, "style_noise": {"probability": 0.5}}
    trainer = Trainer(cfg, device="cpu", progress=False)
    assert trainer.run().is_file()
    backbone = trainer.net.backbone
    assert backbone.style_noise is not None and backbone.style_noise.probability == 0.5
    assert backbone.style_noise_after == (2,)
    rows = list(csv.DictReader(open(tmp_path / "noise" / "log.csv")))
    assert rows and all(float(r["loss_loss"]) == float(r["loss_loss"]) for r in rows)  # finite, not NaN
    with pytest.raises(ValueError, match="style_noise needs"):
        Trainer({**tiny_config(tmp_path / "bad"), "style_noise": {"probability": 0.5}}, device="cpu",
                progress=False)._attach_style_noise()
    for after in ([1], [2, 99]):   # inside the frozen blocks (their ONNX prefix cannot restyle), past the last
        with pytest.raises(ValueError, match="after_blocks"):
            Trainer({**cfg, "out": str(tmp_path / "bad2"), "style_noise": {"probability": 0.5, "after_blocks": after}},
                    device="cpu", progress=False)._attach_style_noise()
    deeper = Trainer({**cfg, "out": str(tmp_path / "deeper"), "style_noise": {"after_blocks": [2, 6]}}, device="cpu",
                     progress=False)
    deeper._attach_style_noise()
    assert deeper.net.backbone.style_noise_after == (2, 6)


def test_a_run_with_close_up_views_trains_their_2d_terms_only(tmp_path):
    """A fourth mode probability draws close-up views (data/training.py) into the batches: the heatmaps learn from
    them, the 3D terms only from the robot's crops. A batch of close-ups alone has a heatmap loss and no 3D loss."""
    from holo_pose_ros.data.generator import load_generator_config
    from holo_pose_ros.data.training import RenderedViews, SampleConfig
    from holo_pose_ros.model.network import add_kinematics
    from holo_pose_ros.train.losses import supervised_losses

    cfg = {**tiny_config(tmp_path / "close"), "views": {"mode_probabilities": [0.4, 0.2, 0.1, 0.3]}}
    trainer = Trainer(cfg, device="cpu", progress=False)
    assert trainer.run().is_file()
    views = RenderedViews("panda", SampleConfig(64, mode_probabilities=(0, 0, 0, 1)),
                          load_generator_config("randomized"), seed=3, length=6)
    samples = [v for v in (views[i] for i in range(6)) if int(v["mode"]) == 3]  # a hand out of view: a crop
    assert len(samples) >= 3
    batch = torch.utils.data.default_collate(samples)
    net = trainer.net.eval()
    with torch.no_grad():
        out = add_kinematics(trainer.robot, net(batch["image"], batch["K_crop"]))
        terms = supervised_losses(out, batch, net.joint_mid, net.joint_half, 64, net.cfg.heatmap_sigma)
    assert float(terms["heatmap"]) > 0 and float(terms["kp2d_reg"]) > 0
    assert {k: float(terms[k]) for k in ("joints", "rotation", "translation", "depth", "kp3d_reg", "kp3d_fk")} == \
        dict.fromkeys(("joints", "rotation", "translation", "depth", "kp3d_reg", "kp3d_fk"), 0.0)
