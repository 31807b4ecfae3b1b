"""The lifter: an MLP from one crop's 2D fit keypoints (image pixels + confidences, the CNN's detections) to H
hypotheses of (joints q, base pose T_cam<-base), the kinematic fit's starts. It is learned from forward kinematics
alone (train/lifter_trainer.py). Its inputs and outputs are expressed relative to a *virtual camera* that looks
along the crop box centre's viewing ray, and depth is predicted through the box scale (z = exp(s) fx / side), so
the same pose seen anywhere in the image, at any focal length, maps to the same network target.

Conventions: OpenCV camera; pixel (0, 0) is the centre of the top-left pixel; boxes (x0, y0, side) are in edge
coordinates (geometry/crop.py); metres, radians. Weights are data: a safetensors file plus a YAML card."""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import yaml
from safetensors.torch import save_file
from torch import nn

from holo_pose_ros.geometry.rotation import rot6d_to_matrix
from holo_pose_ros.model.cards import LIFTER_CARD_KEYS, ModelLoadError, check_card_keys, file_sha256, read_card_file
from holo_pose_ros.model.weights import read_weights
from holo_pose_ros.resources import config_with_overrides, weights_dir
from holo_pose_ros.robots.kinematics import RobotModel

COORD_CLAMP = 4.0  # box-normalized coordinates beyond this (far outside the box) are clipped: wild detections
EXTRA_FEATURES = 5  # ray (3), log box scale, fraction of kept points


# -- configuration ---------------------------------------------------------------------------------------------
def load_lifter_config(config: str | Path | dict | None = None) -> dict:
    """The lifter config: config/lifter.yaml (every default, documented) with `config` (a path or a mapping of
    overrides) merged over it."""
    return config_with_overrides("lifter.yaml", config, "lifter config sections")


@dataclass(frozen=True)
class LifterConfig:
    """The network's shape (the `model` section of config/lifter.yaml)."""

    hidden: int = 1024
    depth: int = 3
    hypotheses: int = 5

    @classmethod
    def from_dict(cls, d: dict) -> "LifterConfig":
        known = set(cls.__dataclass_fields__)
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"lifter model config: unknown keys {sorted(unknown)}; known: {sorted(known)}")
        return cls(**{k: type(getattr(cls, k))(v) for k, v in d.items()})

    def to_dict(self) -> dict:
        return asdict(self)


# -- features and the virtual camera -----------------------------------------------------------------------------
def feature_size(n_fit_keypoints: int) -> int:
    """F of `lifter_features` for M fit keypoints: (x, y, confidence) per point plus EXTRA_FEATURES."""
    return 3 * n_fit_keypoints + EXTRA_FEATURES


def box_centre_px(box: torch.Tensor) -> torch.Tensor:
    """(B, 2) centre of boxes (B, 3: x0, y0, side; edge coordinates) in pixel-centre coordinates."""
    return box[:, :2] + box[:, 2:3] / 2.0 - 0.5


