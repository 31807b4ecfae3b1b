"""A robot's surface as a fixed, small set of points with normals per link (link frames, metres) for the silhouette
term: a farthest-point subset of each link mesh's vertices, which keeps the extremes and spreads the rest evenly.
Vertices, not points inside triangles: a vertex on the projected outline lies exactly on it, where a point inside an
edge-on triangle lies up to the triangle's width times its slant inside (a bias outward of the contour term). Pure
arrays in, so the fit needs no mesh loader or renderer."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol

import numpy as np


class TriangleMesh(Protocol):
    """Anything with vertices (V, 3) metres, unit vertex normals (V, 3) and faces (F, 3) vertex indices (e.g.
    data/meshes.py's LinkMesh)."""

    vertices: np.ndarray
    normals: np.ndarray
    faces: np.ndarray


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) areas of a mesh's triangles, m^2."""
    tri = np.asarray(vertices, float)[np.asarray(faces)]
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def farthest_points(points: np.ndarray, k: int) -> np.ndarray:
    """(k,) indices of a farthest-point subset of points (N, 3), starting from the point farthest from their
    centroid."""
    chosen = [int(np.argmax(np.linalg.norm(points - points.mean(0), axis=1)))]
    dist = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(min(k, len(points)) - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return np.array(chosen)


def sample_surface_points(meshes: Mapping[str, TriangleMesh], n_points: int, min_per_link: int = 2
                          ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Link name -> (points (N_l, 3), unit normals (N_l, 3)) in the link frame, metres: about n_points vertices in
    all, shared out by surface area with at least min_per_link per link (links without area get none);
    deterministic."""
    areas = {name: float(triangle_areas(m.vertices, m.faces).sum()) for name, m in meshes.items()}
    areas = {name: a for name, a in areas.items() if a > 0.0}
    total = sum(areas.values())
    spare = max(n_points - min_per_link * len(areas), 0)
    surface = {}
    for name, area in areas.items():
        vertices, normals = np.asarray(meshes[name].vertices, float), np.asarray(meshes[name].normals, float)
        keep = farthest_points(vertices, min_per_link + int(round(spare * area / total)))
        surface[name] = (vertices[keep], normals[keep] / np.linalg.norm(normals[keep], axis=1, keepdims=True))
    return surface
