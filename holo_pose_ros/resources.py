"""Locate the package's shipped data files (config/, weights/) in a source checkout, a pip install or an
ament (colcon) install, in that order."""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import yaml

PACKAGE_NAME = "holo_pose_ros"
_SOURCE_ROOT = Path(__file__).resolve().parent.parent


def _ament_share() -> Path | None:
    """share/<pkg> of a colcon/ament install, or None outside one."""
    try:
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory(PACKAGE_NAME))
    except (ImportError, LookupError, OSError):  # not installed, not indexed, or AMENT_PREFIX_PATH unset
        return None


def config_dir() -> Path:
    """The folder holding `robots/*.yaml` and the other YAML configuration files."""
    candidates = [_SOURCE_ROOT / "config", Path(sys.prefix) / "share" / PACKAGE_NAME / "config"]
    for path in candidates:
        if (path / "robots").is_dir():
            return path
    share = _ament_share()
    if share is not None and (share / "config" / "robots").is_dir():
        return share / "config"
    raise FileNotFoundError(
        f"{PACKAGE_NAME}: no config folder found; looked in " + ", ".join(str(p) for p in candidates)
        + " and the ament index"
    )


def weights_dir() -> Path:
    """The folder of shipped model weights (inside the Python package, so every install has it)."""
    return Path(__file__).resolve().parent / "weights"


def config_with_overrides(file_name: str, overrides: dict | str | Path | None, what: str) -> dict:
    """config/<file_name> (every default, documented there) with `overrides` (a mapping, or the path of a YAML file
    of the same keys) merged over it, nested mappings key by key; a top-level key the file lacks is a ValueError
    naming `what` (e.g. 'fitting parameters')."""
    with open(config_dir() / file_name) as f:
        defaults = yaml.safe_load(f)
    if overrides is None:
        return defaults
    if not isinstance(overrides, dict):
        with open(overrides) as f:
            overrides = yaml.safe_load(f) or {}
    unknown = set(overrides) - set(defaults)
    if unknown:
        raise ValueError(f"unknown {what} {sorted(unknown)}; known: {', '.join(sorted(defaults))}")
    return _merge(defaults, overrides)


def _merge(base: dict, override: dict) -> dict:
    """Deep merge of `override` into a copy of `base` (nested mappings merged, everything else replaced)."""
    out = copy.deepcopy(base)
    for k, v in override.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out
