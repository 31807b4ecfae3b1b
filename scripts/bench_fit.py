#!/usr/bin/env python3
"""Time Fitter.fit (batched LM, config/fitting.yaml defaults) on synthetic views: joints uniform within the limits,
randomized cameras (config/generate/randomized.yaml, 640x480), the exact projections of every fit keypoint and
the same with Gaussian pixel noise. Starts per frame: one 30 degrees off the truth (each joint, the base rotation;
10 % depth) and the rest 60 degrees off (20 % depth). Prints p50/p95 ms per fit and ADD statistics (DREAM's
keypoints, camera frame). Wall-clock and process CPU time per fit are both shown: on a shared CPU the CPU time is
the closer estimate of a quiet machine's wall time. Single-threaded numpy; compare e.g.
    OMP_NUM_THREADS=1 python scripts/bench_fit.py
    OMP_NUM_THREADS=1 python scripts/bench_fit.py --robot baxter --starts 8
    OMP_NUM_THREADS=1 python scripts/bench_fit.py --parts --starts 3     # the search by parts (fitting/parts.py)
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from holo_pose_ros.data.generator import load_generator_config
from holo_pose_ros.evaluation.metrics import add_auc, add_per_frame
from holo_pose_ros.fitting import Fitter
from holo_pose_ros.fitting.parts import PartsFitter
from holo_pose_ros.fitting.synthetic import keypoints_in_camera, perturbed_start, sample_problem
from holo_pose_ros.robots.kinematics import RobotModel


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robot", default="panda")
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--starts", type=int, default=4, help="starts per frame: one 30-degree, the rest 60-degree")
    parser.add_argument("--noise-px", type=float, default=3.0, help="sigma of the noisy run's pixel noise")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--parts", action="store_true", help="time the search by parts (PartsFitter) instead")
    args = parser.parse_args()

    torch.set_num_threads(1)
    model = RobotModel(args.robot, dtype=torch.float64)
    fitter = Fitter(model)
    search = PartsFitter(fitter) if args.parts else fitter
    generator = load_generator_config("randomized")
    prismatic = np.array([t == "prismatic" for t in model.joint_types])
    rng = np.random.default_rng(args.seed)
    frames = []
    for _ in range(args.frames):
        problem = sample_problem(fitter.tree, fitter.lower, fitter.upper, generator, rng)
        starts = [perturbed_start(problem, fitter.lower, fitter.upper, prismatic, rng, 30.0, 0.1)]
        starts += [perturbed_start(problem, fitter.lower, fitter.upper, prismatic, rng, 60.0, 0.2)
                   for _ in range(args.starts - 1)]
        noise = rng.normal(0.0, args.noise_px, problem.uv.shape)
        frames.append((problem, np.stack([s[0] for s in starts]), np.stack([s[1] for s in starts]), noise))

    n = model.n_keypoints
    print(f"{args.robot}: {fitter.tree.n_points} fit points, {model.n_joints} joints, {args.starts} starts, "
          f"{args.frames} frames, iterations <= {fitter.config['iterations']}{', by parts' if args.parts else ''}")
    print(f"{'pixels':<14}{'p50 ms':>8}{'p95 ms':>8}{'cpu p50':>9}{'cpu p95':>9}{'iters':>7}{'ADD med mm':>12}"
          f"{'mean mm':>9}{'<5 mm %':>9}{'AUC':>7}{'30deg won %':>13}")
    for label, sigma in (("exact", 0.0), (f"{args.noise_px:g} px noise", 1.0)):
        for problem, q0, T0, noise in frames[:5]:                           # warm-up
            search.fit(problem.uv, np.ones(len(problem.uv)), problem.K, q0, T0)
        times, cpu, adds, iterations, first = [], [], [], [], []
        for problem, q0, T0, noise in frames:
            uv = problem.uv + sigma * noise
            t0, c0 = time.perf_counter(), time.process_time()
            result = search.fit(uv, np.ones(len(uv)), problem.K, q0, T0)
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            pred = keypoints_in_camera(fitter.tree, result.q, result.T_cam_base, n)
            true = keypoints_in_camera(fitter.tree, problem.q, problem.T_cam_base, n)
            adds.append(add_per_frame(pred[None], true[None])[0])
            iterations.append(result.iterations)
            first.append(result.start_index == 0)
        ms, cpu_ms = np.array(times) * 1000.0, np.array(cpu) * 1000.0
        adds = np.array(adds)
        print(f"{label:<14}{np.percentile(ms, 50):8.2f}{np.percentile(ms, 95):8.2f}{np.percentile(cpu_ms, 50):9.2f}"
              f"{np.percentile(cpu_ms, 95):9.2f}{np.mean(iterations):7.1f}"
              f"{np.median(adds) * 1000:12.3f}{adds.mean() * 1000:9.2f}{np.mean(adds < 5e-3) * 100:9.1f}"
              f"{add_auc(adds):7.1f}{np.mean(first) * 100:13.1f}")


if __name__ == "__main__":
    main()
