"""Locate the package's shipped data files (config/, weights/) in a source checkout, a pip install or an
ament (colcon) install, in that order."""

from __future__ import annotations

import sys
from pathlib import Path

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
