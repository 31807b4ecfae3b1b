"""Synthetic data generator: renders randomized frames of a robot and writes them as a DREAM folder with a
label mask per frame (`NNNNNN.mask.png`: 0 background, 1 + link index for robot pixels, 255 distractors).
Frame i depends only on (seed, i), so the output is identical for any number of workers.

With `second_robot` (another robot type) each frame also shows that robot beside the first, both in its ground
truth (one DREAM object each, so that each robot's DreamReader reads its own) and in the mask (its links numbered
after the first robot's); placement from config/generate/scene/second_robot.yaml.

A configuration with a `video:` section (config/generate/video.yaml) writes videos instead of independent frames:
clips of `clip_frames` frames, each with one camera, look and background, the robot moving smoothly
(data/motion.py); frame i still depends only on (seed, i). A configuration may start from another with
`extends: NAME` and give only what differs."""

from __future__ import annotations

import dataclasses
import json
import multiprocessing as mp
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import yaml
from tqdm import tqdm

from holo_pose_ros.resources import config_dir

if TYPE_CHECKING:
    from holo_pose_ros.data.scene import FrameScene

DISTRACTOR_LABEL = 255
SETTINGS_FILE = "_generator_settings.json"  # how the folder was made (DREAM readers ignore it)
SECOND_ROBOT_FILE = "scene/second_robot.yaml"  # under config/generate: where a second robot stands


def load_generator_config(config: str | Path) -> dict:
    """A generator YAML by name (config/generate/<name>.yaml) or path."""
    path = Path(config)
    if not path.suffix:
        path = config_dir() / "generate" / f"{config}.yaml"
    if not path.is_file():
        names = sorted(p.stem for p in (config_dir() / "generate").glob("*.yaml"))
        raise ValueError(f"unknown generator config '{config}'; shipped: {', '.join(names)}")
    with open(path) as f:
        cfg = yaml.safe_load(f)
    base = cfg.pop("extends", None)
    return _merged(load_generator_config(base), cfg) if base else cfg


def is_video_folder(folder: str | Path) -> bool:
    """Whether a DREAM folder is a generated video (its settings file names a `video:` section): its frames are
    then clips in order, not independent scenes."""
    path = Path(folder) / SETTINGS_FILE
    if not path.is_file():
        return False
    try:
        return bool((json.loads(path.read_text()).get("generator") or {}).get("video"))
    except (json.JSONDecodeError, AttributeError):
        return False


def _merged(base: dict, override: dict) -> dict:
    """`base` with `override`'s keys replacing its own, mappings merged key by key."""
    out = dict(base)
    for key, value in override.items():
        out[key] = _merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


@dataclass(frozen=True)
class GenerateJob:
    """What every worker needs to render any frame of one folder."""

    robot: str
    out: str
    seed: int
    width: int
    height: int
    K: tuple
    config: dict
    max_faces: int = 12000
    second_robot: str | None = None  # another robot in every frame (config["second_robot"] places it)


@dataclass(frozen=True)
class GenerateSummary:
    n_frames: int
    seconds: float

    @property
    def fps(self) -> float:
        return self.n_frames / max(self.seconds, 1e-9)


