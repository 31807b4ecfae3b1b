"""Keypoint and mask consistency on the user's images (the paper's self-supervision): the fit-keypoint heatmaps
are trained towards the projection of the fitted kinematics (the pseudo-labels), which is a robot by construction
where the heatmaps are only evidence, and a network with a segmentation head has its mask trained towards the
silhouette our renderer draws at the fitted pose (silhouettes.py). Guarded against drift, as the adaptation probe
of December 2026 showed it must be: only the named modules train (by default the keypoint head), every BatchNorm
layer keeps the statistics of the user's images (the network stays in eval mode), the learning rate is small, and
every step also trains on rendered views with their true labels and the full supervised loss."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from holo_pose_ros.adaptation.crops import jittered_box, network_input
from holo_pose_ros.adaptation.pseudo_labels import PseudoLabel
from holo_pose_ros.adaptation.silhouettes import SilhouetteRenderer
from holo_pose_ros.adaptation.sources import SourceFrame
from holo_pose_ros.geometry.crop import crop_affine
from holo_pose_ros.model.heatmaps import gaussian_targets, heatmap_cross_entropy
from holo_pose_ros.model.network import HolisticNet, add_kinematics
from holo_pose_ros.robots.kinematics import RobotModel


LOSS_NAMES = ("keypoint consistency", "mask consistency", "rendered views")  # the per-step losses recorded


@dataclass
class FinetuneResult:
    """What the fine-tuning did: steps, seconds, and every step's losses by name (LOSS_NAMES; mask consistency
    only for a network with a segmentation head and a non-zero weight)."""

    steps: int
    seconds: float
    history: dict[str, np.ndarray]

    def first(self, name: str) -> float:
        """Mean of the loss over the first tenth of the steps (nan without steps)."""
        h = self.history[name]
        return float(h[:max(len(h) // 10, 1)].mean()) if len(h) else float("nan")

    def last(self, name: str) -> float:
        """Mean of the loss over the last tenth of the steps (nan without steps)."""
        h = self.history[name]
        return float(h[-max(len(h) // 10, 1):].mean()) if len(h) else float("nan")


def pseudo_batch(frames: list[SourceFrame], labels: list[PseudoLabel], size: int, batch_size: int,
                 rng: np.random.Generator, silhouettes: SilhouetteRenderer | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """(B, 3, S, S) jittered crops of randomly chosen pseudo-labelled frames, their (B, 3, 3) intrinsics, the
    labels' fit keypoints in crop px (B, M, 2), whether each is in the crop and the image (B, M), and with
    `silhouettes` the fitted robot's (B, S, S) bool silhouette in each crop (else None)."""
    images, Ks, uvs, seen, masks = [], [], [], [], []
    for i in rng.integers(len(labels), size=batch_size):
        label = labels[i]
        frame = frames[label.frame]
        box = jittered_box(label.box, rng)
        x, K = network_input(frame.image, frame.K, box, size)
        A = crop_affine(box, size)
        uv = label.uv_fit_px @ A[:2, :2].T + A[:2, 2]
        images.append(x)
        Ks.append(K)
        uvs.append(uv.astype(np.float32))
        seen.append(label.visible_fit & (uv >= -0.5).all(1) & (uv <= size - 0.5).all(1))
        if silhouettes is not None:
            H, W = frame.image.shape[:2]
            masks.append(silhouettes(label.joints, label.T_cam_base, K, box, W, H))  # K: the crop's intrinsics
    return (torch.from_numpy(np.stack(images)), torch.from_numpy(np.stack(Ks)), torch.from_numpy(np.stack(uvs)),
            torch.from_numpy(np.stack(seen)), torch.from_numpy(np.stack(masks)) if masks else None)


def trainable(net: HolisticNet, prefixes: list[str]) -> list[torch.nn.Parameter]:
    """Freeze every parameter whose name starts with none of `prefixes`; the ones that train."""
    chosen = []
    for name, parameter in net.named_parameters():
        train = any(name.startswith(p) for p in prefixes)
        parameter.requires_grad_(train)
        if train:
            chosen.append(parameter)
    if not chosen:
        raise ValueError(f"finetune.train {prefixes}: no parameter of the network starts with these names")
    return chosen


