"""Synthetic data generator: renders randomized frames of a robot and writes them as a DREAM folder with a
label mask per frame (`NNNNNN.mask.png`: 0 background, 1 + link index for robot pixels, 255 distractors).
Frame i depends only on (seed, i), so the output is identical for any number of workers.

With `second_robot` (another robot type) each frame also shows that robot beside the first, both in its ground
truth (one DREAM object each, so that each robot's DreamReader reads its own) and in the mask (its links numbered
after the first robot's); placement from config/generate/scene/second_robot.yaml."""

from __future__ import annotations

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
        return yaml.safe_load(f)


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
        if self.second is None:
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
                                      scene.distractors)
        background = random_background(rng, job.height, job.width, tuple(cfg["background"]["layers"]),
                                       tuple(cfg["background"]["kinds"]))
        alpha = result.rgba[..., 3:4].astype(np.float32) / 255.0
        image = result.rgba[..., :3].astype(np.float32) * alpha + background * (1.0 - alpha)
        return _post_process(image, cfg["post"], rng), result.labels, scene

    def write(self, index: int) -> int:
        image, labels, scene = self.frame(index)
        self.writer.write(index, image, scene.joints, scene.T_cam_base, mask=labels,
                          others=[(o.joints, o.T_cam_base) for o in scene.others])
        return index


def _post_process(image: np.ndarray, cfg: dict, rng: np.random.Generator) -> np.ndarray:
    """Camera-like degradations: per-channel gain, optional Gaussian blur, sensor noise; -> uint8 RGB."""
    image = image * rng.uniform(cfg["colour_gain"][0], cfg["colour_gain"][1], 3).astype(np.float32)
    if rng.random() < cfg["blur_probability"]:
        image = cv2.GaussianBlur(image, (0, 0), rng.uniform(*cfg["blur_sigma_px"]))
    sigma = rng.uniform(*cfg["noise_sigma"])
    if sigma > 0:
        image = image + rng.normal(0.0, sigma, image.shape).astype(np.float32)
    return np.clip(image, 0, 255).astype(np.uint8)


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


def generate(robot: str, n: int, out: str | Path, seed: int = 0, workers: int | None = None, width: int = 640,
             height: int = 480, config: str | Path = "randomized", progress: bool = True,
             second_robot: str | None = None) -> GenerateSummary:
    """Write `n` frames of `robot` into the DREAM folder `out`, with `workers` processes (default: all cores);
    with `second_robot` (another robot type), that robot stands beside it in every frame."""
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
    workers = max(1, min(workers or os.cpu_count() or 1, n))
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
