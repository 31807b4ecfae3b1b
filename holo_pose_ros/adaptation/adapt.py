"""`holo-pose adapt`: a shipped model adapted to the user's own camera from its images alone, or with the robot's
joint states, on the CPU. In order (config/adapt.yaml):
  1. the parent model finds the robot in every image (none found anywhere: nothing to adapt to);
  2. BatchNorm statistics of the user's images (batchnorm.py): the whole frames and crops as deployed;
  3. when `finetune.steps` > 0 (off by default: measured, it did not pay; docs/adaptation.md): pseudo-labels
     from the re-normalized model's own fits (pseudo_labels.py), with the joint states when the source has them,
     kept where they are confident and two looks agree, then keypoint consistency (finetune.py): the heatmaps
     trained towards those labels, and mask consistency for a network with a segmentation head (its mask towards
     the rendered silhouette of the label's pose), rendered labelled views in every step, for what is left of
     `minutes`.
The model (weights, card, its lifter) is written to a temporary folder and renamed to `out` when complete, so an
interrupted run leaves no half-written model; bad input raises AdaptationInputError and writes nothing."""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from holo_pose_ros.adaptation.batchnorm import reestimate_batchnorm
from holo_pose_ros.adaptation.crops import batches, deployed_inputs
from holo_pose_ros.adaptation.finetune import FinetuneResult, finetune, render_synthetic
from holo_pose_ros.adaptation.interrupts import sigint_latch
from holo_pose_ros.adaptation.pseudo_labels import PseudoLabel, label_frame, select_labels
from holo_pose_ros.adaptation.sources import AdaptationInputError, Source, read_source
from holo_pose_ros.model.cards import file_sha256, read_card
from holo_pose_ros.resources import config_with_overrides

MODEL_NAME = "model"  # the adapted model is OUT/model.yaml (+ .safetensors): `-p model:=OUT/model.yaml`


def load_adapt_config(overrides: dict | str | Path | None = None) -> dict:
    """config/adapt.yaml with `overrides` (a mapping or a YAML path of the same sections) merged over it."""
    return config_with_overrides("adapt.yaml", overrides, "adaptation config sections")


@dataclass
class AdaptResult:
    """What one adaptation did and where the model is."""

    card: Path
    source: Source
    n_found: int
    n_candidates: int
    labels: list[PseudoLabel]
    finetune: FinetuneResult | None
    seconds: float
    figures: dict = field(default_factory=dict)


def _check_out(out: Path) -> None:
    if out.exists():
        raise AdaptationInputError(f"{out} exists: adaptation writes a new model folder (remove it or choose "
                                   "another --out)")


def _detect_all(estimator, frames, progress: bool) -> list[np.ndarray | None]:
    """The parent's crop box of every frame (None where it finds no robot): found as the product finds it, the
    presence times the fit's quality, so that a dark frame the presence head half believes in, but whose keypoints
    nothing explains, is not a robot."""
    boxes = []
    for frame in tqdm(frames, desc="find the robot", unit="image", disable=not progress):
        estimate = estimator.estimate(frame.image, frame.K)  # untracked: every frame on its own
        boxes.append(estimate.box if estimate.found else None)
    return boxes


def _label_all(estimator, frames, progress: bool) -> list[PseudoLabel]:
    candidates = []
    bar = tqdm(frames, desc="pseudo-labels", unit="image", disable=not progress)
    for i, frame in enumerate(bar):
        label = label_frame(estimator, i, frame)
        if label is not None:
            candidates.append(label)
        bar.set_postfix(found=len(candidates))
    return candidates