class FrameRenderer:
    """Renders and writes frames of one job; one per process (it owns a GL context)."""

    def __init__(self, job: GenerateJob):
        import torch

        from holo_pose_ros.data.dream import DreamWriter
        from holo_pose_ros.data.meshes import load_link_meshes
        from holo_pose_ros.data.render import Renderer
        from holo_pose_ros.robots.kinematics import RobotModel

        torch.set_num_threads(1)
        self.job = job
        self.model = RobotModel(job.robot, dtype=torch.float64)
        self.meshes = load_link_meshes(self.model, max_faces=job.max_faces)
        self.renderer = Renderer(job.width, job.height)
        self.K = np.asarray(job.K, dtype=np.float64)
        self.colours = {link: mesh.color for link, mesh in self.meshes.items()}
        self.second, self.all_meshes, self.second_colours = None, self.meshes, {}
        if job.second_robot:
            self.second = RobotModel(job.second_robot, dtype=torch.float64)
            second_meshes = load_link_meshes(self.second, max_faces=job.max_faces)
            shared = sorted(set(second_meshes) & set(self.meshes))
            if shared:
                raise ValueError(f"robots {job.robot} and {job.second_robot} share link names {shared}")
            self.all_meshes = {**self.meshes, **second_meshes}  # labels: the first robot's links, then the second's
            self.second_colours = {link: mesh.color for link, mesh in second_meshes.items()}
        self.writer = DreamWriter(job.out, self.model, self.K, job.width, job.height,
                                  others=[self.second] if self.second is not None else ())
        self.video = job.config.get("video")
        if self.video and self.second is not None:
            raise ValueError("a video configuration shows one robot; it cannot have a second_robot")
        self.static_T_cam_base = None  # camera.static: one camera pose for the whole folder, the robot moves
        if job.config["camera"].get("static", False):
            from holo_pose_ros.data.scene import sample_static_camera

            self.static_T_cam_base = sample_static_camera(self.model, job.config["camera"],
                                                          np.random.default_rng([job.seed, 0, 1]), self.K, job.height)

    def frame(self, index: int) -> tuple[np.ndarray, np.ndarray, FrameScene]:
        """Render frame `index`: (RGB uint8 image, label mask uint8, the scene drawn)."""
        import torch

        from holo_pose_ros.data.backgrounds import random_background
        from holo_pose_ros.data.scene import sample_scene, sample_two_robot_scene

        job, cfg = self.job, self.job.config
        rng = np.random.default_rng([job.seed, index + 1])
        frame_rng = rng  # the sensor's noise: its own draw every frame, videos included
        if self.video:
            scene, rng = self._video_scene(index)
        elif self.second is None:
            scene = sample_scene(self.model, cfg, rng, self.K, job.width, job.height, self.colours,
                                 self.static_T_cam_base)
        else:
            scene = sample_two_robot_scene(self.model, self.second, cfg, cfg["second_robot"], rng, self.K, job.width,
                                           job.height, self.colours, self.second_colours)
        links = self.model.link_transforms(torch.from_numpy(scene.joints[None]), list(self.meshes))
        poses = {link: scene.T_cam_base @ T[0].numpy() for link, T in links.items()}
        for other in scene.others:  # the second robot's links (its meshes follow the first robot's)
            links = self.second.link_transforms(torch.from_numpy(other.joints[None]),
                                                [link for link in self.all_meshes if link not in self.meshes])
            poses.update({link: other.T_cam_base @ T[0].numpy() for link, T in links.items()})
        result = self.renderer.render(poses, self.all_meshes, self.K, scene.materials, scene.light,
                                      scene.distractors, scene.shading)
        background = random_background(rng, job.height, job.width, tuple(cfg["background"]["layers"]),
                                       tuple(cfg["background"]["kinds"]))
        alpha = result.rgba[..., 3:4].astype(np.float32) / 255.0
        image = result.rgba[..., :3].astype(np.float32) * alpha + background * (1.0 - alpha)
        return _post_process(image, cfg["post"], frame_rng), result.labels, scene

    def _video_scene(self, index: int) -> tuple[FrameScene, np.random.Generator]:
        """Frame `index` of a video folder and the generator its clip's background is drawn with: clip
        index // clip_frames keeps one camera (framing its start pose), look and background, all drawn from
        (seed, clip); its joints follow data/motion.py's waypoint path from that start pose."""
        from holo_pose_ros.data.motion import waypoint_path
        from holo_pose_ros.data.scene import sample_scene, sample_static_camera

        job, cfg, video = self.job, self.job.config, self.video
        clip, t = divmod(index, int(video["clip_frames"]))
        rng = np.random.default_rng([job.seed, clip + 1, 1])  # frames draw from [seed, index + 1]: another stream
        lower, upper = self.model.lower.numpy(), self.model.upper.numpy()
        start = rng.uniform(lower, upper)
        T_cam_base = sample_static_camera(self.model, cfg["camera"], rng, self.K, job.height, start)
        scene = sample_scene(self.model, cfg, rng, self.K, job.width, job.height, self.colours, T_cam_base, start)
        path = waypoint_path(lower, upper, start, t + 1, np.random.default_rng([job.seed, clip + 1, 2]),
                             tuple(video["leg_frames"]), float(video["reach"]))
        return dataclasses.replace(scene, joints=path[t]), rng

    def write(self, index: int) -> int:
        image, labels, scene = self.frame(index)
        self.writer.write(index, image, scene.joints, scene.T_cam_base, mask=labels,
                          others=[(o.joints, o.T_cam_base) for o in scene.others])
        return index


