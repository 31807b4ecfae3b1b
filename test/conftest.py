"""Test-wide ROS 2 environment, set before any rclpy.init: discovery stays on this machine and Fast DDS uses the
package's shared-memory transport profile (the one the README recommends)."""

import atexit
import os
import shutil
import tempfile
from pathlib import Path

_PROFILE = str(Path(__file__).resolve().parent.parent / "config" / "fastdds_shm.xml")
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.pop("ROS_LOCALHOST_ONLY", None)  # it would override the discovery range (Jazzy)
os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = _PROFILE
os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = _PROFILE
# ONNX exports (the onnxruntime backend's cache) go to a fresh folder, shared by the session and its subprocesses
os.environ["XDG_CACHE_HOME"] = tempfile.mkdtemp(prefix="holo_pose_test_cache_")
atexit.register(shutil.rmtree, os.environ["XDG_CACHE_HOME"], True)

import pytest  # noqa: E402
import torch  # noqa: E402

from small_model import save_small_model  # noqa: E402


@pytest.fixture(scope="session")
def small_model_card(tmp_path_factory):
    """Model card of the small untrained Panda network (test/small_model.py), built once per test session."""
    return save_small_model(tmp_path_factory.mktemp("small_model"))


@pytest.fixture
def one_torch_thread():
    """One torch thread for a test (its CPU budget on two cores), restored afterwards."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def panda_meshes(tmp_path_factory):
    """The Panda model and its link meshes, built into a private mesh cache (tests never share the user's)."""
    from holo_pose_ros.data.meshes import load_link_meshes
    from holo_pose_ros.robots.kinematics import RobotModel

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("XDG_CACHE_HOME", str(tmp_path_factory.mktemp("cache")))
        model = RobotModel("panda")
        return model, load_link_meshes(model)
