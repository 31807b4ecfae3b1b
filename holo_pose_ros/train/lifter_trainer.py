"""Training the lifter (model/lifter.py) on synthetic samples from forward kinematics (train/lifter_data.py): a
fresh batch every step, AdamW with a cosine schedule over the run (steps or wall-clock minutes), winner-takes-all
over the hypotheses, periodic validation on a fixed held-out batch scored the way the estimator will choose
(best-by-reprojection hypothesis), a CSV log, and the best weights saved with their card."""

from __future__ import annotations

import copy
import csv
import math
import sys
import time
from pathlib import Path

import torch

from holo_pose_ros.geometry.rotation import geodesic_angle, rot6d_to_matrix
from holo_pose_ros.model.lifter import (Lifter, encode_pose, hypothesis_keypoints, keypoint_reprojection_errors,
                                        lifter_features, load_lifter, load_lifter_config, save_lifter)
from holo_pose_ros.resources import weights_dir
from holo_pose_ros.robots.kinematics import RobotModel
from holo_pose_ros.train.lifter_data import LifterBatch, LifterSampler


def hypothesis_losses(lifter: Lifter, out: dict[str, torch.Tensor], batch: LifterBatch, weights: dict) -> torch.Tensor:
    """(B, H) loss of each hypothesis against the batch's truth: weighted L1 of normalized joints, rotation
    matrix entries (relative to the virtual camera), log-depth and the base origin's box-normalized offset."""
    R_true, o_true, s_true = encode_pose(batch.T_cam_base, batch.box, batch.K)
    joints = (out["joints_norm"] - lifter.normalize_joints(batch.q)[:, None]).abs().mean(-1)
    rotation = (rot6d_to_matrix(out["rot6d"]) - R_true[:, None]).abs().mean((-1, -2))
    depth = (out["log_depth"] - s_true[:, None]).abs()
    xy = (out["offset"] - o_true[:, None]).abs().mean(-1)
    return (weights["joints"] * joints + weights["rotation"] * rotation + weights["depth"] * depth
            + weights["xy"] * xy)


def winner_takes_all(losses: torch.Tensor, all_weight: float) -> torch.Tensor:
    """Scalar loss of per-hypothesis losses (B, H): the best hypothesis' loss per sample plus `all_weight` times
    the mean over all hypotheses (so no hypothesis stops learning)."""
    return losses.min(1).values.mean() + all_weight * losses.mean()


def lr_at(progress: float, step: int, warmup: int, min_fraction: float) -> float:
    """Learning-rate factor: linear warm-up over `warmup` steps, then cosine from 1 to `min_fraction` over the
    run's progress in [0, 1]."""
    if step < warmup:
        return (step + 1) / warmup
    return min_fraction + (1.0 - min_fraction) * 0.5 * (1.0 + math.cos(math.pi * min(max(progress, 0.0), 1.0)))


