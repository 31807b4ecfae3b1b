"""A small, untrained but real holistic network (pretrained EfficientNet-Lite0 trunk, 64 px crops) for tests of
the machinery around the model: nodes, bags, the estimator API. Accuracy is not what these tests check."""

from pathlib import Path

import torch

from holo_pose_ros.model.network import HolisticNet, load_model_config
from holo_pose_ros.model.weights import save_model
from holo_pose_ros.robots.kinematics import RobotModel

SMALL = {**load_model_config("lite").to_dict(), "name": "test-small", "input_size": 64, "heatmap_size": 16,
         "depth_bins": 8, "deconv_channels": 32, "regressor_hidden": 64}


def save_small_model(folder: Path, robot: str = "panda", seed: int = 0) -> Path:
    """Build the small network with a fixed seed and save it; returns its model card path."""
    torch.manual_seed(seed)
    net = HolisticNet(load_model_config(SMALL), RobotModel(robot)).eval()
    return save_model(net, robot, Path(folder) / "small")
