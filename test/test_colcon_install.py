"""The install a ROS user does: `colcon build` of the package in a fresh workspace (colcon from PyPI, the test
extra) puts every node's executable where `ros2 run` looks (install/<pkg>/lib/<pkg>/), every config file under
share/<pkg>/config/, and the installed estimator_node, with the workspace sourced, runs from the installed copy and
exits 1 with the reason on a model that does not exist. Nothing is skipped: without colcon the test fails."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from importlib.metadata import distribution
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = "holo_pose_ros"
NOT_SOURCES = shutil.ignore_patterns(".git", ".venv", "runs", "data", "out", "build", "install", "log", "docs",
                                     "__pycache__", "*.egg-info", ".pytest_cache")


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    colcon = Path(sys.executable).parent / "colcon"
    assert colcon.is_file(), f"colcon is not installed beside {sys.executable}: pip install colcon-common-extensions"
    ws = tmp_path_factory.mktemp("colcon_ws")
    shutil.copytree(ROOT, ws / "src" / PACKAGE, ignore=NOT_SOURCES)
    env = {**os.environ, "PATH": f"{colcon.parent}{os.pathsep}{os.environ['PATH']}"}
    build = subprocess.run([str(colcon), "build", "--event-handlers", "console_direct-"], cwd=ws, env=env,
                           capture_output=True, text=True, timeout=600)
    assert build.returncode == 0, build.stdout + build.stderr
    assert "1 package finished" in build.stdout, build.stdout
    return ws


def test_every_console_script_lands_where_ros2_run_looks(workspace):
    scripts = {ep.name for ep in distribution(PACKAGE).entry_points if ep.group == "console_scripts"}
    assert {"estimator_node", "dream_replay_node", "evaluation_node"} <= scripts
    lib = workspace / "install" / PACKAGE / "lib" / PACKAGE
    for name in scripts:
        assert (lib / name).is_file() and os.access(lib / name, os.X_OK), name


def test_every_config_file_and_the_package_index_are_installed(workspace):
    share = workspace / "install" / PACKAGE / "share"
    configs = [p.relative_to(ROOT / "config") for p in (ROOT / "config").rglob("*") if p.is_file()]
    assert len(configs) > 10
    missing = [str(p) for p in configs if not (share / PACKAGE / "config" / p).is_file()]
    assert not missing, missing
    assert (share / PACKAGE / "package.xml").is_file()
    assert (share / "ament_index" / "resource_index" / "packages" / PACKAGE).is_file()


def _sourced(workspace: Path, command: str) -> subprocess.CompletedProcess:
    """`command` in bash with the workspace's install/setup.bash sourced, as a ROS user runs it."""
    script = f"source {workspace / 'install' / 'setup.bash'} && {command}"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run(["bash", "-c", script], cwd=workspace, env=env, capture_output=True, text=True, timeout=300)


def test_the_installed_node_runs_from_the_install_and_refuses_a_missing_model(workspace):
    where = _sourced(workspace, f"{sys.executable} -c 'import holo_pose_ros.resources as r; "
                                f"print(r.__file__); print(r.config_dir())'")
    assert where.returncode == 0, where.stderr
    module, config = where.stdout.split()
    assert Path(module).is_relative_to(workspace / "install"), module
    assert Path(config) == workspace / "install" / PACKAGE / "share" / PACKAGE / "config"
    node = workspace / "install" / PACKAGE / "lib" / PACKAGE / "estimator_node"
    run = _sourced(workspace, f"{node} --ros-args -p model:=no_such_model")
    assert run.returncode == 1, run.stdout + run.stderr
    assert "cannot start: no shipped model 'no_such_model'" in run.stderr, run.stderr
