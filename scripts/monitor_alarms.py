#!/usr/bin/env python3
"""What the joint-state monitor would say on a folder of generated frames, with the truth as the robot's report:
its false alarms (the estimate's own error crossing the thresholds) and, with a fault injected into one joint's
report at a time, how often it catches the fault. The thresholds as the node makes them (config/
joint_state_monitor.yaml's defaults, the model's card, the robot YAML's joint_symmetry_deg); the frames streamed in
file order at 10 Hz, each estimate matched with the report of its own stamp; frames where the robot is not found
publish nothing, as in the node. (It reads the node's defaults through the node's own parameter table, so rclpy must
be importable, as for the node.)

Per joint: the WARN threshold and where it came from; the share of frames whose discrepancy is over WARN (false);
the share of frames at which the joint's debounced level is WARN or above (false alarms); and with `--fault-deg`
(revolute; `--fault-mm` prismatic) added to that joint's report, the share of frames at which it is (caught). Both
shares count from the `persistence`-th frame, the first at which a level can rise.

    python scripts/monitor_alarms.py --model panda --data data/panda_test_randomized_seed3031 [--frames 300] \\
        [--fault-deg 45] [--fault-mm 20] [--card-test-set randomized] [--backend onnxruntime]
"""

from __future__ import annotations

import argparse
import math

import numpy as np
from tqdm import tqdm

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.model.cards import read_card
from holo_pose_ros.monitoring import WARN, JointStateMonitor, frame_level, node_thresholds
from holo_pose_ros.nodes.joint_state_monitor_node import NODE_NAME, PARAMETERS
from holo_pose_ros.nodes.parameters import load_defaults

PERIOD_NS = 100_000_000  # 10 Hz


def estimates(model: str, data: str, frames: int | None, backend: str) -> tuple[Estimator, np.ndarray, np.ndarray]:
    """(estimator, (F, J) estimated joints, (F, J) true joints) over the frames where the robot was found."""
    estimator = Estimator.from_model(model, backend=backend)
    reader = DreamReader(data, estimator.robot)
    est, true = [], []
    for frame in tqdm(list(reader)[:frames], desc="estimate", unit="frame"):
        estimate = estimator.estimate(reader.load_image(frame), frame.K)
        if estimate.found:
            est.append(estimate.joints)
            true.append(frame.joints)
    return estimator, np.array(est, float).reshape(-1, estimator.robot.n_joints), np.array(true, float).reshape(
        -1, estimator.robot.n_joints)


def stream(thresholds, est: np.ndarray, reported: np.ndarray, persistence: int) -> tuple[np.ndarray, np.ndarray]:
    """(F, J) each joint's debounced level after each frame and (F, J) its discrepancy (the monitor's, wrapped as it
    wraps it), the estimates and reports fed as the node feeds them."""
    names = [t.name for t in thresholds]
    monitor = JointStateMonitor(thresholds, persistence=persistence, now=0.0)
    levels, discrepancies = np.zeros(est.shape, int), np.full(est.shape, np.nan)
    for i, (e, r) in enumerate(zip(est, reported)):
        now = i * PERIOD_NS / 1e9
        monitor.add_reported(names, r, i * PERIOD_NS, now)
        for d in monitor.add_estimate(names, e, i * PERIOD_NS, now + 0.01).discrepancies:
            discrepancies[i] = d.values
        levels[i] = [w.level for w in monitor.watches]
    return levels, discrepancies


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default="panda", help="shipped model name or card path")
    parser.add_argument("--data", required=True, help="a generated DREAM folder of the model's robot")
    parser.add_argument("--frames", type=int, default=None, help="only the first N frames")
    parser.add_argument("--fault-deg", type=float, default=45.0, help="fault added to a revolute joint's report")
    parser.add_argument("--fault-mm", type=float, default=20.0, help="fault added to a prismatic joint's report")
    parser.add_argument("--backend", default="onnxruntime", choices=("torch", "onnxruntime"))
    parser.add_argument("--card-test-set", default=None, help="the node's card_test_set (default: its default, '': "
                                                              "per joint the largest error over the card's test sets)")
    args = parser.parse_args(argv)

    p = load_defaults("joint_state_monitor.yaml", NODE_NAME, PARAMETERS)
    if args.card_test_set is not None:
        p["card_test_set"] = args.card_test_set
    estimator, est, true = estimates(args.model, args.data, args.frames, args.backend)
    spec = estimator.robot.spec
    if len(est) <= p["persistence"]:
        parser.error(f"only {len(est)} frames with the robot found: the monitor needs more than persistence "
                     f"({p['persistence']})")
    thresholds = node_thresholds(spec, read_card(args.model)[1], p)
    persistence = int(p["persistence"])
    settled = slice(persistence - 1, None)  # the frames from the first at which a level can have risen
    healthy, d = stream(thresholds, est, true, persistence)
    healthy = healthy[settled]
    over = np.array([[frame_level(v, x.warn, x.error) >= WARN for v, x in zip(row, thresholds)] for row in d])

    print(f"{args.model} on {args.data}: {len(est)} frames with the robot found, the truth as the report; thresholds "
          f"as the node makes them (factor {p['threshold_factor']:g}, persistence {persistence}, card_test_set "
          f"'{p['card_test_set']}')")
    print(f"| joint | WARN threshold | from | over WARN (frames) | false alarms (frames) | fault of "
          f"{args.fault_deg:g} deg / {args.fault_mm:g} mm caught (frames) |")
    print("|---|---:|---|---:|---:|---:|")
    for j, t in enumerate(thresholds):
        linear = t.kind == "prismatic"
        fault = args.fault_mm / 1000.0 if linear else math.radians(args.fault_deg)
        faulty = true.copy()
        faulty[:, j] += fault
        caught = stream(thresholds, est, faulty, persistence)[0][settled, j] >= WARN
        warn = f"{t.warn * 1000:.1f} mm" if linear else f"{math.degrees(t.warn):.1f} deg"
        where = t.source + (f", modulo {math.degrees(t.period):g} deg" if t.symmetric else "")
        blind = "" if t.can_warn else " (can never warn)"
        print(f"| {t.name} | {warn}{blind} | {where} | {over[:, j].mean() * 100:.1f} % | "
              f"{(healthy[:, j] >= WARN).mean() * 100:.1f} % | {caught.mean() * 100:.1f} % |")
    print(f"| any joint | | | {over.any(axis=1).mean() * 100:.1f} % | "
          f"{(healthy >= WARN).any(axis=1).mean() * 100:.1f} % | |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
