#!/usr/bin/env python3
"""How well the 2D evidence can see each estimated joint: geometry only (no network, no rendering).

For every joint, over random views drawn as the generator draws them (joints within the limits, randomized cameras,
640x480):
- **px/deg**: how far one degree of the joint moves the fit keypoints it moves, in pixels (the 90th percentile over
  those points, median over views): the evidence a 2D error of a few pixels has to beat;
- **half-turn mm**: how different the links the joint moves *look* after half a turn of it: the symmetric chamfer
  distance (mm, median over views) between their surface before and after, sampled from the visual meshes. Near 0,
  the distal links are symmetric about the joint's axis (the Panda's hand and fingers): no keypoint detector can tell
  the joint from itself plus half a turn except by what little breaks the symmetry, so its error is often about
  180 degrees however good the 2D;
- a verdict: `weak` under --weak-px-per-deg, `half-turn symmetric` under --symmetric-mm; and the period the robot
  YAML declares (`joint_symmetry_deg`: evaluation and the joint-state monitor compare such a joint modulo it).
With --data (a generated folder), also what a model's estimates make of it there: each joint's mean and median error,
the share of frames over 90 degrees off and the mean error modulo half a turn.

    python scripts/joint_observability.py --robot panda [--views 200] [--surface-points 3000]
    python scripts/joint_observability.py --robot panda --model panda --data data/panda_val_1012 [--frames 120]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from scipy.spatial import cKDTree
from tqdm import tqdm

from holo_pose_ros.data.generator import load_generator_config
from holo_pose_ros.data.meshes import load_link_meshes
from holo_pose_ros.fitting import Fitter
from holo_pose_ros.fitting.parts import chains_of
from holo_pose_ros.fitting.residuals import project
from holo_pose_ros.fitting.surface import sample_surface_points
from holo_pose_ros.fitting.synthetic import sample_problem
from holo_pose_ros.robots.kinematics import RobotModel


def pixel_speed(fitter: Fitter, problem, joint: int, moved: np.ndarray, step_rad: float) -> float:
    """90th percentile over the fit keypoints that `joint` moves of their pixel motion per degree, in one view."""
    q = problem.q.copy()
    q2 = q.copy()
    q2[joint] += step_rad
    T = problem.T_cam_base
    uv = [project(fitter.tree.points(x[None])[0, moved] @ T[:3, :3].T + T[:3, 3], problem.K, 1e-3) for x in (q, q2)]
    return float(np.percentile(np.linalg.norm(uv[1] - uv[0], axis=1), 90) / np.degrees(step_rad))


def half_turn_chamfer_mm(surface, q: np.ndarray, joint: int, moved: np.ndarray) -> float:
    """Symmetric chamfer distance (mm) between the surface points that `joint` moves at q and after half a turn."""
    q2 = q.copy()
    q2[joint] += np.pi                                   # beyond the limits is fine: only the shape matters
    a, b = (surface.points(x[None])[0, moved] for x in (q, q2))
    d_ab, _ = cKDTree(b).query(a)
    d_ba, _ = cKDTree(a).query(b)
    return float(0.5 * (d_ab.mean() + d_ba.mean()) * 1e3)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robot", default="panda")
    parser.add_argument("--views", type=int, default=200)
    parser.add_argument("--surface-points", type=int, default=3000, help="mesh surface samples of the whole robot")
    parser.add_argument("--weak-px-per-deg", type=float, default=0.5)
    parser.add_argument("--symmetric-mm", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--model", default=None, help="with --data: the model whose estimates are scored (default: "
                                                      "the robot's shipped one)")
    parser.add_argument("--data", default=None, help="a generated DREAM folder of the robot")
    parser.add_argument("--frames", type=int, default=None)
    args = parser.parse_args(argv)

    model = RobotModel(args.robot, dtype=torch.float64)
    fitter = Fitter(model)
    samples = sample_surface_points(load_link_meshes(model), args.surface_points)
    surface = fitter.tree.with_link_points({name: p for name, (p, _) in samples.items()})
    moves_points, moves_surface = chains_of(fitter.tree).moves, chains_of(surface).moves
    generator = load_generator_config("randomized")
    rng = np.random.default_rng(args.seed)
    problems = [sample_problem(fitter.tree, fitter.lower, fitter.upper, generator, rng) for _ in range(args.views)]
    print(f"{args.robot}: {fitter.tree.n_points} fit keypoints, {surface.n_points} surface points, {args.views} views")
    print("| joint | fit keypoints it moves | px/deg (p90 of those, median view) | half-turn mm (median view) | verdict "
          "| robot YAML's joint_symmetry_deg |")
    print("|---|---:|---:|---:|---|---:|")
    for j, name in enumerate(model.joint_names):
        if model.joint_types[j] == "prismatic":
            continue
        moved = np.flatnonzero(moves_points[:, j])
        speed = np.median([pixel_speed(fitter, p, j, moved, np.radians(1.0)) for p in problems])
        chamfer = np.median([half_turn_chamfer_mm(surface, p.q, j, moves_surface[:, j]) for p in problems[:20]])
        verdict = ", ".join(v for v, bad in (("weak", speed < args.weak_px_per_deg),
                                              ("half-turn symmetric", chamfer < args.symmetric_mm)) if bad) or "ok"
        declared = model.spec.joint_symmetry.get(name)
        print(f"| {name} | {len(moved)} | {speed:.2f} | {chamfer:.1f} | {verdict} | "
              f"{f'{np.degrees(declared):g}' if declared else '-'} |")
    if args.data:
        measured_errors(args.model or args.robot, args.data, args.frames)
    return 0


def measured_errors(model: str, data: str, frames: int | None) -> None:
    """Print each revolute joint's error of the model's estimates on a folder: mean, median, share over 90 deg and
    mean modulo half a turn (degrees); frames where the robot was not found are left out."""
    from holo_pose_ros.data.dream import DreamReader
    from holo_pose_ros.estimator import Estimator
    from holo_pose_ros.monitoring.joints import wrap_to_period

    estimator = Estimator.from_model(model, backend="onnxruntime", min_confidence=0.0)
    reader = DreamReader(data, estimator.robot)
    errors = []
    for frame in tqdm(list(reader)[:frames], desc="estimate", unit="frame"):
        estimate = estimator.estimate(reader.load_image(frame), frame.K)
        if estimate.found:
            errors.append(np.degrees(estimate.joints - frame.joints))
    errors = np.array(errors)
    print(f"\n{model} on {data}: {len(errors)} frames found")
    print("| joint | mean deg | median deg | over 90 deg | mean modulo half a turn |\n|---|---:|---:|---:|---:|")
    for j, name in enumerate(estimator.robot.joint_names):
        if estimator.robot.joint_types[j] == "prismatic":
            continue
        e = np.abs(errors[:, j])
        half = np.degrees(np.abs(wrap_to_period(np.radians(errors[:, j]), np.pi)))
        print(f"| {name} | {e.mean():.1f} | {np.median(e):.1f} | {np.mean(e > 90) * 100:.0f} % | {half.mean():.1f} |")


if __name__ == "__main__":
    raise SystemExit(main())