def render_synthetic(robot: str, size: int, generator: str, n: int, seed: int, progress: bool) -> list[dict]:
    """`n` rendered training views with their true labels (data/training.py), made once and reused."""
    from holo_pose_ros.data.generator import load_generator_config
    from holo_pose_ros.data.training import RenderedViews, SampleConfig

    views = RenderedViews(robot, SampleConfig(size, mode_probabilities=(0.85, 0.10, 0.05)),
                          load_generator_config(generator), seed=seed, length=n)
    return [views[i] for i in tqdm(range(n), desc="render synthetic views", unit="view", disable=not progress)]


def finetune(net: HolisticNet, robot: RobotModel, frames: list[SourceFrame], labels: list[PseudoLabel],
             synthetic: list[dict], cfg: dict, seconds: float, progress: bool = True, seed: int = 0,
             check_interrupt: Callable[[], None] | None = None) -> FinetuneResult:
    """Train `net` in place for at most `cfg['steps']` steps or `seconds` of wall clock: each step one batch of
    pseudo-labelled crops (heatmap cross-entropy towards the labels, weight cfg['consistency_weight']; with a
    segmentation head, the mask's cross-entropy towards the rendered silhouette of the label's pose, weight
    cfg['mask_consistency_weight']) and one of the rendered views (the losses cfg['synthetic_losses']). The
    network is left in eval mode. `check_interrupt` runs before each step (interrupts.sigint_latch: a Ctrl-C is
    never lost)."""
    from holo_pose_ros.train.losses import mask_loss, supervised_losses, total_loss

    rng = np.random.default_rng(seed)
    size, sigma = net.cfg.input_size, net.cfg.heatmap_sigma
    mask_weight = float(cfg.get("mask_consistency_weight", 0.0)) if net.cfg.segmentation else 0.0
    silhouettes = SilhouetteRenderer(robot.name, size) if mask_weight > 0 else None
    parameters = trainable(net, list(cfg["train"]))
    optimizer = torch.optim.AdamW(parameters, lr=float(cfg["lr"]), weight_decay=0.0)
    net.eval()  # BatchNorm keeps the user's statistics; no dropout
    history: dict[str, list[float]] = {name: [] for name in LOSS_NAMES if name != "mask consistency" or mask_weight}
    start, step = time.perf_counter(), 0
    bar = tqdm(total=int(cfg["steps"]), desc="adapt", unit="step", disable=not progress)
    while step < int(cfg["steps"]) and time.perf_counter() - start < seconds:
        if check_interrupt is not None:
            check_interrupt()
        images, Ks, uv, seen, masks = pseudo_batch(frames, labels, size, int(cfg["batch_size"]), rng, silhouettes)
        out = net(images, Ks)
        targets = gaussian_targets(uv, out["heatmap_logits"].shape[-1], size, sigma)
        losses = {"keypoint consistency": heatmap_cross_entropy(out["heatmap_logits"], targets, seen)}
        if masks is not None:
            losses["mask consistency"] = mask_loss(out["mask_logits"], masks)
        chosen = rng.integers(len(synthetic), size=int(cfg["synthetic_batch_size"]))
        batch = {k: torch.stack([synthetic[i][k] for i in chosen]) for k in synthetic[0]}
        out_s = add_kinematics(robot, {k: v.float() for k, v in net(batch["image"], batch["K_crop"]).items()})
        terms = supervised_losses(out_s, batch, net.joint_mid, net.joint_half, size, sigma)
        losses["rendered views"] = total_loss(terms, cfg["synthetic_losses"])
        loss = (float(cfg["consistency_weight"]) * losses["keypoint consistency"] + losses["rendered views"]
                + (mask_weight * losses["mask consistency"] if masks is not None else 0.0))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(parameters, 5.0)
        optimizer.step()
        step += 1
        for name, value in losses.items():
            history[name].append(float(value.detach()))
        bar.update()
        bar.set_postfix({name.split()[0]: f"{h[-1]:.3f}" for name, h in history.items()})
    bar.close()
    for parameter in net.parameters():
        parameter.requires_grad_(True)
    net.eval()
    return FinetuneResult(step, time.perf_counter() - start, {name: np.array(h) for name, h in history.items()})
