"""Synthetic training batches for the lifter, from forward kinematics alone and vectorized over the batch: joints
uniform within the URDF limits, intrinsics and camera placement drawn like the generator (data/scene.py:
sample_intrinsics, sample_camera, the robot extent of sample_scene; the same YAML fields), the fit keypoints
projected, the estimator's crop box around the in-image ones (geometry/crop.py) jittered like training's
jitter_box, and detections made noisy like a CNN's (pixel noise, outliers, dropped points, confidences).
The robot base is the world frame (z up). Metres, radians, pixels (pixel (0, 0) = centre of the top-left pixel)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from holo_pose_ros.robots.kinematics import RobotModel


@dataclass
class LifterBatch:
    """One batch of B synthetic samples of a robot with M fit keypoints and J joints."""

    uv: torch.Tensor            # (B, M, 2) detected fit keypoints, image pixels (noisy, outliers)
    confidence: torch.Tensor    # (B, M) detection confidence, 0 = not detected (dropped, out of image or box)
    box: torch.Tensor           # (B, 3) crop box (x0, y0, side), edge coordinates, pixels (jittered)
    K: torch.Tensor             # (B, 3, 3) intrinsics, pixels
    q: torch.Tensor             # (B, J) true joints, radians / metres
    T_cam_base: torch.Tensor    # (B, 4, 4) true base pose in the camera frame, metres
    uv_true: torch.Tensor       # (B, M, 2) exact projections of the fit keypoints, pixels
    keypoints_cam: torch.Tensor  # (B, M, 3) fit keypoints in the camera frame, metres
    box_keypoints: torch.Tensor  # (B, 3) the estimator's box around the true in-image DREAM keypoints, before jitter
    in_image: torch.Tensor      # (B, M) bool: true keypoint in front of the camera and inside the frame

    def to(self, device: str | torch.device) -> "LifterBatch":
        return LifterBatch(**{f.name: getattr(self, f.name).to(device) for f in fields(self)})

    def __len__(self) -> int:
        return self.uv.shape[0]


def _uniform(n: int, bounds, g: torch.Generator, dtype: torch.dtype) -> torch.Tensor:
    """(n,) uniform in [bounds[0], bounds[1]]."""
    lo, hi = float(bounds[0]), float(bounds[1])
    return lo + (hi - lo) * torch.rand(n, generator=g, dtype=dtype)


def _signed(n: int, g: torch.Generator, dtype: torch.dtype) -> torch.Tensor:
    """(n,) uniform in [-1, 1]."""
    return 2.0 * torch.rand(n, generator=g, dtype=dtype) - 1.0


def sample_intrinsics_batch(cfg: dict, n: int, width: int, height: int, g: torch.Generator,
                            dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(n, 3, 3) K like data/scene.py:sample_intrinsics (one camera per sample): fx from `focal_px_at_640`
    scaled with the width, fy within `aspect_jitter`, principal point within `principal_offset_frac`."""
    fx = _uniform(n, cfg["focal_px_at_640"], g, dtype) * width / 640.0
    fy = fx * (1.0 + _signed(n, g, dtype) * cfg["aspect_jitter"])
    cx = width / 2.0 + _signed(n, g, dtype) * cfg["principal_offset_frac"] * width
    cy = height / 2.0 + _signed(n, g, dtype) * cfg["principal_offset_frac"] * height
    K = torch.zeros(n, 3, 3, dtype=dtype)
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = fx, fy, cx, cy, 1.0
    return K


