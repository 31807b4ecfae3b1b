"""Model and lifter cards without torch: resolving a shipped name or a path to its card, reading it, checking its
keys, hashing weights files. model/weights.py (which needs torch) builds and loads the networks on top of this;
light clients (the joint-state monitor) read cards with it alone."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import yaml

from holo_pose_ros.resources import weights_dir


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


class ModelLoadError(ValueError):
    """A model or lifter card, or its weights, cannot be used; the message names the file and the reason."""


# top-level keys of a model card (save_model, scripts/ship_model.py) and of a lifter card (model/lifter.py)
MODEL_CARD_KEYS = {"robot", "weights", "weights_sha256", "model", "lifter", "estimator", "training", "validation",
                   "test", "domain_shift", "adaptation"}
LIFTER_CARD_KEYS = {"kind", "robot", "weights", "weights_sha256", "fit_keypoints", "joints", "model", "training",
                    "validation"}


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def read_card_file(card_path: Path) -> dict:
    """The YAML mapping of a model or lifter card file; ModelLoadError naming it when it is not one."""
    try:
        with open(card_path) as f:
            card = yaml.safe_load(f)
    except yaml.YAMLError as e:
        raise ModelLoadError(f"{card_path}: not a valid YAML card ({e})") from e
    if not isinstance(card, dict):
        raise ModelLoadError(f"{card_path}: a card must be a YAML mapping, got {type(card).__name__}")
    return card


def read_card(model: str | Path) -> tuple[Path, dict]:
    """(card path, card) of a shipped name or a card/weights path; ModelLoadError when it is not a YAML mapping."""
    card_path = resolve_model(model)
    return card_path, read_card_file(card_path)


def rewrite_card(card_path: Path, card: dict) -> None:
    """Replace a card file with `card` (YAML, keys in their order) through a temporary file: an interrupted write
    leaves the old card whole."""
    temporary = card_path.with_suffix(".yaml.tmp")
    with open(temporary, "w") as f:
        yaml.safe_dump(card, f, sort_keys=False)
    os.replace(temporary, card_path)


def check_card_keys(card_path: Path, card: dict, known: set[str], required: tuple[str, ...]) -> None:
    """ModelLoadError on unknown top-level keys (a typo or another tool's file) or missing required ones."""
    unknown = sorted(set(card) - known)
    if unknown:
        raise ModelLoadError(f"{card_path}: unknown card keys {unknown}; known: {sorted(known)}")
    missing = [k for k in required if k not in card]
    if missing:
        raise ModelLoadError(f"{card_path}: card lacks {missing}")