def _write_model(net, parent: str | Path, out: Path, adaptation: dict) -> Path:
    """OUT/model.yaml + .safetensors (float16, as shipped) and the parent's lifter beside them, through a
    temporary folder renamed at the end."""
    from holo_pose_ros.model.weights import save_model

    parent_path, parent_card = read_card(parent)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        card = {k: parent_card[k] for k in ("estimator", "training") if k in parent_card}
        if "lifter" in parent_card:
            from holo_pose_ros.model.cards import read_card_file

            lifter_card = parent_path.parent / parent_card["lifter"]
            tmp.mkdir(parents=True)
            shutil.copy2(lifter_card, tmp / lifter_card.name)
            shutil.copy2(lifter_card.parent / read_card_file(lifter_card)["weights"], tmp)
            card["lifter"] = lifter_card.name
        card["adaptation"] = adaptation
        save_model(net, parent_card["robot"], tmp / MODEL_NAME, card, dtype=torch.float16)
        out.parent.mkdir(parents=True, exist_ok=True)
        os.rename(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out / f"{MODEL_NAME}.yaml"


def adapt(model: str | Path, images: str | Path, out: str | Path, joint_states_topic: str | None = None,
          camera_info: str | Path | None = None, image_topic: str | None = None, camera_info_topic: str | None = None,
          minutes: float = 30.0, limit: int | None = None, config: dict | str | Path | None = None,
          progress: bool = True, seed: int = 0, command: str | None = None, plots: str | Path | None = None,
          score: bool | None = None) -> AdaptResult:
    """Adapt `model` to the images of `images` (see the module docstring) and write OUT/model.yaml. `plots`: a
    folder for before/after frames and the loss curves. `score` (default: when the source is a DREAM folder with
    labels) scores the parent and the adapted model on the source's frames, after adaptation (the card's
    `adaptation.source_figures`; frames adaptation saw, so not a held-out figure)."""
    from holo_pose_ros.estimator import Estimator

    start = time.perf_counter()
    out = Path(out)
    _check_out(out)
    cfg = load_adapt_config(config)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    estimator = Estimator.from_model(model)
    if not (estimator.net.cfg.fit_heatmaps and estimator.fit):
        raise AdaptationInputError(f"{model}: adaptation needs a fitted model (fit heatmaps and a lifter)")
    source = read_source(images, estimator.robot.joint_names, joint_states_topic, camera_info, image_topic,
                         camera_info_topic, limit)
    frames = source.frames
    shown = np.unique(np.linspace(0, len(frames) - 1, min(4, len(frames))).astype(int)) if plots else []
    before = [_estimated_uv(estimator, frames[i]) for i in shown]
    boxes = _detect_all(estimator, frames, progress)
    n_found = sum(b is not None for b in boxes)
    if n_found == 0:
        raise AdaptationInputError(f"{images}: no {estimator.robot.name} robot found in any of its {len(frames)} "
                                   "images (another robot, or the camera does not see it?)")
    bn = cfg["batchnorm"]
    inputs, Ks = deployed_inputs(frames, boxes, estimator.size, int(bn["crops_per_frame"]), rng)
    with torch.no_grad():
        reestimate_batchnorm(estimator.net, batches(inputs, Ks, int(bn["batch_size"])), keep=float(bn["keep"]))
    del inputs, Ks
    ft, tuned, candidates, labels = cfg["finetune"], None, [], []
    if int(ft["steps"]) > 0:
        pl = cfg["pseudo_labels"]
        candidates = _label_all(estimator, frames, progress)
        labels = select_labels(candidates, float(pl["min_confidence"]), float(pl["max_disagreement"]),
                               int(pl["min_visible"]))
        if len(labels) < int(pl["min_labels"]):
            raise AdaptationInputError(
                f"{images}: only {len(labels)} usable pseudo-labels of {len(frames)} images (the robot found twice "
                f"in {len(candidates)}); adaptation needs {pl['min_labels']}: give more images in which the whole "
                "robot is seen")
        left_s = minutes * 60.0 - (time.perf_counter() - start)
        if left_s > 0:
            synthetic = render_synthetic(estimator.robot.name, estimator.size, ft["synthetic_generator"],
                                         int(ft["synthetic_views"]), seed=10_000 + seed, progress=progress)
            left_s = minutes * 60.0 - (time.perf_counter() - start)
            with sigint_latch() as check_interrupt:
                tuned = finetune(estimator.net, estimator.robot, frames, labels, synthetic, ft, max(left_s, 0.0),
                                 progress, seed, check_interrupt)
    seconds = time.perf_counter() - start
    parent_path, _ = read_card(model)
    adaptation = {
        "source": str(Path(images).resolve()), "source_kind": source.kind, "n_images": len(frames),
        "n_found": n_found, "joint_states": source.has_joints,
        **({"joint_states_topic": joint_states_topic} if joint_states_topic else {}),
        "n_pseudo_labels": len(labels), "n_candidates": len(candidates),
        "parent": str(parent_path), "parent_sha256": file_sha256(parent_path.parent / read_card(model)[1]["weights"]),
        "minutes": round(seconds / 60.0, 2), "minutes_budget": minutes,
        "finetune_steps": 0 if tuned is None else tuned.steps,
        "losses": None if tuned is None else {name: {"first": round(tuned.first(name), 4),
                                                     "last": round(tuned.last(name), 4)} for name in tuned.history},
        "config": cfg, **({"command": command} if command else {}),
        **({"skipped": dict(source.skipped)} if source.skipped else {}),
    }
    if score is None:
        score = source.kind == "dream" and any(p.suffix == ".json" and not p.name.startswith("_")
                                               for p in Path(images).iterdir())
    figures = _source_figures(model, estimator, images, len(frames), progress) if score else {}
    if figures:
        adaptation["source_figures"] = figures
    card = _write_model(estimator.net, model, out, adaptation)
    if plots:
        from holo_pose_ros.evaluation.plots import plot_before_after, plot_loss_curves

        plots = Path(plots)
        after = [_estimated_uv(estimator, frames[i]) for i in shown]
        plot_before_after([frames[i].image for i in shown], before, after, estimator.robot.keypoint_parents,
                          plots / "before_after.png", [frames[i].name for i in shown])
        if tuned is not None and tuned.steps:
            plot_loss_curves(tuned.history, plots / "losses.png")
    return AdaptResult(card, source, n_found, len(candidates), labels, tuned, seconds, figures)


def _estimated_uv(estimator, frame) -> np.ndarray | None:
    """The DREAM keypoints (N, 2) px of the estimator's fitted estimate of one frame, None when not found."""
    estimator.reset()
    estimate = estimator.estimate(frame.image, frame.K, frame.joints)
    estimator.reset()
    return estimate.keypoints_2d if estimate.found else None


def _source_figures(parent: str | Path, adapted, folder: str | Path, n_frames: int, progress: bool) -> dict:
    """ADD AUC, mean ADD and the fit keypoints' median 2D error of the parent and the adapted estimator on the
    first `n_frames` frames of the labelled DREAM folder the adaptation read (its labels are read here, after
    adaptation, and only here)."""
    from holo_pose_ros.data.dream import DreamReader
    from holo_pose_ros.estimator import Estimator
    from holo_pose_ros.evaluation.run import evaluate_folder

    figures = {}
    for name, estimator in (("parent", Estimator.from_model(parent)), ("adapted", adapted)):
        report, _, _ = evaluate_folder(estimator, DreamReader(folder, estimator.robot), limit=n_frames,
                                       progress=progress)
        figures[name] = {k: round(float(report[k]), 2) for k in ("add_auc", "add_mean_mm", "kp2d_fit_median_px")
                         if report.get(k) is not None}
    return figures


def format_adaptation(result: AdaptResult) -> str:
    """The lines `holo-pose adapt` prints: what was read, found, labelled and trained, and where the model is."""
    lines = [f"{len(result.source.frames)} images ({result.source.kind}"
             + (", with joint states" if result.source.has_joints else "") + f"): robot found in {result.n_found}"
             + (f", {len(result.labels)} pseudo-labels kept of {result.n_candidates} found twice"
                if result.finetune is not None else "") + "; BatchNorm statistics re-estimated on them"]
    if result.source.skipped:
        lines.append("skipped: " + ", ".join(f"{n} {why}" for why, n in result.source.skipped.items()))
    if result.finetune is not None:
        f = result.finetune
        lines.append(f"fine-tuned {f.steps} steps in {f.seconds / 60:.1f} min: " + ", ".join(
            f"{name} {f.first(name):.3f} -> {f.last(name):.3f}" for name in f.history))
    for name, figures in result.figures.items():
        lines.append(f"{name} on the source frames: AUC {figures.get('add_auc', float('nan')):.1f}, mean ADD "
                     f"{figures.get('add_mean_mm', float('nan')):.0f} mm, fit keypoints "
                     f"{figures.get('kp2d_fit_median_px', float('nan')):.1f} px")
    lines.append(f"adapted model: {result.card} ({result.seconds / 60:.1f} min); use it with --model {result.card} "
                 f"or -p model:={result.card}")
    return "\n".join(lines)