def box_ray(box: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(B, 3) unit viewing ray (camera frame) of each box centre: K^-1 [cx, cy, 1], normalized."""
    c = box_centre_px(box)
    x = (c[:, 0] - K[:, 0, 2] - K[:, 0, 1] * (c[:, 1] - K[:, 1, 2]) / K[:, 1, 1]) / K[:, 0, 0]
    y = (c[:, 1] - K[:, 1, 2]) / K[:, 1, 1]
    return nn.functional.normalize(torch.stack([x, y, torch.ones_like(x)], dim=1), dim=1)


def virtual_camera_rotation(ray: torch.Tensor) -> torch.Tensor:
    """R_cam<-virtual (B, 3, 3): the smallest rotation taking the optical axis e_z to `ray` (B, 3, unit), i.e. the
    real camera turned to look at the box centre (Rodrigues about e_z x ray; rays never point backwards)."""
    v = torch.stack([-ray[:, 1], ray[:, 0], torch.zeros_like(ray[:, 0])], dim=1)  # e_z x ray
    c = ray[:, 2]
    zero = torch.zeros_like(c)
    vx = torch.stack([torch.stack([zero, -v[:, 2], v[:, 1]], 1), torch.stack([v[:, 2], zero, -v[:, 0]], 1),
                      torch.stack([-v[:, 1], v[:, 0], zero], 1)], dim=1)
    eye = torch.eye(3, dtype=ray.dtype, device=ray.device).expand_as(vx)
    return eye + vx + (vx @ vx) / (1.0 + c)[:, None, None]


def lifter_features(uv_px: torch.Tensor, confidence: torch.Tensor, box: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(B, F) network input of M fit keypoints uv_px (B, M, 2, image pixels) with confidences (B, M, [0, 1]; 0 =
    not detected), the crop box (B, 3: x0, y0, side, pixels) and intrinsics K (B, 3, 3). Per point: box-normalized
    coordinates (uv - box centre) / side * 2 (zeroed where confidence is 0, clipped at +-COORD_CLAMP) and the
    confidence; then the box centre's unit viewing ray, log(side / fx) (the box's angular size) and the fraction
    of kept points. Shifting points and box together changes only the ray."""
    side = box[:, 2]
    n = (uv_px - box_centre_px(box)[:, None]) / side[:, None, None] * 2.0
    kept = confidence > 0
    n = torch.where(kept[..., None], n.clamp(-COORD_CLAMP, COORD_CLAMP), torch.zeros_like(n))
    c = torch.where(kept, confidence, torch.zeros_like(confidence))
    extra = [box_ray(box, K), torch.log(side / K[:, 0, 0])[:, None], kept.to(n.dtype).mean(1, keepdim=True)]
    return torch.cat([n.flatten(1), c] + extra, dim=1)


def encode_pose(T_cam_base: torch.Tensor, box: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The lifter's pose targets of T_cam<-base (B, 4, 4; metres) seen in `box` (B, 3) with K (B, 3, 3):
    R_virtual<-base (B, 3, 3), the base origin's image offset o (B, 2) from the box centre in the virtual camera,
    in box half-sides, and s (B,) = log(z side / fx) with z the origin's depth along the ray (metres).
    Inverse of `decode_pose`."""
    Rv = virtual_camera_rotation(box_ray(box, K))
    R = Rv.transpose(1, 2) @ T_cam_base[:, :3, :3]
    p = (Rv.transpose(1, 2) @ T_cam_base[:, :3, 3:4])[..., 0]
    z = p[:, 2].clamp(min=1e-3)
    side = box[:, 2]
    o = torch.stack([p[:, 0] / z * K[:, 0, 0], p[:, 1] / z * K[:, 1, 1]], dim=1) * 2.0 / side[:, None]
    return R, o, torch.log(z * side / K[:, 0, 0])


def decode_pose(R_virtual: torch.Tensor, o: torch.Tensor, s: torch.Tensor, box: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """T_cam<-base (..., 4, 4) from the lifter's outputs R_virtual<-base (B, ..., 3, 3), offset o (B, ..., 2, box
    half-sides) and log-depth s (B, ...) for boxes (B, 3) and K (B, 3, 3); `...` are hypothesis dimensions."""
    extra = R_virtual.dim() - 3
    view = (-1,) + (1,) * extra
    Rv = virtual_camera_rotation(box_ray(box, K)).reshape(view + (3, 3))
    side, fx, fy = box[:, 2].reshape(view), K[:, 0, 0].reshape(view), K[:, 1, 1].reshape(view)
    z = torch.exp(s) * fx / side
    p = torch.stack([o[..., 0] * side / (2.0 * fx) * z, o[..., 1] * side / (2.0 * fy) * z, z], dim=-1)
    T = torch.zeros(R_virtual.shape[:-2] + (4, 4), dtype=R_virtual.dtype, device=R_virtual.device)
    T[..., :3, :3] = Rv @ R_virtual
    T[..., :3, 3] = (Rv @ p[..., None])[..., 0]
    T[..., 3, 3] = 1.0
    return T


# -- the network ---------------------------------------------------------------------------------------------------
class _Block(nn.Module):
    """Pre-LayerNorm residual MLP block: x + W gelu(LN(x))."""

    def __init__(self, width: int):
        super().__init__()
        self.norm, self.fc = nn.LayerNorm(width), nn.Linear(width, width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.fc(nn.functional.gelu(self.norm(x)))


class Lifter(nn.Module):
    """2D fit keypoints -> H hypotheses of (q, T_cam<-base). Each hypothesis is J normalized joints (tanh, mapped
    into the URDF limits), a 6D rotation relative to the virtual camera, the base origin's offset from the box
    centre (box half-sides) and its log-depth via the box scale. The joint limits come from `robot`, never the file."""

    def __init__(self, cfg: LifterConfig | dict, robot: RobotModel):
        super().__init__()
        self.cfg = cfg if isinstance(cfg, LifterConfig) else LifterConfig.from_dict(cfg)
        self.robot = robot
        self.n_joints, self.n_fit_keypoints, H = robot.n_joints, robot.n_fit_keypoints, self.cfg.hypotheses
        self.register_buffer("joint_mid", ((robot.lower + robot.upper) / 2).float().cpu(), persistent=False)
        self.register_buffer("joint_half", ((robot.upper - robot.lower) / 2).float().cpu(), persistent=False)
        self.inp = nn.Linear(feature_size(self.n_fit_keypoints), self.cfg.hidden)
        self.blocks = nn.Sequential(*[_Block(self.cfg.hidden) for _ in range(self.cfg.depth - 1)])
        self.norm = nn.LayerNorm(self.cfg.hidden)
        self.out_size = self.n_joints + 6 + 3
        self.head = nn.Linear(self.cfg.hidden, H * self.out_size)
        with torch.no_grad():  # start near the identity 6D rotation, centred joints, origin at the box centre
            self.head.weight.mul_(0.1)
            bias = self.head.bias.view(H, self.out_size)
            bias.zero_()
            bias[:, self.n_joints:self.n_joints + 6] = torch.tensor([1.0, 0, 0, 0, 1.0, 0])

    def forward(self, features: torch.Tensor, bf16: bool = False) -> dict[str, torch.Tensor]:
        """Raw outputs of features (B, F): joints_norm (B, H, J, in [-1, 1]), rot6d (B, H, 6), offset o (B, H, 2,
        box half-sides), log_depth s (B, H). `bf16` runs the trunk under CPU bfloat16 autocast (training: ~3x
        faster matmuls where the CPU has AMX); the head stays float32."""
        with torch.autocast(features.device.type, dtype=torch.bfloat16, enabled=bf16):
            x = nn.functional.gelu(self.inp(features))
            x = nn.functional.gelu(self.norm(self.blocks(x)))
        y = self.head(x.to(features.dtype)).view(features.shape[0], self.cfg.hypotheses, self.out_size)
        J = self.n_joints
        return {"joints_norm": torch.tanh(y[..., :J]), "rot6d": y[..., J:J + 6], "offset": y[..., J + 6:J + 8],
                "log_depth": y[..., J + 8]}

    def set_translation_prior(self, offset: torch.Tensor, log_depth: float) -> None:
        """Set the head's bias so every hypothesis starts at the mean target offset (2,) and log-depth (the
        trainer measures them on a first batch): the log-depth of a robot is far from 0 and AdamW moves one
        bias by ~lr a step."""
        with torch.no_grad():
            bias = self.head.bias.view(self.cfg.hypotheses, self.out_size)
            bias[:, self.n_joints + 6:self.n_joints + 8] = offset.to(bias)
            bias[:, self.n_joints + 8] = float(log_depth)

    def joints(self, joints_norm: torch.Tensor) -> torch.Tensor:
        """Normalized joints in [-1, 1] -> q within the URDF limits (radians / metres)."""
        return self.joint_mid.to(joints_norm) + self.joint_half.to(joints_norm) * joints_norm

    def normalize_joints(self, q: torch.Tensor) -> torch.Tensor:
        """q (radians / metres) -> [-1, 1] over the URDF limits (the inverse of `joints`)."""
        return (q - self.joint_mid.to(q)) / self.joint_half.to(q)

    def hypotheses(self, uv: torch.Tensor, confidence: torch.Tensor, box: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(q (B, H, J) radians / metres, T_cam<-base (B, H, 4, 4) metres) of 2D fit keypoints uv (B, M, 2, image
        pixels), confidences (B, M), crop boxes (B, 3) and K (B, 3, 3). Runs the MLP in its own dtype; the
        outputs have the inputs' dtype (pass float64 to get float64 poses)."""
        uv = torch.as_tensor(uv)
        dtype = uv.dtype if uv.dtype.is_floating_point else torch.float32
        param = next(self.parameters())
        uv, confidence, box, K = (torch.as_tensor(a, dtype=dtype, device=param.device) for a in (uv, confidence, box, K))
        out = self(lifter_features(uv, confidence, box, K).to(param.dtype))
        out = {k: v.to(dtype) for k, v in out.items()}
        R = rot6d_to_matrix(out["rot6d"])
        return self.joints(out["joints_norm"]), decode_pose(R, out["offset"], out["log_depth"], box, K)


