"""Resolve a robot's URDF (from an installed distribution, a file or a string) and its mesh file names."""

from __future__ import annotations

import importlib.metadata
import os
from functools import lru_cache
from pathlib import Path

from holo_pose_ros.robots.spec import UrdfSource


@lru_cache(maxsize=None)
def find_in_distribution(package: str, path: str) -> Path:
    """The installed file of distribution `package` whose path ends with `path` (e.g. example-robot-data's
    `robots/panda_description/urdf/panda.urdf`, which cmeel installs under `cmeel.prefix/share/...`)."""
    try:
        files = importlib.metadata.files(package) or []
    except importlib.metadata.PackageNotFoundError as e:
        raise FileNotFoundError(f"robot description package '{package}' is not installed (pip install {package})") from e
    suffix = "/" + path.strip("/")
    for f in files:
        if ("/" + str(f)).endswith(suffix):
            located = Path(str(f.locate()))
            if located.is_file():
                return located
    raise FileNotFoundError(f"'{path}' not found in the installed distribution '{package}'")


def urdf_file(source: UrdfSource) -> Path | None:
    """The URDF's path on disk, or None when the URDF is given as a string."""
    if source.string is not None:
        return None
    if source.file is not None:
        path = Path(os.path.expanduser(source.file))
        if not path.is_file():
            raise FileNotFoundError(f"URDF file not found: {path}")
        return path
    return find_in_distribution(source.package, source.path)


def urdf_text(source: UrdfSource) -> str:
    """The URDF XML text."""
    path = urdf_file(source)
    return source.string if path is None else path.read_text()


def resolve_mesh_filename(filename: str, urdf_dir: Path | None) -> str:
    """Map a URDF mesh reference to a file: `package://NAME/rest` is looked up in the ancestor folder of the URDF
    named NAME (ROS share layout), then relative to the URDF folder (pybullet's `package://meshes/...`);
    `file://` and relative paths are taken as they are / relative to the URDF."""
    if filename.startswith("file://"):
        return filename[len("file://"):]
    if filename.startswith("package://"):
        name, _, rest = filename[len("package://"):].partition("/")
        candidates = []
        if urdf_dir is not None:
            for ancestor in [urdf_dir, *urdf_dir.parents]:
                if ancestor.name == name:
                    candidates.append(ancestor / rest)
                    break
            candidates.append(urdf_dir / name / rest)
            candidates.append(urdf_dir / rest)
        for c in candidates:
            if c.is_file():
                return str(c)
        raise FileNotFoundError(f"cannot resolve mesh '{filename}' (tried {', '.join(map(str, candidates))})")
    if urdf_dir is not None and not os.path.isabs(filename):
        return str(urdf_dir / filename)
    return filename
