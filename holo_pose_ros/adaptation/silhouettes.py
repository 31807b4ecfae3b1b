"""Mask-consistency targets: the silhouette of the fitted robot, drawn by the generator's own renderer through a
crop's intrinsics at the network's input size, exactly as a training view's mask is drawn. A rendered silhouette
of the pseudo-label's pose is the target of the segmentation head on the user's images (the paper's mask
consistency), so no differentiable renderer is needed."""

from __future__ import annotations

import numpy as np
import torch

from holo_pose_ros.data.render import Light, robot_foreground
from holo_pose_ros.data.training import outside_frame_mask


class SilhouetteRenderer:
    """Robot-foreground masks (S, S) bool of a robot at given joints and base pose, seen through a crop's
    intrinsics; pixels of the crop outside the original W x H frame are background, as in training views."""

    def __init__(self, robot_name: str, size: int, max_faces: int = 12000):
        from holo_pose_ros.data.meshes import load_link_meshes
        from holo_pose_ros.data.render import Renderer
        from holo_pose_ros.robots.kinematics import RobotModel

        self.size = int(size)
        self.model = RobotModel(robot_name, dtype=torch.float64)
        self.meshes = load_link_meshes(self.model, max_faces)
        self.renderer = Renderer(self.size, self.size)

    def __call__(self, joints: np.ndarray, T_cam_base: np.ndarray, K_crop: np.ndarray, box: np.ndarray,
                 width: int, height: int) -> np.ndarray:
        """The (S, S) mask of joints (J,) radians/metres and pose T_cam<-base (4, 4) metres through K_crop (3, 3)
        crop px; `box` (x0, y0, side) px is the crop's box in the W x H image."""
        with torch.inference_mode():
            links = self.model.link_transforms(torch.from_numpy(np.array(joints, np.float64)[None]))
        poses = {name: T_cam_base @ links[name][0].numpy() for name in self.meshes}
        result = self.renderer.render(poses, self.meshes, K_crop, {}, Light())
        return robot_foreground(result.labels) & ~outside_frame_mask(box, self.size, width, height)