def hypothesis_keypoints(robot: RobotModel, q: torch.Tensor, T_cam_base: torch.Tensor) -> torch.Tensor:
    """(B, H, M, 3) fit keypoints in the camera frame (metres) of hypotheses q (B, H, J), T_cam<-base (B, H, 4, 4);
    in the robot's dtype."""
    B, H = q.shape[:2]
    kp = robot.fit_keypoints_in_camera(q.reshape(B * H, -1).to(robot.dtype), T_cam_base.reshape(B * H, 4, 4).to(robot.dtype))
    return kp.view(B, H, -1, 3)


def keypoint_reprojection_errors(keypoints_cam: torch.Tensor, uv: torch.Tensor, confidence: torch.Tensor,
                                 K: torch.Tensor) -> torch.Tensor:
    """(B, H) confidence-weighted mean pixel distance between hypotheses' camera-frame fit keypoints (B, H, M, 3,
    metres) projected with K (B, 3, 3) and the detections uv (B, M, 2, pixels; confidence (B, M)). A point behind
    the camera counts 10^4 px."""
    kp = keypoints_cam.to(uv.dtype)
    Kb = K.to(uv.dtype)[:, None, None]
    z = kp[..., 2].clamp(min=1e-3)
    proj = torch.stack([Kb[..., 0, 0] * kp[..., 0] / z + Kb[..., 0, 1] * kp[..., 1] / z + Kb[..., 0, 2],
                        Kb[..., 1, 1] * kp[..., 1] / z + Kb[..., 1, 2]], dim=-1)
    dist = (proj - uv[:, None]).norm(dim=-1)
    dist = torch.where(kp[..., 2] > 1e-3, dist, torch.full_like(dist, 1e4))
    w = confidence.to(uv.dtype)[:, None]
    return (w * dist).sum(-1) / w.sum(-1).clamp(min=1e-9)


