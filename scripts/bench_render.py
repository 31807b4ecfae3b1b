#!/usr/bin/env python3
"""Time Renderer.render (draw + readback) for the shipped robots at a random joint configuration per frame,
viewed from about 1.5-2.5 m, with and without four distractor primitives. Prints a table of ms/frame.

llvmpipe's thread count is read when the GL context is created; compare e.g.
    python scripts/bench_render.py
    LP_NUM_THREADS=1 python scripts/bench_render.py
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from holo_pose_ros.data.meshes import load_link_meshes
from holo_pose_ros.data.render import Light, Material, Primitive, Renderer
from holo_pose_ros.geometry.camera import look_at
from holo_pose_ros.robots.kinematics import RobotModel

CAMERAS = {  # robot -> (eye, target) in the robot base frame, metres
    "panda": ((1.3, 0.6, 0.8), (0.0, 0.0, 0.45)),
    "kuka": ((1.6, 0.7, 0.9), (0.0, 0.0, 0.6)),
    "baxter": ((2.5, 0.8, 1.0), (0.0, 0.0, 0.3)),
}


def distractors(rng: np.random.Generator) -> list[Primitive]:
    """Four primitives scattered in front of the camera (camera frame, metres)."""
    prims = []
    for kind in ("box", "sphere", "cylinder", "box"):
        T = np.eye(4)
        T[:3, 3] = rng.uniform([-0.6, -0.4, 1.0], [0.6, 0.4, 2.0])
        prims.append(Primitive(kind, rng.uniform(0.05, 0.2, 3), T, Material(pattern="checker")))
    return prims


def time_robot(renderer: Renderer, robot: str, frames: int, with_distractors: bool) -> float:
    """Mean ms per render call over `frames` random configurations (after one warm-up render)."""
    model = RobotModel(robot)
    meshes = load_link_meshes(model)
    eye, target = CAMERAS[robot]
    T_cam_base = np.linalg.inv(look_at(np.array(eye), np.array(target)))
    K = np.array([[600.0, 0, renderer.width / 2], [0, 600.0, renderer.height / 2], [0, 0, 1]])
    q = model.sample_uniform(frames + 1, generator=torch.Generator().manual_seed(0))
    transforms = model.link_transforms(q, list(meshes))
    poses = [{k: T_cam_base @ v[i].double().numpy() for k, v in transforms.items()} for i in range(frames + 1)]
    rng = np.random.default_rng(0)
    prims = distractors(rng) if with_distractors else []
    renderer.render(poses[0], meshes, K, {}, Light(), prims)
    start = time.perf_counter()
    for pose in poses[1:]:
        renderer.render(pose, meshes, K, {}, Light(), prims)
    return (time.perf_counter() - start) / frames * 1000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--frames", type=int, default=50)
    parser.add_argument("--robots", nargs="+", default=list(CAMERAS))
    args = parser.parse_args()
    renderer = Renderer(args.width, args.height)
    threads = os.environ.get("LP_NUM_THREADS", "default")
    print(f"{args.width}x{args.height}, {args.frames} frames, LP_NUM_THREADS={threads}")
    print(f"{'robot':<8} {'faces':>7} {'ms/frame':>9} {'+4 distractors':>15}")
    for robot in args.robots:
        faces = sum(len(m.faces) for m in load_link_meshes(RobotModel(robot)).values())
        plain = time_robot(renderer, robot, args.frames, False)
        busy = time_robot(renderer, robot, args.frames, True)
        print(f"{robot:<8} {faces:>7} {plain:>9.1f} {busy:>15.1f}")


if __name__ == "__main__":
    main()