@torch.no_grad()
def evaluate_lifter(lifter: Lifter, batch: LifterBatch) -> dict[str, float]:
    """Held-out metrics of a lifter on a batch. `*_selected`: the hypothesis with the lowest confidence-weighted
    reprojection error of the fit keypoints (how the estimator picks, without ground truth); `*_oracle`: the best
    hypothesis by that metric. Joint errors are over revolute joints (degrees); prismatic ones in mm; ADD is the
    mean 3D distance of DREAM's keypoints in the camera frame (mm). `neutral_joint_error_deg`: the robot's
    neutral pose as the estimate, the baseline."""
    robot = lifter.robot
    was_training = lifter.training
    lifter.eval()
    q, T = lifter.hypotheses(batch.uv, batch.confidence, batch.box, batch.K)
    lifter.train(was_training)
    kp = hypothesis_keypoints(robot, q, T)
    reproj = keypoint_reprojection_errors(kp, batch.uv, batch.confidence, batch.K)
    sel = reproj.argmin(1)
    rows = torch.arange(len(batch))
    revolute = torch.tensor([t != "prismatic" for t in robot.joint_types])
    err = (q - batch.q[:, None]).abs()
    joint_deg = torch.rad2deg(err[..., revolute]).mean(-1)                          # (B, H)
    N = robot.n_keypoints
    add_mm = (kp[..., :N, :] - batch.keypoints_cam[:, None, :N]).norm(dim=-1).mean(-1) * 1e3  # (B, H)
    rot_deg = torch.rad2deg(geodesic_angle(T[..., :3, :3], batch.T_cam_base[:, None, :3, :3]))
    trans_mm = (T[..., :3, 3] - batch.T_cam_base[:, None, :3, 3]).norm(dim=-1) * 1e3
    neutral = torch.rad2deg((robot.neutral - batch.q).abs()[:, revolute]).mean(-1)
    metrics = {
        "joint_error_deg": joint_deg[rows, sel].mean(),
        "joint_error_deg_median": joint_deg[rows, sel].median(),
        "joint_error_deg_oracle": joint_deg.min(1).values.mean(),
        "neutral_joint_error_deg": neutral.mean(),
        "add_mm": add_mm[rows, sel].mean(),
        "add_mm_median": add_mm[rows, sel].median(),
        "add_mm_oracle": add_mm.min(1).values.mean(),
        "rotation_error_deg": rot_deg[rows, sel].mean(),
        "translation_error_mm": trans_mm[rows, sel].mean(),
        "reprojection_px": reproj[rows, sel].mean(),
        "reprojection_px_median": reproj[rows, sel].median(),
    }
    if (~revolute).any():
        metrics["prismatic_error_mm"] = (err[..., ~revolute].mean(-1)[rows, sel] * 1e3).mean()
    metrics["joint_error_vs_neutral"] = metrics["joint_error_deg"] / metrics["neutral_joint_error_deg"]
    return {k: round(float(v), 4) for k, v in metrics.items()}


VALIDATION_NOTE = ("held-out synthetic samples of the training distribution (config sampler section, its noise "
                   "included); metrics without suffix: of the hypothesis with the lowest confidence-weighted "
                   "reprojection error (the estimator's pick), *_oracle: of the best one; joint errors over "
                   "revolute joints (deg), ADD over DREAM's keypoints in the camera frame (mm); "
                   "neutral_joint_error_deg: the neutral pose's")


def default_out(robot_name: str) -> Path:
    """Where `holo-pose train-lifter` writes by default: the shipped weights folder, `<robot>_lifter`."""
    return weights_dir() / f"{robot_name}_lifter"


