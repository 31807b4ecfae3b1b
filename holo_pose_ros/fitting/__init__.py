"""Kinematic fitting: batched Levenberg-Marquardt of a robot's joints and base pose to 2D keypoint evidence,
within the joint limits, from several starts. No learning, no rclpy, no renderer."""

from holo_pose_ros.fitting.kinematic_tree import KinematicTree
from holo_pose_ros.fitting.solver import FitResult, Fitter, load_fitting_config

__all__ = ["Fitter", "FitResult", "KinematicTree", "load_fitting_config"]
