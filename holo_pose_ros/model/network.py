"""The holistic network (paper §3): DepthNet -> root depth, a shared backbone -> KeypointNet (P'), JointNet (q)
and RotationNet (R), then differentiable forward kinematics -> keypoints P and the base pose. Built from a model
YAML (config/model/<name>.yaml) and a robot; camera frame OpenCV, metres, radians."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
import yaml
from torch import nn

from holo_pose_ros.geometry.rotation import matrix_to_rot6d, rot6d_to_matrix
from holo_pose_ros.model.backbones import build_backbone
from holo_pose_ros.model.heads import DepthHead, IterativeRegressor, KeypointHead, PyramidHead, reference_depth
from holo_pose_ros.model.heatmaps import decode_heatmaps
from holo_pose_ros.resources import config_dir
from holo_pose_ros.robots.kinematics import RobotModel


@dataclass(frozen=True)
class ModelConfig:
    """A network configuration; see config/model/*.yaml for what each field means."""

    name: str
    input_size: int
    backbone: str
    depth_backbone: str
    pretrained: bool
    depth_pretrained: bool
    heatmap_size: int
    depth_bins: int
    deconv_channels: int
    regressor_hidden: int
    iterations: int
    dropout: float
    fit_heatmaps: bool = False      # 2D heatmaps of the robot's fit keypoints (older cards have none)
    heatmap_sigma: float = 1.0      # Gaussian target sigma, heatmap cells
    skip_connections: bool = False  # the keypoint head also sees the backbone's stride-16/8/4 maps (older: no)
    head: str = "deconv"            # deconv: KeypointHead (the paper's deconvolutions) | pyramid: PyramidHead (FPN-lite)
    head_channels: int = 96         # width of the pyramid head's levels
    segmentation: bool = False      # the keypoint head also predicts the robot-foreground mask (heatmap resolution)

    def to_dict(self) -> dict:
        return asdict(self)


def load_model_config(config: str | Path | dict) -> ModelConfig:
    """A model configuration by name (config/model/<name>.yaml), path, or dict. One with `base: <name>` is that
    configuration with its own fields replacing the base's (a variant lists only what differs)."""
    if not isinstance(config, dict):
        path = Path(config)
        if not path.suffix:
            path = config_dir() / "model" / f"{config}.yaml"
        if not path.is_file():
            raise ValueError(f"unknown model config '{config}'")
        with open(path) as f:
            config = yaml.safe_load(f)
    fields = dict(config)
    base = fields.pop("base", None)
    if base is not None:
        fields = {**load_model_config(base).to_dict(), **fields}
    return ModelConfig(**fields)


class HolisticNet(nn.Module):
    """Image crop (B, 3, S, S) in [0, 1] RGB + the crop's K (B, 3, 3) -> every head's output (no FK: the network
    alone exports to ONNX; `add_kinematics` completes the estimate)."""

    def __init__(self, cfg: ModelConfig, robot: RobotModel):
        super().__init__()
        spec = robot.spec
        self.cfg = cfg
        self.root_index = robot.root_index
        self.robot_name = robot.name
        self.reference_side_m = spec.constants.get("reference_box_side_m", 1.0)
        self.backbone = build_backbone(cfg.backbone, cfg.pretrained)
        info = self.backbone.info
        self.register_buffer("mean", torch.tensor(info.mean).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(info.std).view(1, 3, 1, 1))
        self.depth_backbone = None if cfg.depth_backbone == "shared" else build_backbone(cfg.depth_backbone, cfg.depth_pretrained)
        depth_info = info if self.depth_backbone is None else self.depth_backbone.info
        self.register_buffer("depth_mean", torch.tensor(depth_info.mean).view(1, 3, 1, 1))
        self.register_buffer("depth_std", torch.tensor(depth_info.std).view(1, 3, 1, 1))
        self.depth_head = DepthHead(depth_info.channels)
        depth_range_m = spec.constants.get("keypoint_depth_range_m", 1.3)
        n_fit = robot.n_fit_keypoints if cfg.fit_heatmaps else 0
        if cfg.head == "pyramid":
            if not cfg.skip_connections:
                raise ValueError("the pyramid head reads the backbone's skip maps: set skip_connections: true")
            self.keypoint_head = PyramidHead(info.channels, info.skip_channels, robot.n_keypoints, cfg.input_size,
                                             cfg.heatmap_size, cfg.depth_bins, cfg.head_channels, depth_range_m, n_fit,
                                             cfg.segmentation)
        elif cfg.head == "deconv":
            self.keypoint_head = KeypointHead(info.channels, robot.n_keypoints, cfg.input_size, cfg.heatmap_size,
                                              cfg.depth_bins, cfg.deconv_channels, depth_range_m, n_fit,
                                              info.skip_channels if cfg.skip_connections else (), cfg.segmentation)
        else:
            raise ValueError(f"unknown head '{cfg.head}' (deconv, pyramid)")
        lower, upper = robot.lower.float().cpu(), robot.upper.float().cpu()
        self.register_buffer("joint_mid", (lower + upper) / 2)
        self.register_buffer("joint_half", (upper - lower) / 2)
        neutral = (robot.neutral.float().cpu() - self.joint_mid) / self.joint_half
        self.joint_net = IterativeRegressor(info.channels, neutral, cfg.iterations, cfg.regressor_hidden, cfg.dropout)
        self.rotation_net = IterativeRegressor(info.channels, matrix_to_rot6d(torch.eye(3)), cfg.iterations,
                                               cfg.regressor_hidden, cfg.dropout)
        self.presence = nn.Linear(info.channels, 1)

    def _features(self, image: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor] | None]:
        """The backbone's stride-32 features and, with skip connections, its maps at strides 16, 8, 4."""
        if self.cfg.skip_connections:
            return self.backbone.pyramid((image - self.mean) / self.std)
        return self.backbone((image - self.mean) / self.std), None

    def localize(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        """The whole-image pass of detection, 2D only: image (B, 3, S, S) in [0, 1], any S that is a multiple of
        32 (a lower one than the crop's costs less) -> presence_logit (B,), and DREAM's keypoints from their fit
        heatmaps: uv (B, N, 2) px of this input, confidence (B, N). No depth, joints, rotation or 3D volume: a
        box and a presence are all the localizer gives."""
        if not self.cfg.fit_heatmaps:
            raise ValueError(f"network '{self.cfg.name}' has no fit heatmaps: its localizer is the full pass")
        features, skips = self._features(image)
        head = self.keypoint_head
        heatmaps = F.conv2d(head.heatmap_features(features, skips), head.fit_out.weight[:head.n],
                            head.fit_out.bias[:head.n])  # DREAM's keypoints come first among the fit keypoints
        uv, confidence = decode_heatmaps(heatmaps, image.shape[-1])
        return {"presence_logit": self.presence(features.mean((2, 3))).squeeze(-1), "uv": uv, "confidence": confidence}

    def forward(self, image: torch.Tensor, K_crop: torch.Tensor) -> dict[str, torch.Tensor]:
        features, skips = self._features(image)
        pooled = features.mean((2, 3))
        if self.depth_backbone is None:
            depth_pooled = pooled
        else:
            depth_pooled = self.depth_backbone((image - self.depth_mean) / self.depth_std).mean((2, 3))
        depth = self.depth_head(depth_pooled, reference_depth(K_crop, self.cfg.input_size, self.reference_side_m))
        kp = self.keypoint_head(features, skips)
        root = torch.zeros_like(kp["dz"])
        root[:, self.root_index] = 1.0
        dz = kp["dz"] * (1.0 - root)                      # the root keypoint sits at depth d exactly
        keypoints_reg = pixel_rays(kp["uv"], K_crop) * (depth[:, None] + dz)[..., None]
        joints_norm = self.joint_net(pooled)
        r6 = self.rotation_net(pooled)
        return {
            "depth": depth, "uv": kp["uv"], "dz": dz, "keypoint_confidence": kp["confidence"],
            "keypoints_reg": keypoints_reg, "t": keypoints_reg[:, self.root_index],
            "joints_norm": joints_norm, "joints": self.joint_mid + self.joint_half * joints_norm,
            "rot6d": r6, "R": rot6d_to_matrix(r6), "presence_logit": self.presence(pooled).squeeze(-1),
            **{k: kp[k] for k in ("heatmap_logits", "fit_uv", "fit_confidence", "mask_logits") if k in kp},
        }


class Localizer(nn.Module):
    """HolisticNet's `localize` pass as a module of its own (the same parameters, not a copy), to export or run
    apart from the crop pass."""

    def __init__(self, net: HolisticNet):
        super().__init__()
        self.net = net

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.net.localize(image)


def example_inputs(size: int, batch: int = 1, device: str | torch.device = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Random crops (batch, 3, size, size) and a plausible crop K (focal = size px, centred) to trace, export or
    count the FLOPs of a network pass."""
    K = torch.tensor([[size, 0.0, size / 2], [0.0, size, size / 2], [0.0, 0.0, 1.0]], device=device)
    return torch.rand(batch, 3, size, size, device=device), K.repeat(batch, 1, 1)


def pixel_rays(uv: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """K^-1 [u, v, 1]: (B, N, 2) pixels and (B, 3, 3) upper-triangular intrinsics (skew allowed) -> (B, N, 3) rays
    with z = 1. Written out rather than with linalg.inv, which ONNX has no operator for."""
    fx, fy, skew = K[:, 0, 0, None], K[:, 1, 1, None], K[:, 0, 1, None]
    cx, cy = K[:, 0, 2, None], K[:, 1, 2, None]
    y = (uv[..., 1] - cy) / fy
    x = (uv[..., 0] - cx - skew * y) / fx
    return torch.stack([x, y, torch.ones_like(x)], -1)


def add_kinematics(robot: RobotModel, out: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Complete the network's output with FK: keypoints P = R * P_root(q) + t (B, N, 3, camera frame) and the
    base pose T_cam<-base = [R | t] * inv(T_base<-root(q)) (B, 4, 4). Differentiable in q, R and t."""
    q = out["joints"].to(robot.dtype)
    R, t = out["R"].to(robot.dtype), out["t"].to(robot.dtype)
    links = robot.link_transforms(q, [k.link for k in robot.spec.keypoints])
    root_inv = torch.linalg.inv(links[robot.spec.keypoints[robot.root_index].link])
    in_root = torch.stack([(root_inv @ links[k.link])[:, :3, 3] for k in robot.spec.keypoints], dim=1)
    T_cam_root = torch.zeros(q.shape[0], 4, 4, dtype=q.dtype, device=q.device)
    T_cam_root[:, :3, :3], T_cam_root[:, :3, 3], T_cam_root[:, 3, 3] = R, t, 1.0
    return {**out, "keypoints_fk": in_root @ R.transpose(1, 2) + t[:, None], "T_cam_base": T_cam_root @ root_inv}
