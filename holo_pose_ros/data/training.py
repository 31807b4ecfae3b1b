"""Training samples rendered on the fly, directly at the network's input size: a full camera frame is drawn
(joints, camera, look; data/scene.py), then one view of it is rendered through the crop's intrinsics, exactly
as the deployed estimator would see it:
  - `crop`: the box the localizer would give (in-image keypoints, grown by the crop margin) with random shift,
    scale and aspect jitter, so imperfect boxes do not hurt;
  - `full`: the whole letterboxed frame (the localizer's pass);
  - `negative`: a `crop` or `full` view with no robot (presence target 0);
  - `close_up`: the box around one of the robot YAML's `close_ups` (an arm, a hand: its fit keypoints in the image),
    jittered like a crop: the estimator's second pass at the part's own scale (`close_ups`). Only the 2D terms apply.
Areas of a view outside the original frame are black, as in `crop_image`; the view's robot-foreground mask (S x S
bool, the segmentation target) is false there. Sample i depends only on (seed, i)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from holo_pose_ros.data.render import robot_foreground
from holo_pose_ros.geometry.camera import in_image, project
from holo_pose_ros.geometry.crop import (CROP_MARGIN, MIN_CLOSE_UP_POINTS, crop_affine, crop_box_from_keypoints,
                                         full_image_box)

MODES = ("crop", "full", "negative", "close_up")


@dataclass(frozen=True)
class SampleConfig:
    """How views are drawn (fractions, pixels)."""

    input_size: int
    frame_width: int = 640
    frame_height: int = 480
    mode_probabilities: tuple[float, ...] = (0.75, 0.15, 0.10)  # crop, full, negative[, close_up]
    crop_margin: float = CROP_MARGIN  # the estimator's crop recipe: keypoint extent grown by this on each side
    shift_sigma: float = 0.08       # box centre jitter, in box sides
    scale_range: tuple[float, float] = (0.85, 1.3)


def jitter_box(box: np.ndarray, rng: np.random.Generator, cfg: SampleConfig) -> np.ndarray:
    """A randomly shifted and scaled copy of a square box (x0, y0, side)."""
    side = box[2] * rng.uniform(*cfg.scale_range)
    centre = box[:2] + box[2] / 2 + rng.normal(0, cfg.shift_sigma * box[2], 2)
    return np.array([centre[0] - side / 2, centre[1] - side / 2, side])


def outside_frame_mask(box: np.ndarray, size: int, width: int, height: int) -> np.ndarray:
    """(S, S) bool: crop pixels whose centre falls outside the original W x H frame."""
    A_inv = np.linalg.inv(crop_affine(box, size))
    c = np.arange(size, dtype=np.float64)
    u = A_inv[0, 0] * c + A_inv[0, 2]
    v = A_inv[1, 1] * c + A_inv[1, 2]
    return (v[:, None] < -0.5) | (v[:, None] > height - 0.5) | (u[None, :] < -0.5) | (u[None, :] > width - 0.5)


class RenderedViews(torch.utils.data.Dataset):
    """`length` random training views of one robot (an index is a seed: any length, no files)."""

    def __init__(self, robot: str, sample_cfg: SampleConfig, generator_cfg: dict, seed: int, length: int, max_faces: int = 12000):
        self.robot_name, self.cfg, self.gen_cfg, self.seed, self.length = robot, sample_cfg, generator_cfg, seed, length
        self.max_faces = max_faces
        self._state = None  # built lazily in the process that renders (DataLoader workers)
        self._mode_p = mode_probabilities(sample_cfg.mode_probabilities)  # checked once, drawn from per sample
        if self._mode_p[MODES.index("close_up")] > 0:
            from holo_pose_ros.robots.spec import load_robot_spec

            if not load_robot_spec(robot).close_ups:
                raise ValueError(f"close-up views asked for, but the robot YAML of '{robot}' names no close_ups")

    def __len__(self) -> int:
        return self.length

    def _lazy(self):
        if self._state is None:
            from holo_pose_ros.data.meshes import load_link_meshes
            from holo_pose_ros.data.render import Renderer
            from holo_pose_ros.robots.kinematics import RobotModel

            model = RobotModel(self.robot_name, dtype=torch.float64)
            meshes = load_link_meshes(model, self.max_faces)
            self._state = (model, meshes, Renderer(self.cfg.input_size, self.cfg.input_size))
            self._close_ups = model.close_up_fit_indices()
        return self._state

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        from holo_pose_ros.data.backgrounds import random_background
        from holo_pose_ros.data.generator import _post_process
        from holo_pose_ros.data.scene import sample_intrinsics, sample_scene

        model, meshes, renderer = self._lazy()
        cfg, gen, S = self.cfg, self.gen_cfg, self.cfg.input_size
        W, H = cfg.frame_width, cfg.frame_height
        rng = np.random.default_rng([self.seed, index])
        K = sample_intrinsics(gen["intrinsics"], rng, W, H)
        scene = sample_scene(model, gen, rng, K, W, H, {k: m.color for k, m in meshes.items()})
        q = torch.from_numpy(scene.joints[None])
        links = model.link_transforms(q)
        kp_base = torch.stack([links[k.link][0, :3, 3] for k in model.spec.keypoints]).numpy()
        kp_cam = kp_base @ scene.T_cam_base[:3, :3].T + scene.T_cam_base[:3, 3]
        mode = MODES[rng.choice(len(MODES), p=self._mode_p)]
        view = ("crop", "full")[rng.integers(2)] if mode == "negative" else mode
        fit_cam = model.fit_keypoints_in_camera(q, torch.from_numpy(scene.T_cam_base))[0].numpy()
        if view == "close_up":
            box = self._close_up_box(project(fit_cam, K), rng)
            if box is None:  # no part in view: a crop of the whole robot
                mode = view = "crop"
        if view == "full":
            box = full_image_box(W, H)
        elif view == "crop":
            box = jitter_box(crop_box_from_keypoints(project(kp_cam, K), W, H, cfg.crop_margin), rng, cfg)
        K_crop = crop_affine(box, S) @ K
        robot = {} if mode == "negative" else meshes
        poses = {name: scene.T_cam_base @ links[name][0].numpy() for name in robot}
        result = renderer.render(poses, robot, K_crop, scene.materials, scene.light, scene.distractors,
                                 scene.shading)
        background = random_background(rng, S, S, tuple(gen["background"]["layers"]),
                                       tuple(gen["background"]["kinds"]))
        alpha = result.rgba[..., 3:4].astype(np.float32) / 255.0
        image = _post_process(result.rgba[..., :3] * alpha + background * (1.0 - alpha), gen["post"], rng)
        outside = outside_frame_mask(box, S, W, H)
        image[outside] = 0
        foreground = robot_foreground(result.labels) & ~outside  # robot pixels in view
        T_cam_root = scene.T_cam_base @ links[model.spec.keypoints[model.root_index].link][0].numpy()
        uv = project(kp_cam, K_crop)
        visible = (uv >= -0.5).all(1) & (uv <= S - 0.5).all(1) & in_image(project(kp_cam, K), W, H)
        uv_fit = project(fit_cam, K_crop)
        visible_fit = (uv_fit >= -0.5).all(1) & (uv_fit <= S - 0.5).all(1) & in_image(project(fit_cam, K), W, H)
        f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
        return {
            "image": torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).float() / 255.0,
            "K_crop": f32(K_crop), "joints": f32(scene.joints), "keypoints_3d": f32(kp_cam), "uv": f32(uv),
            "visible": torch.from_numpy(visible), "uv_fit": f32(uv_fit), "visible_fit": torch.from_numpy(visible_fit), "R_root": f32(T_cam_root[:3, :3]), "t_root": f32(T_cam_root[:3, 3]),
            "presence": torch.tensor(float(mode != "negative")), "mode": torch.tensor(MODES.index(mode)),
            "mask": torch.from_numpy(foreground),
        }

    def _close_up_box(self, uv_fit_image: np.ndarray, rng: np.random.Generator) -> np.ndarray | None:
        """A jittered box around one of the robot's close-up parts, drawn among those with MIN_CLOSE_UP_POINTS fit
        keypoints in the image (all fit keypoints' image px in; through the crop recipe), or None when none has."""
        W, H = self.cfg.frame_width, self.cfg.frame_height
        seen = in_image(uv_fit_image, W, H)
        parts = [idx[seen[idx]] for idx in self._close_ups.values()]
        parts = [idx for idx in parts if len(idx) >= MIN_CLOSE_UP_POINTS]
        if not parts:
            return None
        idx = parts[rng.integers(len(parts))]
        return jitter_box(crop_box_from_keypoints(uv_fit_image[idx], W, H, self.cfg.crop_margin), rng, self.cfg)


def mode_probabilities(probabilities: tuple[float, ...]) -> np.ndarray:
    """The four modes' probabilities from a config's three (crop, full, negative: no close-ups) or four."""
    p = np.zeros(len(MODES))
    if len(probabilities) not in (3, 4) or any(x < 0 for x in probabilities) or not np.isclose(sum(probabilities), 1):
        raise ValueError(f"mode_probabilities: 3 or 4 non-negative numbers (crop, full, negative[, close_up]) that sum "
                         f"to 1, got {list(probabilities)}")
    p[:len(probabilities)] = probabilities
    return p
