"""The staged training loop (paper §3.5): DepthNet pretraining, then the whole network end to end on rendered
views. Resumable checkpoints, a CSV log per validation interval, the kept model chosen on a generated validation
folder scored through the deployed estimator (never a test set). AMP and channels_last on a GPU; several GPUs
with torchrun (DDP)."""

from __future__ import annotations

import csv
import math
import os
import time
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import yaml
from tqdm import tqdm

from holo_pose_ros.data.generator import generate, load_generator_config
from holo_pose_ros.data.training import RenderedViews, SampleConfig
from holo_pose_ros.model.heads import reference_depth
from holo_pose_ros.model.network import HolisticNet, add_kinematics, load_model_config
from holo_pose_ros.model.weights import save_model, transfer_weights
from holo_pose_ros.robots.kinematics import RobotModel
from holo_pose_ros.train.losses import supervised_losses, total_loss
from holo_pose_ros.train.style_noise import FeatureStatisticsNoise


def load_train_config(path: str | Path) -> dict:
    with open(path) as f:
        cfg = yaml.safe_load(f)
    for key in ("robot", "model", "generator", "out", "stages", "batch_size"):
        if key not in cfg:
            raise ValueError(f"{path}: missing required key '{key}'")
    return cfg


def lr_factor(step: int, steps: int, warmup: int) -> float:
    """Linear warm-up, then cosine decay to 5 % of the stage's learning rate."""
    if step < warmup:
        return (step + 1) / warmup
    progress = (step - warmup) / max(1, steps - warmup)
    return 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))


def freeze_first_blocks(net: HolisticNet, blocks: int) -> list[torch.nn.Module]:
    """Freeze the stem and the first `blocks` blocks of an EfficientNet-Lite backbone: no gradients and fixed
    BatchNorm statistics (their modules stay in eval mode). Their backward is most of a step's cost on the CPU
    (Lite0 at 192 px, batch 24: 1.25 s -> 0.61 s a step with 5 blocks frozen); low-level features transfer."""
    if blocks <= 0:
        return []
    trunk = getattr(net.backbone, "net", None)
    if trunk is None or not hasattr(trunk, "_blocks"):
        raise ValueError("freeze_blocks needs an EfficientNet-Lite backbone")
    frozen = [trunk._conv_stem, trunk._bn0, *trunk._blocks[:blocks]]
    for module in frozen:
        module.requires_grad_(False)
        module.eval()
    return frozen


def train_only(net: HolisticNet, prefixes: list[str]) -> list[torch.nn.Module]:
    """Freeze every parameter whose name starts with none of `prefixes` and keep the whole network in eval mode
    (fixed BatchNorm statistics, no dropout): trains a new output layer on a shipped network without changing
    anything it computed before. The trained modules must not depend on the mode (no BatchNorm, no dropout)."""
    names = [name for name, _ in net.named_parameters()]
    trained = [n for n in names if any(n.startswith(p) for p in prefixes)]
    if not trained:
        raise ValueError(f"train_only {prefixes}: no parameter of the network starts with these names")
    for name, parameter in net.named_parameters():
        parameter.requires_grad_(name in trained)
    return [net]


def _campaign_so_far(init_from: str | None, robot: str) -> tuple[int, float]:
    """(views, wall-clock training hours) that the warm-start model's card records; (0, 0) without one, and for a
    donor of another robot (a transfer starts the robot's campaign: its views were of the donor's robot)."""
    if not init_from:
        return 0, 0.0
    from holo_pose_ros.model.cards import read_card

    card = read_card(init_from)[1]
    if card.get("robot") != robot:
        return 0, 0.0
    training = card.get("training") or {}
    return int(training.get("cumulative_views", training.get("samples", 0))), float(training.get("cumulative_train_hours", 0.0))


