"""Domain randomization: draw one synthetic frame's scene (joints, camera pose, link materials, light,
distractor objects) from the ranges of a generator YAML. The robot base is the world frame (z up); metres."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from holo_pose_ros.data.render import Light, Material, Primitive
from holo_pose_ros.geometry.camera import intrinsics_matrix, look_at


@dataclass
class FrameScene:
    """Everything the renderer and the writer need for one frame."""

    joints: np.ndarray          # (J,) radians / metres, YAML order
    T_cam_base: np.ndarray      # (4, 4) robot base in the camera frame
    materials: dict[str, Material]
    light: Light
    distractors: list[Primitive]


def _uniform(rng: np.random.Generator, bounds) -> float:
    return float(rng.uniform(float(bounds[0]), float(bounds[1])))


def sample_intrinsics(cfg: dict, rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """K (3x3) of a folder's camera, focal length scaled with the image width."""
    fx = _uniform(rng, cfg["focal_px_at_640"]) * width / 640.0
    fy = fx * (1.0 + rng.uniform(-1, 1) * cfg["aspect_jitter"])
    cx = width / 2.0 + rng.uniform(-1, 1) * cfg["principal_offset_frac"] * width
    cy = height / 2.0 + rng.uniform(-1, 1) * cfg["principal_offset_frac"] * height
    return intrinsics_matrix(fx, fy, cx, cy)


def _robot_extent(points_base: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (3,) and radius (metres) of a sphere around the robot's link origins, padded for the meshes."""
    centre = (points_base.min(0) + points_base.max(0)) / 2.0
    radius = float(np.linalg.norm(points_base - centre, axis=1).max()) * 1.1 + 0.08
    return centre, radius


def sample_camera(cfg: dict, rng: np.random.Generator, centre: np.ndarray, radius: float, K: np.ndarray, height: int) -> np.ndarray:
    """T_cam<-base for a camera around the robot: distance from the wanted image fill, random azimuth,
    elevation and roll, look-at point jittered around the robot centre (close-ups and truncation included)."""
    fill = _uniform(rng, cfg["fill"])
    distance = radius * K[1, 1] / (fill * height / 2.0)
    azimuth = np.radians(_uniform(rng, cfg["azimuth_deg"]))
    elevation = np.radians(_uniform(rng, cfg["elevation_deg"]))
    target = centre + rng.normal(0.0, cfg["look_at_jitter"] * radius / max(fill, 1.0), 3)
    eye = target + distance * np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    sigma = np.radians(cfg["roll_deg_sigma"])
    roll = float(np.clip(rng.normal(0.0, sigma), -3 * sigma, 3 * sigma))
    return np.linalg.inv(look_at(eye, target, roll=roll))


def _random_material(cfg: dict, rng: np.random.Generator, base_colour: np.ndarray | None) -> Material:
    """A link or object material: its own colour (jittered) or a random colour and procedural pattern."""
    if base_colour is not None:
        colour = np.clip(base_colour * rng.uniform(0.85, 1.15) + rng.normal(0, 0.03, 3), 0, 1)
        return Material(colour.astype(np.float32), colour.astype(np.float32), "plain", 0.05,
                        _uniform(rng, cfg["specular"]), _uniform(rng, cfg["shininess"]))
    patterns = cfg["patterns"]
    return Material(
        rng.uniform(0, 1, 3).astype(np.float32), rng.uniform(0, 1, 3).astype(np.float32),
        str(patterns[rng.integers(len(patterns))]), _uniform(rng, cfg["pattern_scale_m"]),
        _uniform(rng, cfg["specular"]), _uniform(rng, cfg["shininess"]),
    )


def _random_light(cfg: dict, rng: np.random.Generator) -> Light:
    """A directional light mostly from the camera side and above, with a tinted colour and ambient term."""
    direction = np.array([rng.uniform(-1, 1), rng.uniform(-0.2, 1), rng.uniform(0.2, 1.2)])
    intensity = _uniform(rng, cfg["intensity"])
    tint = 1.0 + rng.uniform(-1, 1, 3) * cfg["tint"]
    ambient = _uniform(rng, cfg["ambient"]) * (1.0 + rng.uniform(-1, 1, 3) * cfg["tint"])
    return Light((direction / np.linalg.norm(direction)).astype(np.float32),
                 np.clip(intensity * tint, 0, 2).astype(np.float32), np.clip(ambient, 0, 1).astype(np.float32))


def _random_distractors(cfg: dict, appearance: dict, rng: np.random.Generator, T_cam_base: np.ndarray,
                        keypoints_base: np.ndarray, radius: float, K: np.ndarray, width: int, height: int) -> list[Primitive]:
    """Boxes, spheres and cylinders around the robot; some placed on the line of sight to a keypoint."""
    out = []
    kp_cam = keypoints_base @ T_cam_base[:3, :3].T + T_cam_base[:3, 3]
    robot_depth = float(np.median(kp_cam[:, 2]))
    for _ in range(int(rng.integers(cfg["count"][0], cfg["count"][1] + 1))):
        size = np.array([_uniform(rng, cfg["size"]) * radius for _ in range(3)]) * 0.5
        if rng.random() < cfg["occluder_probability"]:
            fraction = rng.uniform(0.35, 0.85)  # of the way to a keypoint; shrink with it to keep the angular size
            p = kp_cam[rng.integers(len(kp_cam))] * fraction
            size *= fraction
        else:
            z = rng.uniform(0.4, 1.6) * robot_depth
            uv1 = np.array([rng.uniform(0, width), rng.uniform(0, height), 1.0])
            p = np.linalg.solve(K, uv1) * z
        if p[2] - size.max() < 0.1:  # keep it in front of the near plane
            continue
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        T = np.eye(4)
        T[:3, :3] = q * np.sign(np.linalg.det(q))
        T[:3, 3] = p
        kind = ("box", "sphere", "cylinder")[rng.integers(3)]
        out.append(Primitive(kind, size.astype(np.float32), T, _random_material(appearance, rng, None)))
    return out


def sample_scene(model, cfg: dict, rng: np.random.Generator, K: np.ndarray, width: int, height: int,
                 link_colours: dict[str, np.ndarray]) -> FrameScene:
    """Draw one frame: joints uniform within the URDF limits, then camera, materials, light and distractors.
    `model` is a float64 RobotModel; `link_colours` the meshes' own colours (for the realistic look)."""
    import torch

    lower, upper = model.lower.numpy(), model.upper.numpy()
    q = rng.uniform(lower, upper)
    links = model.link_transforms(torch.from_numpy(q[None]))
    origins = np.stack([T[0, :3, 3].numpy() for T in links.values()])
    keypoints = model.keypoints(torch.from_numpy(q[None]))[0].numpy()
    centre, radius = _robot_extent(origins)
    T_cam_base = sample_camera(cfg["camera"], rng, centre, radius, K, height)
    appearance = cfg["appearance"]
    realistic = rng.random() < appearance["realistic_colour_probability"]
    materials = {link: _random_material(appearance, rng, colour if realistic else None) for link, colour in link_colours.items()}
    return FrameScene(
        joints=q,
        T_cam_base=T_cam_base,
        materials=materials,
        light=_random_light(cfg["lighting"], rng),
        distractors=_random_distractors(cfg["distractors"], appearance, rng, T_cam_base, keypoints, radius, K, width, height),
    )
