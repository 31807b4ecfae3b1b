"""Domain randomization: draw one synthetic frame's scene (joints, camera pose, link materials, light, shading,
distractor objects) from the ranges of a generator YAML. The robot base is the world frame (z up); metres.
`sample_two_robot_scene` adds a second robot beside the first (config/generate/scene/second_robot.yaml).
Optional appearance keys (`flat_colours`, `shading`) draw nothing from the rng when a YAML leaves them out."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from holo_pose_ros.data.render import Light, Material, Primitive, Shading
from holo_pose_ros.geometry.camera import intrinsics_matrix, look_at


@dataclass
class PlacedRobot:
    """A further robot of a scene: its joints and where its base stands."""

    joints: np.ndarray          # (J,) radians / metres, its YAML order
    T_cam_base: np.ndarray      # (4, 4) its base in the camera frame


@dataclass
class FrameScene:
    """Everything the renderer and the writer need for one frame."""

    joints: np.ndarray          # (J,) radians / metres, YAML order
    T_cam_base: np.ndarray      # (4, 4) robot base in the camera frame
    materials: dict[str, Material]  # every link of every robot of the scene
    light: Light
    distractors: list[Primitive]
    others: list[PlacedRobot] = field(default_factory=list)  # robots besides the first (none by default)
    shading: Shading = Shading()  # how the frame is lit (Blinn-Phong unless appearance.shading says otherwise)


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


def _flat_material(appearance: dict, flat: dict, rng: np.random.Generator) -> Material:
    """An untextured material (plain pattern) of one random colour: a grey (probability flat.grey_probability) or
    a hue uniform on the colour wheel; saturation and value (brightness, 0..1) from flat.saturation and
    flat.value, specular terms from the appearance ranges."""
    grey = rng.random() < flat["grey_probability"]
    hue_deg = 0.0 if grey else rng.uniform(0.0, 360.0)
    saturation = 0.0 if grey else _uniform(rng, flat["saturation"])
    hsv = np.array([[[hue_deg, saturation, _uniform(rng, flat["value"])]]], np.float32)  # OpenCV float HSV
    colour = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0]
    return Material(colour, colour, "plain", 0.05, _uniform(rng, appearance["specular"]),
                    _uniform(rng, appearance["shininess"]))


def _link_materials(appearance: dict, rng: np.random.Generator, link_colours: dict[str, np.ndarray]) -> dict[str, Material]:
    """Every link's material for one frame: all the links' own colours (probability realistic_colour_probability),
    else, with the optional `flat_colours` section and its probability, each link its own untextured colour,
    else random colours and patterns."""
    if rng.random() < appearance["realistic_colour_probability"]:
        return {link: _random_material(appearance, rng, colour) for link, colour in link_colours.items()}
    flat = appearance.get("flat_colours")
    if flat is not None and rng.random() < flat["probability"]:
        return {link: _flat_material(appearance, flat, rng) for link in link_colours}
    return {link: _random_material(appearance, rng, None) for link in link_colours}


def _random_shading(appearance: dict, rng: np.random.Generator) -> Shading:
    """The frame's shading: Blinn-Phong without the optional `shading` list (no draw), else a pick from it
    (weights `shading_probabilities`, default uniform); toon's band count uniform in `toon_bands` (integers)."""
    modes = appearance.get("shading")
    if modes is None:
        return Shading()
    mode = str(rng.choice(modes, p=appearance.get("shading_probabilities")))
    if mode != "toon":
        return Shading(mode)
    low, high = appearance["toon_bands"]
    return Shading(mode, int(rng.integers(low, high + 1)))


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


def sample_static_camera(model, cfg: dict, rng: np.random.Generator, K: np.ndarray, height: int,
                         joints: np.ndarray | None = None) -> np.ndarray:
    """T_cam<-base of a camera that stays put while the robot moves (generator option camera.static, and each clip
    of a video): drawn as for one frame, aimed at the centre of the pose `joints` (default: the neutral pose), its
    extent grown by camera.static_radius_scale and filling camera.static_fill of the image, so that most poses
    near it stay in view."""
    import torch

    q = model.neutral[None].to(model.dtype) if joints is None else torch.as_tensor(np.asarray(joints)[None], dtype=model.dtype)
    links = model.link_transforms(q)
    origins = np.stack([T[0, :3, 3].numpy() for T in links.values()])
    centre, radius = _robot_extent(origins)
    framing = {**cfg, "fill": cfg["static_fill"], "look_at_jitter": 0.0}
    return sample_camera(framing, rng, centre, radius * float(cfg["static_radius_scale"]), K, height)