def _append_row(path: Path, row: dict) -> None:
    """Append a row to a CSV log; a log written by an older version, with fewer columns, is rewritten with the
    new header first (its rows get empty cells), so a resumed run never misaligns its columns."""
    if path.exists():
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            fields, rows = list(reader.fieldnames or []), list(reader)
        if set(row) - set(fields):
            fields += [k for k in row if k not in fields]
            with open(path, "w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=fields)
                writer.writeheader()
                writer.writerows(rows)
    else:
        fields = list(row)
    with open(path, "a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        if f.tell() == 0:
            writer.writeheader()
        writer.writerow(row)


class Trainer:
    """Owns the model, data, optimizer and bookkeeping of one training run."""

    def __init__(self, cfg: dict, device: str | None = None, progress: bool = True):
        self.cfg, self.progress = cfg, progress
        self.distributed = int(os.environ.get("WORLD_SIZE", "1")) > 1
        if self.distributed:
            dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
        self.rank = dist.get_rank() if self.distributed else 0
        if device is None:
            device = f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}" if torch.cuda.is_available() else "cpu"
        self.device = torch.device(device)
        self.cuda = self.device.type == "cuda"
        # the training forward under bfloat16 autocast (losses in float32): on GPUs always; on a CPU with AVX-512 BF16
        # or AMX where the config asks (`bf16: true`; the Panda recipe's step 1.23 -> 0.90 s, docs/speed.md)
        self.bf16 = bool(cfg.get("bf16", self.cuda))
        if self.bf16 and not self.cuda and not torch.ops.mkldnn._is_mkldnn_bf16_supported():
            # without native bfloat16 (an AVX2-only CPU) autocast emulates it: a step took 30-40 s instead of 1.2
            warnings.warn("bf16: this CPU has no native bfloat16 (AVX-512 BF16 or AMX); training in float32")
            self.bf16 = False
        torch.manual_seed(cfg.get("seed", 0))
        self.out = Path(cfg["out"])
        self.out.mkdir(parents=True, exist_ok=True)
        self.robot = RobotModel(cfg["robot"], device=self.device)
        self.model_cfg = load_model_config(cfg["model"])
        self.net = HolisticNet(self.model_cfg, self.robot).to(self.device)
        self.frozen = freeze_first_blocks(self.net, cfg.get("freeze_blocks", 0))
        if cfg.get("train_only"):
            self.frozen = train_only(self.net, cfg["train_only"])
        self.net = self.net.to(memory_format=torch.channels_last)  # faster on the CPU too (depthwise convolutions)
        views = cfg.get("views", {})
        self.sample_cfg = SampleConfig(
            self.model_cfg.input_size,
            mode_probabilities=tuple(views.get("mode_probabilities", (0.75, 0.15, 0.10))),
            shift_sigma=views.get("shift_sigma", 0.08), scale_range=tuple(views.get("scale_range", (0.85, 1.3))))
        self.generator_cfg = load_generator_config(cfg["generator"])
        self.step, self.stage_index, self.best_auc = 0, 0, -1.0
        self.best_add_mm = math.inf  # breaks ties of the AUC (early in training it is 0 for every checkpoint)
        self.best_kp2d_px = math.inf  # the kept-model criterion of networks with fit heatmaps
        self.total_steps = sum(s["steps"] for s in cfg["stages"])
        # cumulative over a campaign: the warm-start model's own training, then this run's (restored on resume)
        self.views_before, self.hours_before = _campaign_so_far(cfg.get("init_from"), cfg["robot"])
        self.hours_this_run, self._clock = 0.0, time.perf_counter()

    # -- data ----------------------------------------------------------------------------------------------
    def _loader(self, count: int) -> torch.utils.data.DataLoader:
        """The next `count` views of this rank's stream (deterministic), from index = the campaign's view count so
        far: a resumed run, and a new run warm-started from a shipped card, both see views never seen before."""
        start = self._views()
        seed = self.cfg.get("seed", 0) * 1000 + self.rank
        dataset = torch.utils.data.Subset(RenderedViews(self.cfg["robot"], self.sample_cfg, self.generator_cfg, seed,
                                                        start + count), range(start, start + count))
        workers = self.cfg.get("num_workers", 1)
        return torch.utils.data.DataLoader(dataset, batch_size=self.cfg["batch_size"], num_workers=workers,
                                           pin_memory=self.cuda, persistent_workers=False,
                                           multiprocessing_context="spawn" if workers else None, drop_last=True)

    def calibrate_depth_scale(self, n: int) -> float:
        """Set DepthNet's lambda_0 to the median of d / d_c over `n` rendered crop views."""
        dataset = RenderedViews(self.cfg["robot"], SampleConfig(self.model_cfg.input_size, mode_probabilities=(1.0, 0.0, 0.0)),
                                self.generator_cfg, seed=-1 % 2**31, length=n)
        ratios = []
        for i in range(n):
            s = dataset[i]
            d_c = reference_depth(s["K_crop"][None], self.model_cfg.input_size, self.net.reference_side_m)
            ratios.append(float(s["t_root"][2] / d_c))
        lam = float(np.median(ratios))
        self.net.depth_head.log_lambda0.fill_(math.log(lam))
        return lam

    def validation_folder(self) -> Path:
        """The generated validation folder (made once, reused)."""
        v = self.cfg["validation"]
        folder = self.out / f"val_seed{v['seed']}"
        if not (folder / f"{v['frames'] - 1:06d}.json").exists():
            generate(self.cfg["robot"], v["frames"], folder, seed=v["seed"], config=v.get("config", "randomized"),
                     progress=False)
        return folder

    # -- checkpoints ---------------------------------------------------------------------------------------
    def save_checkpoint(self, optimizer) -> None:
        torch.save({"net": self.net.state_dict(), "optimizer": optimizer.state_dict(), "step": self.step,
                    "stage_index": self.stage_index, "best_auc": self.best_auc, "best_add_mm": self.best_add_mm,
                    "best_kp2d_px": self.best_kp2d_px, "hours": self._train_hours() - self.hours_before,
                    "views_before": self.views_before, "hours_before": self.hours_before},
                   self.out / "last.pt")

    def load_checkpoint(self) -> dict | None:
        """Restore the resumable checkpoint `last.pt` this trainer wrote into its own run directory. It is the
        package's only pickle-format file (model weights and optimizer state, read with torch's restricted
        `weights_only` unpickler); shipped and user models are safetensors, which `model/weights.py` reads."""
        path = self.out / "last.pt"
        if not path.exists():
            return None
        state = torch.load(path, map_location=self.device, weights_only=True)
        self.net.load_state_dict(state["net"])
        self.step, self.stage_index, self.best_auc = state["step"], state["stage_index"], state["best_auc"]
        self.best_add_mm = state.get("best_add_mm", math.inf)
        self.best_kp2d_px = state.get("best_kp2d_px", math.inf)
        self.hours_this_run, self._clock = state.get("hours", 0.0), time.perf_counter()
        # what the campaign had seen when this run started (init_from may since name this run's own shipped card)
        self.views_before = state.get("views_before", self.views_before)
        self.hours_before = state.get("hours_before", self.hours_before)
        return state

    def _attach_frozen_prefix(self) -> None:
        """On the CPU (`frozen_backend: onnxruntime`, the default there), the frozen stem and blocks run in ONNX
        Runtime during training steps, exported from the weights just loaded (train/frozen_prefix.py)."""
        backend = self.cfg.get("frozen_backend", "torch" if self.cuda else "onnxruntime")
        if backend not in ("torch", "onnxruntime"):
            raise ValueError(f"frozen_backend must be torch or onnxruntime, got '{backend}'")
        if not self.frozen or backend == "torch" or self.cfg.get("train_only"):
            return
        if self.cuda:
            raise ValueError("frozen_backend: onnxruntime is for CPU training")
        from holo_pose_ros.train.frozen_prefix import OnnxFrozenPrefix

        self.net.backbone.frozen_prefix = OnnxFrozenPrefix(
            self.net.backbone, self.cfg["freeze_blocks"], self.model_cfg.input_size,
            self.out / f"frozen_prefix_rank{self.rank}.onnx", threads=torch.get_num_threads())

    def _attach_style_noise(self) -> None:
        """`style_noise: {probability, scale, after_blocks}`: the maps leaving the frozen blocks (and those leaving
        each of `after_blocks`, backbone block indices, when given) get their channel statistics redrawn while
        training (train/style_noise.py), so that the trained layers learn not to lean on them."""
        if not self.cfg.get("style_noise"):
            return
        cfg = dict(self.cfg["style_noise"])
        after = cfg.pop("after_blocks", None)
        noise = FeatureStatisticsNoise.from_config(cfg) or FeatureStatisticsNoise()   # {after_blocks} alone: defaults
        freeze = self.cfg.get("freeze_blocks", 0)
        if freeze <= 0 or not hasattr(self.net.backbone, "style_noise"):
            raise ValueError("style_noise needs an EfficientNet-Lite backbone with freeze_blocks > 0: the noise "
                             "restyles the maps that leave the frozen blocks")
        blocks = len(self.net.backbone.net._blocks)
        after = [freeze - 1] if after is None else sorted({int(i) for i in after})
        if not after or after[0] < freeze - 1 or after[-1] >= blocks:
            raise ValueError(f"style_noise.after_blocks {after}: block indices from the frozen blocks' last "
                             f"({freeze - 1}) to the backbone's last ({blocks - 1})")
        self.net.backbone.style_noise = noise
        self.net.backbone.style_noise_after = tuple(after)

    def _param_groups(self, stage: dict) -> list[dict]:
        """The trainable parameters in two groups: the heads (first; the logged lr is theirs) and the backbone,
        whose learning rate is the stage's times `backbone_lr_factor` (default 1). A stage that trains a freshly
        initialized head with factor 0 keeps the head's first, large and random gradients out of the backbone."""
        backbone = {id(p) for p in self.net.backbone.parameters()}
        trainable = [p for p in self.net.parameters() if p.requires_grad]
        return [{"params": [p for p in trainable if id(p) not in backbone], "lr_scale": 1.0},
                {"params": [p for p in trainable if id(p) in backbone], "lr_scale": float(stage.get("backbone_lr_factor", 1.0))}]

    def _train_hours(self) -> float:
        """Cumulative wall-clock training hours (on this machine's cores) of the campaign so far."""
        return self.hours_before + self.hours_this_run + (time.perf_counter() - self._clock) / 3600

    def _views(self) -> int:
        """Cumulative training views of the campaign so far."""
        return self.views_before + self.step * self.cfg["batch_size"]

    # -- the loop ------------------------------------------------------------------------------------------
    def validate(self) -> dict:
        """Score the current network through the deployed estimator on the validation folder, with the 2D error of
        its keypoint evidence (pixels of the 640 x 480 frame)."""
        from holo_pose_ros.data.dream import DreamReader
        from holo_pose_ros.estimator import Estimator
        from holo_pose_ros.evaluation.run import evaluate_folder, evaluate_methods

        self.net.eval()
        lifter = self._validation_lifter()
        estimator = Estimator(self.net, self.robot, self.device, lifter=lifter)
        reader = DreamReader(self.validation_folder(), self.cfg["robot"])
        if lifter is None:
            report, _, _ = evaluate_folder(estimator, reader, progress=False)
        else:  # the same detections, feed-forward and fitted (what the product runs since the fit's depth prior)
            reports = evaluate_methods(estimator, reader, progress=False, known_joints=False)
            report = {**reports["feed-forward"], "fitted_add_auc": reports["fitted"]["add_auc"],
                      "fitted_add_mean_mm": reports["fitted"]["add_mean_mm"]}
        self.net.train()
        for module in self.frozen:
            module.eval()
        return report

    def _validation_lifter(self):
        """The lifter that validation fits with (`validation.lifter`, a lifter card; default the robot's shipped
        one), or None: for networks without fit heatmaps, or with `validation.lifter: none`."""
        if not self.model_cfg.fit_heatmaps:
            return None
        if not hasattr(self, "_lifter"):
            from holo_pose_ros.model.lifter import load_lifter, shipped_lifter

            path = self.cfg["validation"].get("lifter") or shipped_lifter(self.cfg["robot"])
            self._lifter = None if path is None or str(path) == "none" else load_lifter(path, self.device).eval()
        return self._lifter

    def run(self, resume: bool = False) -> Path | None:
        """Train every stage; returns the kept model card (rank 0)."""
        state = self.load_checkpoint() if resume else None
        if state is None:
            if self.cfg.get("init_from"):
                copied, fresh = transfer_weights(self.net, self.cfg["init_from"], whole=bool(self.cfg.get("train_only")))
                if self.rank == 0:
                    print(f"warm start from {self.cfg['init_from']}: {copied} tensors copied, {fresh} left as initialized")
            if not self.cfg.get("train_only"):  # a train_only run keeps its donor's DepthNet scale, like all else
                lam = self.calibrate_depth_scale(int(self.cfg.get("depth_calibration_views", 256)))
                if self.rank == 0:
                    print(f"DepthNet lambda_0 = {lam:.3f} (median d / d_c of rendered crops)")
        self._attach_frozen_prefix()
        self._attach_style_noise()
        self.net.train()
        for module in self.frozen:
            module.eval()
        # a stage may leave heads out of its loss (e.g. no heatmap term): DDP must not wait for their gradients
        net = torch.nn.parallel.DistributedDataParallel(self.net, find_unused_parameters=True) if self.distributed else self.net
        log_path = self.out / "log.csv"
        bar = tqdm(total=self.total_steps, initial=self.step, desc="train", unit="step", disable=self.rank != 0 or not self.progress)
        kept = self.out / "best.yaml" if self.best_auc >= 0 else None
        done_before = sum(s["steps"] for s in self.cfg["stages"][:self.stage_index])
        for stage_index in range(self.stage_index, len(self.cfg["stages"])):
            stage = self.cfg["stages"][stage_index]
            self.stage_index = stage_index
            optimizer = torch.optim.AdamW(self._param_groups(stage), lr=stage["lr"], weight_decay=self.cfg.get("weight_decay", 1e-4))
            if state is not None and state["stage_index"] == stage_index:
                optimizer.load_state_dict(state["optimizer"])
            stage_step = self.step - done_before
            sums, count, tick = {}, 0, time.perf_counter()
            loader = self._loader((stage["steps"] - stage_step) * self.cfg["batch_size"])
            for batch in loader:
                batch = {k: v.to(self.device, non_blocking=True) for k, v in batch.items()}
                for group in optimizer.param_groups:
                    group["lr"] = stage["lr"] * group["lr_scale"] * lr_factor(stage_step, stage["steps"], stage.get("warmup_steps", 0))
                image = batch["image"].to(memory_format=torch.channels_last)
                with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.bf16):
                    out = net(image, batch["K_crop"])
                out = {k: v.float() for k, v in out.items()}
                out = add_kinematics(self.robot, out)
                terms = supervised_losses(out, batch, self.net.joint_mid, self.net.joint_half, self.model_cfg.input_size,
                                          self.model_cfg.heatmap_sigma)
                loss = total_loss(terms, stage["losses"])
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(net.parameters(), self.cfg.get("grad_clip", 5.0))
                optimizer.step()
                self.step += 1
                stage_step += 1
                count += 1
                for k, v in {**terms, "loss": loss}.items():
                    sums[k] = sums.get(k, 0.0) + float(v.detach())
                bar.update()
                views_per_s = count * self.cfg["batch_size"] / max(time.perf_counter() - tick, 1e-9)
                bar.set_postfix(stage=stage["name"], loss=f"{float(loss.detach()):.3f}", views_s=f"{views_per_s:.1f}")
                every = self.cfg["validation"]["every_steps"]
                if self.rank == 0 and (stage_step % every == 0 or stage_step == stage["steps"]):
                    kept = self._end_interval(stage, optimizer, sums, count, time.perf_counter() - tick, log_path) or kept
                    sums, count, tick = {}, 0, time.perf_counter()
            done_before += stage["steps"]
            state = None
        bar.close()
        if self.distributed:
            dist.barrier()  # rank 0 may still be validating the last interval
            dist.destroy_process_group()
        return kept

    def _end_interval(self, stage: dict, optimizer, sums: dict, count: int, seconds: float, log_path: Path) -> Path | None:
        """Validate, log a CSV row, checkpoint, and keep the model if it is the best so far."""
        report = self.validate() if stage["name"] != "depth" else {}
        row = {"step": self.step, "stage": stage["name"], "lr": optimizer.param_groups[0]["lr"],
               "images_per_s": count * self.cfg["batch_size"] / max(seconds, 1e-9),
               **{f"loss_{k}": v / max(count, 1) for k, v in sums.items()},
               "views": self._views(), "train_hours": round(self._train_hours(), 4),
               **{f"val_{k}": report.get(k) for k in ("add_auc", "add_mean_mm", "n_not_found", "depth_error_mm",
                                                      "kp2d_dream_median_px", "kp2d_fit_median_px", "n_missed_2d",
                                                      "fitted_add_auc", "fitted_add_mean_mm")}}
        row["val_depth_error_mm"] = (report.get("depth_error_mm") or {}).get("mean")
        _append_row(log_path, row)
        auc = report.get("add_auc")
        add_mm = report.get("add_mean_mm")
        add_mm = math.inf if add_mm is None else add_mm
        kp2d = report.get("kp2d_fit_median_px")
        if self.cfg.get("train_only"):  # the extended network computes what its donor did: keep the latest layer
            improved = True
        elif self.model_cfg.fit_heatmaps:  # the fit's accuracy follows the 2D error of its evidence
            improved = kp2d is not None and kp2d < self.best_kp2d_px
        else:
            improved = auc is not None and (auc, -add_mm) > (self.best_auc, -self.best_add_mm)
        if improved:
            self.best_auc, self.best_add_mm = auc, add_mm
            self.best_kp2d_px = math.inf if kp2d is None else kp2d
        self.save_checkpoint(optimizer)  # once, with the best AUC so far, so a resumed run keeps the right best
        meta = {
            "training": {"config": self.cfg, "steps": self.step, "samples": self.step * self.cfg["batch_size"],
                         "cumulative_views": self._views(), "cumulative_train_hours": round(self._train_hours(), 3)},
            "validation": {k: report[k] for k in ("n_frames", "n_not_found", "add_auc", "add_mean_mm", "add_median_mm",
                                                  "kp2d_dream_median_px", "kp2d_fit_median_px", "fitted_add_auc",
                                                  "fitted_add_mean_mm") if k in report},
        }
        if self.cfg["validation"].get("snapshots"):  # every validated model, for a choice on other looks' folders
            save_model(self.net, self.cfg["robot"], self.out / "snapshots" / f"step_{self.step:06d}", meta)
        if improved:
            return save_model(self.net, self.cfg["robot"], self.out / "best", meta)
        return None
