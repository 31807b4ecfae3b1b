"""Write a robot's extra fit keypoints into its YAML: farthest-point samples of each link's visual mesh surface
(link frame, metres), so that every estimated joint moves several points off its axis and the fit can see it.

    python scripts/make_fit_keypoints.py --robot panda --points 120

Points are shared out between links by surface area (at least `--min-per-link` each); the YAML's existing
`fit_keypoints:` block (always the file's last block) is replaced, everything above it is kept as written.
Deterministic: the same meshes give the same points.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from holo_pose_ros.data.meshes import load_link_meshes
from holo_pose_ros.robots.kinematics import RobotModel

MARKER = "# Extra fit keypoints"


def surface_samples(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points drawn uniformly on a triangle mesh's surface."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(faces), n, p=area / area.sum())
    a, b = rng.random((2, n, 1))
    flip = (a + b) > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    t = tri[pick]
    return t[:, 0] + a * (t[:, 1] - t[:, 0]) + b * (t[:, 2] - t[:, 0])


def farthest_points(points: np.ndarray, k: int) -> np.ndarray:
    """(k, 3) farthest-point subset of `points`, starting from the point farthest from their centroid."""
    chosen = [int(np.argmax(np.linalg.norm(points - points.mean(0), axis=1)))]
    dist = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(k - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return points[chosen]


def mesh_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    tri = vertices[faces]
    return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robot", required=True)
    parser.add_argument("--points", type=int, default=120, help="extra points in all")
    parser.add_argument("--min-per-link", type=int, default=3)
    args = parser.parse_args()
    model = RobotModel(args.robot, dtype=torch.float64)
    meshes = load_link_meshes(model)
    areas = {name: mesh_area(m.vertices, m.faces) for name, m in meshes.items()}
    total = sum(areas.values())
    spare = args.points - args.min_per_link * len(meshes)
    if spare < 0:
        raise SystemExit(f"--points {args.points} is fewer than {args.min_per_link} per link for {len(meshes)} links")
    counts = {name: args.min_per_link + int(round(spare * a / total)) for name, a in areas.items()}
    rng = np.random.default_rng(0)
    lines = [f"{MARKER} (scripts/make_fit_keypoints.py --robot {args.robot} --points {args.points}): farthest-point",
             "# samples of each link's visual mesh surface, link frame, metres. The heatmap network and the fit use",
             "# DREAM's keypoints above plus these; evaluation uses DREAM's only.", "fit_keypoints:"]
    for name, m in meshes.items():
        dense = surface_samples(m.vertices.astype(np.float64), m.faces, 4000, rng)
        for i, p in enumerate(farthest_points(dense, counts[name])):
            lines.append(f"  - {{name: {name}_fit{i}, link: {name}, xyz: [{p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}]}}")
    path = model.spec.source_file
    with open(path) as f:
        text = f.read()
    if MARKER in text:
        text = text[:text.index(MARKER)]
    with open(path, "w") as f:
        f.write(text.rstrip("\n") + "\n" + "\n".join(lines) + "\n")
    print(f"{path}: {sum(counts.values())} fit keypoints on {len(meshes)} links "
          f"({', '.join(f'{k} {v}' for k, v in counts.items())})")


if __name__ == "__main__":
    main()