UPSCALE_INTERPOLATIONS = {"linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC}  # post.upscale_interpolation


def _post_process(image: np.ndarray, cfg: dict, rng: np.random.Generator) -> np.ndarray:
    """Camera-like degradations of a float RGB image (grey levels 0..255) -> uint8 RGB, in the order a camera
    applies them: per-channel gain; optics (motion blur, Gaussian blur, vignetting); a lower-resolution sensor
    (downscale then upscale); sensor noise (shot, then Gaussian read noise); tone curve; JPEG. Steps other than
    gain, blur and read noise run only when their optional key is set in `cfg` and draw nothing from `rng`
    otherwise, so older configs give the same pixels for the same rng."""
    image = image * rng.uniform(cfg["colour_gain"][0], cfg["colour_gain"][1], 3).astype(np.float32)
    if (lengths := cfg.get("motion_blur_length_px")) and rng.random() < cfg.get("motion_blur_probability", 1.0):
        image = motion_blur(image, rng.uniform(*lengths), rng.uniform(0.0, np.pi))
    if rng.random() < cfg["blur_probability"]:
        image = cv2.GaussianBlur(image, (0, 0), rng.uniform(*cfg["blur_sigma_px"]))
    if strengths := cfg.get("vignette_strength"):
        image = vignette(image, rng.uniform(*strengths))
    if factors := cfg.get("downscale_factor"):
        names = cfg.get("upscale_interpolation", ["linear"])
        image = resample(image, rng.uniform(*factors), UPSCALE_INTERPOLATIONS[names[rng.integers(len(names))]])
    if gains := cfg.get("shot_noise_gain"):
        image = shot_noise(image, rng.uniform(*gains), rng)
    sigma = rng.uniform(*cfg["noise_sigma"])
    if sigma > 0:
        image = image + rng.normal(0.0, sigma, image.shape).astype(np.float32)
    gammas, contrasts = cfg.get("tone_gamma"), cfg.get("tone_contrast")
    if gammas or contrasts:
        image = tone_curve(image, rng.uniform(*gammas) if gammas else 1.0,
                           rng.uniform(*contrasts) if contrasts else 0.0)
    image = np.clip(image, 0, 255).astype(np.uint8)
    if qualities := cfg.get("jpeg_quality"):
        image = jpeg_roundtrip(image, int(rng.integers(qualities[0], qualities[1] + 1)))
    return image


def motion_blur(image: np.ndarray, length_px: float, angle_rad: float) -> np.ndarray:
    """Linear motion blur: the mean of the image along a segment `length_px` long (pixels) at `angle_rad` from
    the image x axis, centred on each pixel (an anti-aliased line kernel)."""
    if length_px <= 1.0:
        return image
    size = int(np.ceil(length_px)) | 1
    centre, half = size / 2.0 - 0.5, length_px / 2.0 - 0.5
    dx, dy = half * np.cos(angle_rad), half * np.sin(angle_rad)
    shift = 4  # cv2.line's fixed-point sub-pixel coordinates: 2^shift units per pixel
    p0 = (round((centre - dx) * 2 ** shift), round((centre - dy) * 2 ** shift))
    p1 = (round((centre + dx) * 2 ** shift), round((centre + dy) * 2 ** shift))
    kernel = cv2.line(np.zeros((size, size), np.float32), p0, p1, 1.0, 1, cv2.LINE_AA, shift=shift)
    return cv2.filter2D(image, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REFLECT)


def vignette(image: np.ndarray, strength: float) -> np.ndarray:
    """Lens vignetting: brightness falls off as 1 - strength r^2, r the distance from the image centre over the
    half-diagonal (corners keep 1 - strength of their brightness)."""
    h, w = image.shape[:2]
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = ((x - (w - 1) / 2.0) ** 2 + (y - (h - 1) / 2.0) ** 2) / (((w - 1) / 2.0) ** 2 + ((h - 1) / 2.0) ** 2)
    return image * (1.0 - strength * r2)[..., None]


def resample(image: np.ndarray, factor: float, interpolation: int) -> np.ndarray:
    """A lower-resolution sensor: shrink by `factor` (>= 1) with area averaging, then enlarge back to the input
    size with `interpolation` (cv2.INTER_LINEAR or INTER_CUBIC); detail finer than `factor` pixels is lost."""
    h, w = image.shape[:2]
    small = cv2.resize(image, (max(1, round(w / factor)), max(1, round(h / factor))), interpolation=cv2.INTER_AREA)
    return cv2.resize(small, (w, h), interpolation=interpolation)


def shot_noise(image: np.ndarray, gain: float, rng: np.random.Generator) -> np.ndarray:
    """Signal-dependent (photon shot) noise, Gaussian approximation of Poisson: variance `gain` x signal, in grey
    levels (gain = grey levels per photo-electron)."""
    sigma = np.sqrt(gain * np.maximum(image, 0.0))
    return image + (rng.standard_normal(image.shape, dtype=np.float32) * sigma).astype(np.float32)


def tone_curve(image: np.ndarray, gamma: float, contrast: float) -> np.ndarray:
    """A camera's tone curve on grey levels 0..255: x^gamma on x in [0, 1] (gamma < 1 brightens), then an S curve
    x + contrast (smoothstep(x) - x) (contrast in [-1, 1]: > 0 steeper mid-tones, < 0 flatter; monotonic)."""
    x = np.clip(image / 255.0, 0.0, 1.0) ** gamma
    x = x + contrast * (x * x * (3.0 - 2.0 * x) - x)
    return (x * 255.0).astype(np.float32)


def jpeg_roundtrip(image: np.ndarray, quality: int) -> np.ndarray:
    """Encode a uint8 RGB image as JPEG at `quality` (0..100) and decode it: block and ringing artefacts, chroma
    subsampling."""
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


_WORKER: FrameRenderer | None = None


def _init_worker(job: GenerateJob) -> None:
    global _WORKER
    _WORKER = FrameRenderer(job)


def _write_in_worker(index: int) -> int:
    return _WORKER.write(index)


def make_job(robot: str, out: str | Path, seed: int, width: int = 640, height: int = 480,
             config: str | Path = "randomized", second_robot: str | None = None) -> GenerateJob:
    """The job of one folder: its camera (K drawn from the seed) and configuration; with `second_robot`, the
    configuration's `second_robot:` section (else config/generate/scene/second_robot.yaml's) places it."""
    from holo_pose_ros.data.scene import sample_intrinsics

    cfg = load_generator_config(config)
    if second_robot:
        if Path(str(second_robot)).stem == Path(str(robot)).stem:
            raise ValueError(f"second_robot must be another robot type than {robot!r} (a DREAM reader tells the "
                             "robots of a frame apart by their class)")
        if "second_robot" not in cfg:
            cfg = {**cfg, **load_generator_config(config_dir() / "generate" / SECOND_ROBOT_FILE)}
    K = sample_intrinsics(cfg["intrinsics"], np.random.default_rng([seed, 0]), width, height)
    return GenerateJob(robot, str(out), int(seed), int(width), int(height), tuple(map(tuple, K.tolist())), cfg,
                       second_robot=second_robot or None)


# A worker process starts by importing the package and building its renderer: 8 frames took 9.8 s with two workers
# and 4.0 s in this process (7 December 2026, a training run sharing the cores), so a pool pays only for long folders.
FRAMES_PER_WORKER = 16


def generate(robot: str, n: int, out: str | Path, seed: int = 0, workers: int | None = None, width: int = 640,
             height: int = 480, config: str | Path = "randomized", progress: bool = True,
             second_robot: str | None = None) -> GenerateSummary:
    """Write `n` frames of `robot` into the DREAM folder `out`, with `workers` processes (default: all cores, at most
    one per FRAMES_PER_WORKER frames, so a short folder renders in this process); with `second_robot` (another robot
    type), that robot stands beside it in every frame. The frames are the same for any number of workers."""
    if n < 1:
        raise ValueError("n must be at least 1")
    job = make_job(robot, out, seed, width, height, config, second_robot)
    Path(out).mkdir(parents=True, exist_ok=True)
    settings = {"robot": robot, "n": n, "seed": seed, "width": width, "height": height, "config": str(config),
                "generator": job.config, "command": f"holo-pose generate --robot {robot} --n {n} --out {out} "
                                                      f"--seed {seed} --width {width} --height {height} --config {config}"}
    if job.second_robot:
        settings["second_robot"] = job.second_robot
        settings["command"] += f" --second-robot {job.second_robot}"
    (Path(out) / SETTINGS_FILE).write_text(json.dumps(settings, indent=2))
    workers = max(1, min(workers or os.cpu_count() or 1, n if workers else n // FRAMES_PER_WORKER))
    bar = tqdm(total=n, desc=f"generate {robot}", unit="frame", disable=not progress)
    start = time.perf_counter()
    if workers == 1:
        renderer = FrameRenderer(job)
        start = time.perf_counter()
        for i in range(n):
            renderer.write(i)
            bar.update()
    else:
        # One single-threaded llvmpipe per worker process: no oversubscription of the cores.
        os.environ.setdefault("LP_NUM_THREADS", "1")
        with mp.get_context("spawn").Pool(workers, initializer=_init_worker, initargs=(job,)) as pool:
            for _ in pool.imap_unordered(_write_in_worker, range(n), chunksize=4):
                bar.update()
    bar.close()
    return GenerateSummary(n, time.perf_counter() - start)