def robot_extent_batch(points_base: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Centre (B, 3) and radius (B,, metres) of a sphere around each sample's link origins (B, L, 3), padded for
    the meshes: data/scene.py:_robot_extent, batched."""
    centre = (points_base.amin(1) + points_base.amax(1)) / 2.0
    radius = (points_base - centre[:, None]).norm(dim=-1).amax(1) * 1.1 + 0.08
    return centre, radius


def look_at_batch(eye: torch.Tensor, target: torch.Tensor, roll: torch.Tensor) -> torch.Tensor:
    """T_world<-cam (B, 4, 4) of OpenCV cameras at `eye` (B, 3) looking at `target` (B, 3), world z up in the
    image, rolled by `roll` (B,, radians): geometry/camera.py:look_at, batched."""
    forward = nn_normalize(target - eye)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=eye.dtype).expand_as(forward)
    right = torch.cross(forward, up, dim=-1)
    degenerate = right.norm(dim=-1, keepdim=True) < 1e-6
    alt = torch.cross(forward, torch.tensor([1.0, 0.0, 0.0], dtype=eye.dtype).expand_as(forward), dim=-1)
    right = nn_normalize(torch.where(degenerate, alt, right))
    down = torch.cross(forward, right, dim=-1)
    c, s = torch.cos(roll)[:, None], torch.sin(roll)[:, None]
    right, down = c * right + s * down, -s * right + c * down
    T = torch.zeros(eye.shape[0], 4, 4, dtype=eye.dtype)
    T[:, :3, :3] = torch.stack([right, down, forward], dim=2)
    T[:, :3, 3] = eye
    T[:, 3, 3] = 1.0
    return T


def nn_normalize(v: torch.Tensor) -> torch.Tensor:
    """Unit vectors along the last dimension."""
    return v / v.norm(dim=-1, keepdim=True).clamp(min=1e-12)


def invert_rigid(T: torch.Tensor) -> torch.Tensor:
    """(B, 4, 4) inverse of rigid transforms."""
    R_t = T[:, :3, :3].transpose(1, 2)
    out = torch.zeros_like(T)
    out[:, :3, :3] = R_t
    out[:, :3, 3] = -(R_t @ T[:, :3, 3:4])[..., 0]
    out[:, 3, 3] = 1.0
    return out


def sample_cameras_batch(cfg: dict, centre: torch.Tensor, radius: torch.Tensor, K: torch.Tensor, height: int,
                         g: torch.Generator) -> torch.Tensor:
    """T_cam<-base (B, 4, 4) like data/scene.py:sample_camera: distance from the wanted image `fill`, azimuth,
    elevation, clipped-normal roll and a look-at point jittered around the robot centre."""
    n, dtype = centre.shape[0], centre.dtype
    fill = _uniform(n, cfg["fill"], g, dtype)
    distance = radius * K[:, 1, 1] / (fill * height / 2.0)
    azimuth = torch.deg2rad(_uniform(n, cfg["azimuth_deg"], g, dtype))
    elevation = torch.deg2rad(_uniform(n, cfg["elevation_deg"], g, dtype))
    jitter = cfg["look_at_jitter"] * radius / fill.clamp(min=1.0)
    target = centre + torch.randn(n, 3, generator=g, dtype=dtype) * jitter[:, None]
    direction = torch.stack([torch.cos(elevation) * torch.cos(azimuth), torch.cos(elevation) * torch.sin(azimuth),
                             torch.sin(elevation)], dim=1)
    eye = target + distance[:, None] * direction
    sigma = math.radians(cfg["roll_deg_sigma"])
    roll = (torch.randn(n, generator=g, dtype=dtype) * sigma).clamp(-3 * sigma, 3 * sigma)
    return invert_rigid(look_at_batch(eye, target, roll))


def project_batch(points_cam: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(B, M, 3) camera-frame points (metres) -> (B, M, 2) pixels with K (B, 3, 3); depth clamped at 1 mm."""
    z = points_cam[..., 2].clamp(min=1e-3)
    u = K[:, None, 0, 0] * points_cam[..., 0] / z + K[:, None, 0, 1] * points_cam[..., 1] / z + K[:, None, 0, 2]
    v = K[:, None, 1, 1] * points_cam[..., 1] / z + K[:, None, 1, 2]
    return torch.stack([u, v], dim=-1)


def keypoint_boxes(uv: torch.Tensor, visible: torch.Tensor, width: int, height: int, margin: float,
                   min_side: float = 32.0) -> torch.Tensor:
    """(B, 3) the estimator's crop boxes (geometry/crop.py:crop_box_from_keypoints, batched): the extent of the
    in-image points (B, M, 2, pixels; `visible` (B, M) also requires them in front of the camera), or of all points
    clipped to the frame when fewer than two are in it, grown by `margin` on each side, square about its centre."""
    inside = visible & (uv[..., 0] >= 0) & (uv[..., 0] <= width) & (uv[..., 1] >= 0) & (uv[..., 1] <= height)
    enough = inside.sum(1) >= 2
    use = torch.where(enough[:, None], inside, torch.ones_like(inside))
    limits = torch.tensor([float(width), float(height)], dtype=uv.dtype)
    pts = torch.where(enough[:, None, None], uv, torch.minimum(torch.maximum(uv, torch.zeros_like(limits)), limits))
    big = torch.finfo(uv.dtype).max
    lo = torch.where(use[..., None], pts, torch.full_like(pts, big)).amin(1) + 0.5
    hi = torch.where(use[..., None], pts, torch.full_like(pts, -big)).amax(1) + 0.5
    centre = (lo + hi) / 2.0
    side = ((hi - lo).amax(1) * (1.0 + 2.0 * margin)).clamp(min=min_side)
    return torch.stack([centre[:, 0] - side / 2.0, centre[:, 1] - side / 2.0, side], dim=1)


def jitter_boxes(box: torch.Tensor, shift_sigma: float, scale_range, g: torch.Generator) -> torch.Tensor:
    """(B, 3) randomly shifted and scaled copies of square boxes (data/training.py:jitter_box, batched): side
    times U(scale_range), centre moved by N(0, shift_sigma side)."""
    n, dtype = box.shape[0], box.dtype
    side = box[:, 2] * _uniform(n, scale_range, g, dtype)
    centre = box[:, :2] + box[:, 2:3] / 2 + torch.randn(n, 2, generator=g, dtype=dtype) * shift_sigma * box[:, 2:3]
    return torch.stack([centre[:, 0] - side / 2, centre[:, 1] - side / 2, side], dim=1)


def noisy_detections(uv: torch.Tensor, visible: torch.Tensor, box: torch.Tensor, cfg: dict,
                     g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """(uv (B, M, 2) pixels, confidence (B, M)) of a detector seeing the exact projections `uv` of points that
    are `visible` (in front of the camera, inside the frame), through crop `box`: per-sample Gaussian noise of
    sigma U(sigma_px), a share U(outlier_fraction) of points anywhere in the box, a share U(drop_fraction)
    dropped; invisible points (and, with drop_outside_box, points outside the box) get confidence 0, kept points
    U(confidence)."""
    B, M, dtype = uv.shape[0], uv.shape[1], uv.dtype
    sigma = _uniform(B, cfg["sigma_px"], g, dtype)
    out = uv + torch.randn(B, M, 2, generator=g, dtype=dtype) * sigma[:, None, None]
    outlier = torch.rand(B, M, generator=g, dtype=dtype) < _uniform(B, cfg["outlier_fraction"], g, dtype)[:, None]
    anywhere = box[:, None, :2] - 0.5 + torch.rand(B, M, 2, generator=g, dtype=dtype) * box[:, None, 2:3]
    out = torch.where(outlier[..., None], anywhere, out)
    dropped = torch.rand(B, M, generator=g, dtype=dtype) < _uniform(B, cfg["drop_fraction"], g, dtype)[:, None]
    keep = visible & ~dropped
    if cfg["drop_outside_box"]:
        lo, hi = box[:, None, :2] - 0.5, box[:, None, :2] + box[:, None, 2:3] - 0.5
        keep &= ((out >= lo) & (out <= hi)).all(-1)
    confidence = torch.where(keep, _uniform(B * M, cfg["confidence"], g, dtype).view(B, M), torch.zeros(B, M, dtype=dtype))
    return out, confidence


class LifterSampler:
    """Draws LifterBatch-es of one robot (a float32 RobotModel is fine) from the `sampler` section of
    config/lifter.yaml and a generator YAML's `intrinsics` and `camera` sections. All on the CPU."""

    def __init__(self, robot: RobotModel, sampler_cfg: dict, generator_cfg: dict | None = None):
        from holo_pose_ros.data.generator import load_generator_config

        self.robot, self.cfg = robot, sampler_cfg
        self.gen = generator_cfg if generator_cfg is not None else load_generator_config(sampler_cfg["generator"])
        self.width, self.height = int(sampler_cfg["width"]), int(sampler_cfg["height"])
        # fit keypoints straight from the one FK call that also gives the extent (as RobotModel.fit_keypoints)
        self._links = robot.link_names
        fit = robot.spec.fit_keypoints
        self._fit_link = torch.tensor([self._links.index(k.link) for k in fit])
        self._fit_xyz = torch.tensor([k.xyz for k in fit], dtype=robot.dtype).reshape(-1, 3)

    def sample(self, n: int, generator: torch.Generator) -> LifterBatch:
        """n fresh samples; the same generator state gives the same batch."""
        robot, cfg, g = self.robot, self.cfg, generator
        dtype = robot.dtype
        q = robot.lower + torch.rand(n, robot.n_joints, generator=g, dtype=dtype) * (robot.upper - robot.lower)
        K = sample_intrinsics_batch(self.gen["intrinsics"], n, self.width, self.height, g, dtype)
        with torch.no_grad():
            links = robot.link_transforms(q, self._links)
            T_links = torch.stack([links[name] for name in self._links], dim=1)        # (B, L, 4, 4)
            centre, radius = robot_extent_batch(T_links[:, :, :3, 3])
            T_cam_base = sample_cameras_batch(self.gen["camera"], centre, radius, K, self.height, g)
            T_fit = T_links[:, self._fit_link]                                          # (B, M, 4, 4)
            kp_base = (T_fit[..., :3, :3] @ self._fit_xyz[None, :, :, None])[..., 0] + T_fit[..., :3, 3]
            kp_cam = kp_base @ T_cam_base[:, :3, :3].transpose(1, 2) + T_cam_base[:, None, :3, 3]
        uv_true = project_batch(kp_cam, K)
        front = kp_cam[..., 2] > float(cfg["min_depth_m"])
        W, H = self.width, self.height
        in_image = front & (uv_true[..., 0] >= 0) & (uv_true[..., 0] <= W) & (uv_true[..., 1] >= 0) & (uv_true[..., 1] <= H)
        bc = cfg["box"]
        n = robot.n_keypoints  # the crop recipe bounds DREAM's keypoints, which the fit keypoints list first
        box0 = keypoint_boxes(uv_true[:, :n], front[:, :n], W, H, float(bc["margin"]), float(bc["min_side_px"]))
        box = jitter_boxes(box0, float(bc["shift_sigma"]), bc["scale_range"], g)
        uv, confidence = noisy_detections(uv_true, in_image, box, cfg["noise"], g)
        return LifterBatch(uv=uv, confidence=confidence, box=box, K=K, q=q, T_cam_base=T_cam_base, uv_true=uv_true,
                           keypoints_cam=kp_cam, box_keypoints=box0, in_image=in_image)