def train_lifter(robot: str | RobotModel, config: str | Path | dict | None = None, minutes: float | None = None,
                 steps: int | None = None, out: str | Path | None = None, progress: bool = True,
                 log: str | Path | None = None, command: str | None = None) -> Path:
    """Train a lifter of `robot` for `minutes` of wall-clock time or `steps` steps (exactly one), validating every
    `train.validation.every_s` seconds and at the end; keep the best by `train.validation.keep_by`, write it to
    `out`.safetensors + `out`.yaml (card with config, training and the saved file's validation metrics) and the
    log to `log` (default `out`_log.csv). Returns the card's path. CPU; uses torch's thread setting."""
    if (minutes is None) == (steps is None):
        raise ValueError("train_lifter: give exactly one of minutes and steps")
    robot = robot if isinstance(robot, RobotModel) else RobotModel(robot)
    cfg = load_lifter_config(config)
    tc, vc = cfg["train"], cfg["train"]["validation"]
    out = Path(out) if out is not None else default_out(robot.name)
    log = Path(log) if log is not None else out.parent / f"{out.name}_log.csv"
    log.parent.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(int(tc["seed"]))
    g = torch.Generator().manual_seed(int(tc["seed"]))
    sampler = LifterSampler(robot, cfg["sampler"])
    val_batch = sampler.sample(int(vc["samples"]), torch.Generator().manual_seed(int(vc["seed"])))
    lifter = Lifter(cfg["model"], robot)
    first = sampler.sample(4096, g)
    _, o0, s0 = encode_pose(first.T_cam_base, first.box, first.K)
    lifter.set_translation_prior(o0.mean(0), float(s0.median()))
    opt = torch.optim.AdamW(lifter.parameters(), lr=float(tc["lr"]), weight_decay=float(tc["weight_decay"]))
    batch_size, warmup = int(tc["batch_size"]), int(tc["warmup_steps"])
    budget_s = None if minutes is None else float(minutes) * 60.0

    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=steps, unit="step", file=sys.stderr, dynamic_ncols=True,
                   desc=f"lifter {robot.name}" + (f" {minutes:g} min" if minutes is not None else ""))
    columns = ["step", "samples", "elapsed_s", "lr", "train_loss"]
    rows: list[dict] = []
    best, best_state, step, samples, loss_avg = math.inf, None, 0, 0, None
    start = last_val = time.perf_counter()

    def validate() -> dict:
        nonlocal best, best_state
        metrics = evaluate_lifter(lifter, val_batch)
        row = {"step": step, "samples": samples, "elapsed_s": round(time.perf_counter() - start, 1),
               "lr": opt.param_groups[0]["lr"], "train_loss": round(loss_avg or float("nan"), 5), **metrics}
        rows.append(row)
        with open(log, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=columns + list(metrics))
            writer.writeheader()
            writer.writerows(rows)
        if metrics[vc["keep_by"]] < best:
            best, best_state = metrics[vc["keep_by"]], copy.deepcopy(lifter.state_dict())
        return metrics

    lifter.train()
    while True:
        elapsed = time.perf_counter() - start
        progress_frac = step / steps if steps is not None else elapsed / budget_s
        if progress_frac >= 1.0:
            break
        for group in opt.param_groups:
            group["lr"] = float(tc["lr"]) * lr_at(progress_frac, step, warmup, float(tc["min_lr_fraction"]))
        batch = sampler.sample(batch_size, g)
        out_raw = lifter(lifter_features(batch.uv, batch.confidence, batch.box, batch.K), bf16=bool(tc["bf16"]))
        loss = winner_takes_all(hypothesis_losses(lifter, out_raw, batch, tc["loss"]), float(tc["all_hypotheses_weight"]))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(lifter.parameters(), float(tc["grad_clip"]))
        opt.step()
        step, samples = step + 1, samples + batch_size
        loss_value = float(loss.detach())
        loss_avg = loss_value if loss_avg is None else 0.98 * loss_avg + 0.02 * loss_value
        if time.perf_counter() - last_val >= float(vc["every_s"]):
            m = validate()
            last_val = time.perf_counter()
            if bar is not None:
                bar.write(f"step {step} samples {samples}: joints {m['joint_error_deg']:.1f} deg (oracle "
                          f"{m['joint_error_deg_oracle']:.1f}, neutral {m['neutral_joint_error_deg']:.1f}), ADD "
                          f"{m['add_mm']:.0f} mm, reprojection {m['reprojection_px']:.1f} px")
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{loss_avg:.3f}", samples_s=f"{samples / (time.perf_counter() - start):.0f}",
                            best=f"{best:.1f}")
    validate()
    if bar is not None:
        bar.close()
    train_minutes = (time.perf_counter() - start) / 60.0
    lifter.load_state_dict(best_state)
    save_dtype = getattr(torch, str(tc["save_dtype"]))
    card = {
        "training": {"samples_seen": samples, "steps": step, "minutes": round(train_minutes, 2),
                     "command": command or f"train_lifter({robot.name!r}, minutes={minutes}, steps={steps})",
                     "torch_threads": torch.get_num_threads(), "kept_by": vc["keep_by"],
                     "log": log.name, "config": {k: cfg[k] for k in ("sampler", "train")}},
    }
    card_path = save_lifter(lifter, out, card, dtype=save_dtype)
    saved = load_lifter(card_path, robot=robot)  # the metrics of the file as shipped (e.g. float16)
    card["validation"] = {"what": VALIDATION_NOTE, "samples": int(vc["samples"]), "seed": int(vc["seed"]),
                          "weights": str(tc["save_dtype"]), **evaluate_lifter(saved, val_batch)}
    return save_lifter(lifter, out, card, dtype=save_dtype)
