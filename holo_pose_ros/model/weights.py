"""Weights as data: a safetensors file (no pickle) plus a YAML model card beside it naming the robot, the network
configuration, the weights' sha256, how it was trained and what it scored. `--model panda` resolves to the shipped
card. Loading checks the card's keys, the weights' existence, hash, format and robot before building anything, and
fails with one ModelLoadError naming the file and what is wrong."""

from __future__ import annotations

from dataclasses import fields, replace
from pathlib import Path

import torch
import yaml
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

from holo_pose_ros.model.cards import MODEL_CARD_KEYS, ModelLoadError, check_card_keys, file_sha256, read_card
from holo_pose_ros.model.network import HolisticNet, ModelConfig, load_model_config
from holo_pose_ros.robots.kinematics import RobotModel


def read_weights(card_path: Path, card: dict) -> dict[str, torch.Tensor]:
    """The card's safetensors tensors, after checking that the file exists, has the sha256 the card records
    (cards written before the hash was recorded are only format-checked) and was saved for the card's robot.
    safetensors holds raw tensors only: nothing is unpickled or executed."""
    path = card_path.parent / str(card["weights"])
    if not path.is_file():
        raise ModelLoadError(f"{card_path}: its weights file {path} does not exist")
    recorded = card.get("weights_sha256")
    if recorded is not None and file_sha256(path) != recorded:
        raise ModelLoadError(f"{path}: sha256 {file_sha256(path)} differs from the {recorded} that {card_path.name} "
                             "records: the weights were altered, truncated or replaced")
    try:
        with safe_open(str(path), framework="pt") as f:
            metadata = f.metadata() or {}
        state = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as e:
        raise ModelLoadError(f"{path}: not a readable safetensors file ({e})") from e
    if metadata.get("robot", card["robot"]) != card["robot"]:
        raise ModelLoadError(f"{path}: weights saved for robot '{metadata['robot']}', but {card_path.name} is a "
                             f"'{card['robot']}' card")
    return state


def save_model(net: HolisticNet, robot: str, path: str | Path, card: dict | None = None,
               dtype: torch.dtype = torch.float32) -> Path:
    """Write `path`.safetensors and its card `path`.yaml (robot, model config, plus `card`). float16 halves the
    file (shipped weights); loading casts back to float32."""
    path = Path(path).with_suffix("")
    unknown = sorted(set(card or {}) - MODEL_CARD_KEYS)
    if unknown:
        raise ValueError(f"save_model: unknown card keys {unknown}; known: {sorted(MODEL_CARD_KEYS)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().to(dtype).cpu().contiguous() for k, v in net.state_dict().items() if v.dtype.is_floating_point}
    save_file(state, str(path.with_suffix(".safetensors")), metadata={"robot": robot, "config": net.cfg.name})
    full_card = {"robot": robot, "weights": path.with_suffix(".safetensors").name,
                 "weights_sha256": file_sha256(path.with_suffix(".safetensors")), "model": net.cfg.to_dict(), **(card or {})}
    with open(path.with_suffix(".yaml"), "w") as f:
        yaml.safe_dump(full_card, f, sort_keys=False)
    return path.with_suffix(".yaml")


ROBOT_SPECIFIC = ("joint_mid", "joint_half", "joint_net.initial", "depth_head.log_lambda0")


def transfer_weights(net: HolisticNet, model: str | Path, whole: bool = False) -> tuple[int, int]:
    """Warm-start `net` from another model (usually another robot's shipped weights): copy every tensor whose
    name and shape match, except what belongs to the donor's robot (joint limits, initial joints, lambda_0);
    with `whole`, those too (the donor must be of the same robot: the network is extended, not transferred).
    Returns (tensors copied, tensors left as initialized)."""
    card_path, card = read_card(model)
    if whole and card["robot"] != net.robot_name:
        raise ValueError(f"{card_path}: a '{card['robot']}' model cannot be extended into a '{net.robot_name}' network")
    if card["model"]["backbone"] != net.cfg.backbone or card["model"]["depth_backbone"] != net.cfg.depth_backbone:
        raise ValueError(f"{card_path}: backbones {card['model']['backbone']}/{card['model']['depth_backbone']} "
                         f"differ from this network's {net.cfg.backbone}/{net.cfg.depth_backbone}")
    donor = load_file(str(card_path.parent / card["weights"]))
    own = net.state_dict()
    copied = {k: v.to(own[k].dtype) for k, v in donor.items()
              if k in own and own[k].shape == v.shape and (whole or k not in ROBOT_SPECIFIC)}
    net.load_state_dict(copied, strict=False)
    return len(copied), len(own) - len(copied)


def load_model(model: str | Path, device: str | torch.device = "cpu") -> tuple[HolisticNet, RobotModel, dict]:
    """(network in eval mode, its robot, its card) from a shipped name or a card/weights path."""
    card_path, card = read_card(model)
    check_card_keys(card_path, card, MODEL_CARD_KEYS, ("robot", "weights", "model"))
    if not isinstance(card["model"], dict) or set(card["model"]) - {f.name for f in fields(ModelConfig)}:
        known = sorted(f.name for f in fields(ModelConfig))
        raise ModelLoadError(f"{card_path}: 'model' must be a network configuration with keys among {known}")
    state = read_weights(card_path, card)
    try:
        robot = RobotModel(card["robot"], device=device)
        cfg = load_model_config(card["model"])
    except (TypeError, ValueError) as e:
        raise ModelLoadError(f"{card_path}: {e}") from e
    net = HolisticNet(replace(cfg, pretrained=False, depth_pretrained=False), robot)  # the weights come from the file
    net.cfg = cfg
    own = net.state_dict()
    wrong = [k for k, v in state.items() if k in own and own[k].shape != v.shape]
    missing = [k for k in own if k not in state and not k.endswith("num_batches_tracked")]
    unexpected = [k for k in state if k not in own]
    if missing or unexpected or wrong:
        raise ModelLoadError(f"{card_path}: weights do not match the network (missing {missing[:5]}, unexpected "
                             f"{unexpected[:5]}, other shapes {wrong[:5]}): a card of another robot or network?")
    net.load_state_dict(state, strict=False)
    return net.to(device).eval(), robot, card
