"""Kinematic fitting: batched Levenberg-Marquardt of a robot's joints and base pose to 2D keypoint evidence and,
optionally, a foreground mask's silhouette, within the joint limits, from several starts. No learning, no rclpy, no
renderer."""

from holo_pose_ros.fitting.kinematic_tree import KinematicTree
from holo_pose_ros.fitting.silhouette import Silhouette
from holo_pose_ros.fitting.solver import BasePrior, FitResult, Fitter, load_fitting_config
from holo_pose_ros.fitting.surface import sample_surface_points

__all__ = ["BasePrior", "Fitter", "FitResult", "KinematicTree", "Silhouette", "load_fitting_config", "sample_surface_points"]
