"""Weights as data: a safetensors file (no pickle) plus a YAML model card beside it naming the robot, the network
configuration, how it was trained and what it scored. `--model panda` resolves to the shipped card."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import torch
import yaml
from safetensors.torch import load_file, save_file

from holo_pose_ros.model.network import HolisticNet, load_model_config
from holo_pose_ros.resources import weights_dir
from holo_pose_ros.robots.kinematics import RobotModel


def resolve_model(model: str | Path) -> Path:
    """A model card path from a shipped name ('panda'), a card (.yaml) or a weights file (.safetensors)."""
    path = Path(model)
    if path.suffix == ".safetensors":
        path = path.with_suffix(".yaml")
    elif not path.suffix:
        path = weights_dir() / f"{model}.yaml"
        if not path.is_file():
            raise ValueError(f"no shipped model '{model}'; shipped: {', '.join(shipped_models()) or 'none'}")
    if not path.is_file():
        raise FileNotFoundError(f"model card not found: {path}")
    return path


def shipped_models() -> list[str]:
    """Names of the shipped models (their cards in holo_pose_ros/weights; lifter cards, `*_lifter.yaml`, aside)."""
    return sorted(p.stem for p in weights_dir().glob("*.yaml") if not p.stem.endswith("_lifter"))


def read_card(model: str | Path) -> tuple[Path, dict]:
    """(card path, card) of a shipped name or a card/weights path."""
    card_path = resolve_model(model)
    with open(card_path) as f:
        return card_path, yaml.safe_load(f)


def save_model(net: HolisticNet, robot: str, path: str | Path, card: dict | None = None,
               dtype: torch.dtype = torch.float32) -> Path:
    """Write `path`.safetensors and its card `path`.yaml (robot, model config, plus `card`). float16 halves the
    file (shipped weights); loading casts back to float32."""
    path = Path(path).with_suffix("")
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().to(dtype).cpu().contiguous() for k, v in net.state_dict().items() if v.dtype.is_floating_point}
    save_file(state, str(path.with_suffix(".safetensors")), metadata={"robot": robot, "config": net.cfg.name})
    full_card = {"robot": robot, "weights": path.with_suffix(".safetensors").name, "model": net.cfg.to_dict(), **(card or {})}
    with open(path.with_suffix(".yaml"), "w") as f:
        yaml.safe_dump(full_card, f, sort_keys=False)
    return path.with_suffix(".yaml")


ROBOT_SPECIFIC = ("joint_mid", "joint_half", "joint_net.initial", "depth_head.log_lambda0")


def transfer_weights(net: HolisticNet, model: str | Path) -> tuple[int, int]:
    """Warm-start `net` from another model (usually another robot's shipped weights): copy every tensor whose
    name and shape match, except what belongs to the donor's robot (joint limits, initial joints, lambda_0).
    Returns (tensors copied, tensors left as initialized)."""
    card_path, card = read_card(model)
    if card["model"]["backbone"] != net.cfg.backbone or card["model"]["depth_backbone"] != net.cfg.depth_backbone:
        raise ValueError(f"{card_path}: backbones {card['model']['backbone']}/{card['model']['depth_backbone']} "
                         f"differ from this network's {net.cfg.backbone}/{net.cfg.depth_backbone}")
    donor = load_file(str(card_path.parent / card["weights"]))
    own = net.state_dict()
    copied = {k: v.to(own[k].dtype) for k, v in donor.items()
              if k in own and own[k].shape == v.shape and k not in ROBOT_SPECIFIC}
    net.load_state_dict(copied, strict=False)
    return len(copied), len(own) - len(copied)


def load_model(model: str | Path, device: str | torch.device = "cpu") -> tuple[HolisticNet, RobotModel, dict]:
    """(network in eval mode, its robot, its card) from a shipped name or a card/weights path."""
    card_path, card = read_card(model)
    robot = RobotModel(card["robot"], device=device)
    cfg = load_model_config(card["model"])
    net = HolisticNet(replace(cfg, pretrained=False, depth_pretrained=False), robot)  # the weights come from the file
    net.cfg = cfg
    state = load_file(str(card_path.parent / card["weights"]))
    missing, unexpected = net.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.endswith("num_batches_tracked")]
    if missing or unexpected:
        raise ValueError(f"{card_path}: weights do not match the network (missing {missing[:5]}, unexpected {unexpected[:5]})")
    return net.to(device).eval(), robot, card