def reprojection_errors(robot: RobotModel, q: torch.Tensor, T_cam_base: torch.Tensor, uv: torch.Tensor,
                        confidence: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(B, H) confidence-weighted mean pixel distance between the projected fit keypoints of hypotheses
    (q (B, H, J), T_cam<-base (B, H, 4, 4)) and the detected uv (B, M, 2, pixels; confidence (B, M)): how the
    estimator ranks hypotheses without ground truth (argmin over H)."""
    return keypoint_reprojection_errors(hypothesis_keypoints(robot, q, T_cam_base), uv, confidence, K)


# -- weights as data -----------------------------------------------------------------------------------------------
def fit_keypoints_hash(robot: RobotModel) -> str:
    """sha256 (first 16 hex digits) of the robot's fit keypoints (name, link, offset in micrometres) and joint
    names: a lifter is only valid for exactly these."""
    lines = [f"{k.name} {k.link} " + " ".join(f"{round(v * 1e6)}" for v in k.xyz) for k in robot.spec.fit_keypoints]
    lines += [f"joint {n}" for n in robot.joint_names]
    return hashlib.sha256("\n".join(lines).encode()).hexdigest()[:16]


def resolve_lifter(path: str | Path) -> Path:
    """The card (.yaml) of a lifter from a card or weights path, a path without suffix, or a shipped name
    ('panda_lifter')."""
    p = Path(path)
    if p.suffix == ".safetensors":
        p = p.with_suffix(".yaml")
    elif p.suffix != ".yaml":
        local = Path(str(p) + ".yaml")
        p = local if local.is_file() else weights_dir() / f"{p.name}.yaml"
    if not p.is_file():
        shipped = sorted(x.stem for x in weights_dir().glob("*_lifter.yaml"))
        raise FileNotFoundError(f"lifter card not found: {p} (shipped lifters: {', '.join(shipped) or 'none'})")
    return p


def shipped_lifter(robot_name: str) -> Path | None:
    """The card of a robot's shipped lifter (weights/<robot>_lifter.yaml), or None when it has none: what fits a
    network whose card names no lifter (a training run's card, its validation)."""
    p = weights_dir() / f"{robot_name}_lifter.yaml"
    return p if p.is_file() else None


def save_lifter(lifter: Lifter, path: str | Path, card: dict | None = None, dtype: torch.dtype = torch.float32) -> Path:
    """Write `path`.safetensors (weights in `dtype`) and the card `path`.yaml beside it: robot, fit keypoint count
    and hash, joint names, model config, plus `card` (training, validation, ...). Returns the card's path."""
    path = Path(path)
    if path.suffix in (".yaml", ".safetensors"):
        path = path.with_suffix("")
    path.parent.mkdir(parents=True, exist_ok=True)
    weights = path.parent / f"{path.name}.safetensors"
    robot = lifter.robot
    state = {k: v.detach().to(dtype).cpu().contiguous() for k, v in lifter.state_dict().items()}
    save_file(state, str(weights), metadata={"robot": robot.name, "kind": "lifter"})
    full = {"kind": "lifter", "robot": robot.name, "weights": weights.name, "weights_sha256": file_sha256(weights),
            "fit_keypoints": {"count": robot.n_fit_keypoints, "hash": fit_keypoints_hash(robot)},
            "joints": list(robot.joint_names), "model": lifter.cfg.to_dict(), **(card or {})}
    card_path = path.parent / f"{path.name}.yaml"
    with open(card_path, "w") as f:
        yaml.safe_dump(full, f, sort_keys=False)
    return card_path


def load_lifter(path_or_card: str | Path, device: str | torch.device = "cpu", robot: RobotModel | None = None) -> Lifter:
    """The lifter (eval mode, float32) of a card or weights path, or a shipped name. `robot` (default: the card's
    robot from its YAML) must have the fit keypoints and joints the lifter was trained for, else ValueError."""
    card_path = resolve_lifter(path_or_card)
    card = read_card_file(card_path)
    if card.get("kind") != "lifter":
        raise ModelLoadError(f"{card_path}: not a lifter card (kind: {card.get('kind')})")
    check_card_keys(card_path, card, LIFTER_CARD_KEYS, ("robot", "weights", "fit_keypoints", "model"))
    state = {k: v.float() for k, v in read_weights(card_path, card).items()}
    robot = robot or RobotModel(card["robot"], device=device)
    want, have = card["fit_keypoints"], {"count": robot.n_fit_keypoints, "hash": fit_keypoints_hash(robot)}
    if robot.name != card["robot"] or want["count"] != have["count"] or want["hash"] != have["hash"]:
        raise ModelLoadError(
            f"{card_path}: this lifter was trained for robot '{card['robot']}' with {want['count']} fit keypoints "
            f"(hash {want['hash']}), but robot '{robot.name}' ({robot.spec.source_file}) now has {have['count']} "
            f"(hash {have['hash']}): its fit keypoints or joints changed; retrain with "
            f"`holo-pose train-lifter --robot {robot.name}`")
    lifter = Lifter(LifterConfig.from_dict(card["model"]), robot)
    try:
        lifter.load_state_dict(state)
    except RuntimeError as e:
        raise ModelLoadError(f"{card_path}: weights do not match the lifter ({str(e).splitlines()[0]})") from e
    lifter.card = card
    return lifter.to(device).eval()
