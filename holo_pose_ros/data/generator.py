"""Synthetic data generator: renders randomized frames of a robot and writes them as a DREAM folder with a
label mask per frame (`NNNNNN.mask.png`: 0 background, 1 + link index for robot pixels, 255 distractors).
Frame i depends only on (seed, i), so the output is identical for any number of workers."""

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
        self.writer = DreamWriter(job.out, self.model, self.K, job.width, job.height)
        self.colours = {link: mesh.color for link, mesh in self.meshes.items()}

    def frame(self, index: int) -> tuple[np.ndarray, np.ndarray, FrameScene]:
        """Render frame `index`: (RGB uint8 image, label mask uint8, the scene drawn)."""
        import torch

        from holo_pose_ros.data.backgrounds import random_background
        from holo_pose_ros.data.scene import sample_scene

        job, cfg = self.job, self.job.config
        rng = np.random.default_rng([job.seed, index + 1])
        scene = sample_scene(self.model, cfg, rng, self.K, job.width, job.height, self.colours)
        links = self.model.link_transforms(torch.from_numpy(scene.joints[None]), list(self.meshes))
        poses = {link: scene.T_cam_base @ T[0].numpy() for link, T in links.items()}
        result = self.renderer.render(poses, self.meshes, self.K, scene.materials, scene.light, scene.distractors)
        background = random_background(rng, job.height, job.width, tuple(cfg["background"]["layers"]),
                                       tuple(cfg["background"]["kinds"]))
        alpha = result.rgba[..., 3:4].astype(np.float32) / 255.0
        image = result.rgba[..., :3].astype(np.float32) * alpha + background * (1.0 - alpha)
        return _post_process(image, cfg["post"], rng), result.labels, scene

    def write(self, index: int) -> int:
        image, labels, scene = self.frame(index)
        self.writer.write(index, image, scene.joints, scene.T_cam_base, mask=labels)
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
             config: str | Path = "randomized") -> GenerateJob:
    """The job of one folder: its camera (K drawn from the seed) and configuration."""
    from holo_pose_ros.data.scene import sample_intrinsics

    cfg = load_generator_config(config)
    K = sample_intrinsics(cfg["intrinsics"], np.random.default_rng([seed, 0]), width, height)
    return GenerateJob(robot, str(out), int(seed), int(width), int(height), tuple(map(tuple, K.tolist())), cfg)


def generate(robot: str, n: int, out: str | Path, seed: int = 0, workers: int | None = None, width: int = 640,
             height: int = 480, config: str | Path = "randomized", progress: bool = True) -> GenerateSummary:
    """Write `n` frames of `robot` into the DREAM folder `out`, with `workers` processes (default: all cores)."""
    if n < 1:
        raise ValueError("n must be at least 1")
    job = make_job(robot, out, seed, width, height, config)
    Path(out).mkdir(parents=True, exist_ok=True)
    settings = {"robot": robot, "n": n, "seed": seed, "width": width, "height": height, "config": str(config),
                "generator": job.config, "command": f"holo-pose generate --robot {robot} --n {n} --out {out} "
                                                      f"--seed {seed} --width {width} --height {height} --config {config}"}
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