def sample_scene(model, cfg: dict, rng: np.random.Generator, K: np.ndarray, width: int, height: int,
                 link_colours: dict[str, np.ndarray], T_cam_base: np.ndarray | None = None,
                 joints: np.ndarray | None = None) -> FrameScene:
    """Draw one frame: joints uniform within the URDF limits (unless `joints` fixes them), then camera (unless
    `T_cam_base` fixes it), materials, light, distractors and shading. `model` is a float64 RobotModel;
    `link_colours` the meshes' own colours (for the realistic look)."""
    import torch

    lower, upper = model.lower.numpy(), model.upper.numpy()
    q = rng.uniform(lower, upper) if joints is None else np.asarray(joints, dtype=np.float64)
    links = model.link_transforms(torch.from_numpy(q[None]))
    origins = np.stack([T[0, :3, 3].numpy() for T in links.values()])
    keypoints = model.keypoints(torch.from_numpy(q[None]))[0].numpy()
    centre, radius = _robot_extent(origins)
    if T_cam_base is None:
        T_cam_base = sample_camera(cfg["camera"], rng, centre, radius, K, height)
    appearance = cfg["appearance"]
    return FrameScene(
        joints=q,
        T_cam_base=T_cam_base,
        materials=_link_materials(appearance, rng, link_colours),
        light=_random_light(cfg["lighting"], rng),
        distractors=_random_distractors(cfg["distractors"], appearance, rng, T_cam_base, keypoints, radius, K, width, height),
        shading=_random_shading(appearance, rng),
    )


def _pose_sample(model, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joints uniform within the URDF limits; (q, link origins (L, 3), keypoints (N, 3)) in the base frame."""
    import torch

    q = rng.uniform(model.lower.numpy(), model.upper.numpy())
    links = model.link_transforms(torch.from_numpy(q[None]))
    origins = np.stack([T[0, :3, 3].numpy() for T in links.values()])
    return q, origins, model.keypoints(torch.from_numpy(q[None]))[0].numpy()


def place_beside(centre: np.ndarray, radius: float, other_centre: np.ndarray, other_radius: float, gap_m: float,
                 direction_rad: float, yaw_rad: float) -> np.ndarray:
    """T_base<-other_base (4, 4): the other robot's base on the same floor (z = 0), turned by `yaw_rad` about z, its
    bounding sphere (other_centre, other_radius in its own base frame) `gap_m` beyond the first's (centre, radius)
    along the horizontal direction `direction_rad`: the two spheres' centres are radius + other_radius + gap_m
    apart horizontally, so the robots never touch. Metres, radians."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    distance = radius + other_radius + gap_m
    target_xy = centre[:2] + distance * np.array([np.cos(direction_rad), np.sin(direction_rad)])
    T[:2, 3] = target_xy - (T[:3, :3] @ other_centre)[:2]
    return T


def sample_two_robot_scene(model, second, cfg: dict, placement: dict, rng: np.random.Generator, K: np.ndarray,
                           width: int, height: int, link_colours: dict[str, np.ndarray],
                           second_colours: dict[str, np.ndarray]) -> FrameScene:
    """One frame of two robots: joints of each uniform within its limits, the second beside the first
    (`place_beside`, gap and yaw drawn from `placement`), the camera framing both and looking across the line
    between them (azimuth within placement.camera.across_deg of its perpendicular, either side), so that neither
    hides the other; then materials (both robots' links), light, distractors and shading as `sample_scene`. The first
    robot's base is the world frame; the second robot is scene.others[0]."""
    q1, origins1, kp1 = _pose_sample(model, rng)
    q2, origins2, kp2 = _pose_sample(second, rng)
    c1, r1 = _robot_extent(origins1)
    c2, r2 = _robot_extent(origins2)
    direction = rng.uniform(0.0, 2.0 * np.pi)
    T_12 = place_beside(c1, r1, c2, r2, _uniform(rng, placement["gap_m"]), direction,
                        np.radians(_uniform(rng, placement["yaw_deg"])))
    c2_in_1 = T_12[:3, :3] @ c2 + T_12[:3, 3]
    centre = (c1 + c2_in_1) / 2.0
    radius = max(np.linalg.norm(c1 - centre) + r1, np.linalg.norm(c2_in_1 - centre) + r2)
    camera = {**cfg["camera"], **{k: v for k, v in placement["camera"].items() if k != "across_deg"}}
    side = 1.0 if rng.random() < 0.5 else -1.0
    azimuth = np.degrees(direction) + side * 90.0 + rng.uniform(-1, 1) * placement["camera"]["across_deg"]
    camera["azimuth_deg"] = [azimuth, azimuth]
    T_cam_base = sample_camera(camera, rng, centre, radius, K, height)
    appearance = cfg["appearance"]
    materials = _link_materials(appearance, rng, {**link_colours, **second_colours})
    keypoints = np.concatenate([kp1, kp2 @ T_12[:3, :3].T + T_12[:3, 3]])
    return FrameScene(
        joints=q1,
        T_cam_base=T_cam_base,
        materials=materials,
        light=_random_light(cfg["lighting"], rng),
        distractors=_random_distractors(cfg["distractors"], appearance, rng, T_cam_base, keypoints, radius, K,
                                        width, height),
        others=[PlacedRobot(q2, T_cam_base @ T_12)],
        shading=_random_shading(appearance, rng),
    )
