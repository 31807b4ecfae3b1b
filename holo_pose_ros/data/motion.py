"""Smooth joint motion for generated videos (the generator's `video:` section): a clip's joints move from waypoint
to waypoint, each leg eased in and out (zero velocity at the waypoints, as a point-to-point robot program moves),
within the URDF limits. Radians (metres for prismatic joints), frames."""

from __future__ import annotations

import numpy as np


def waypoint_path(lower: np.ndarray, upper: np.ndarray, start: np.ndarray, n_frames: int, rng: np.random.Generator,
                  leg_frames: tuple[int, int], reach: float) -> np.ndarray:
    """(n_frames, J) joints: from `start`, legs of a uniform integer number of frames in `leg_frames` [low, high]
    to waypoints drawn uniformly within +- `reach` of each joint's range around `start` (clipped to the limits),
    eased with 0.5 - 0.5 cos(pi s) over each leg."""
    lower, upper, start = (np.asarray(a, dtype=np.float64) for a in (lower, upper, start))
    if n_frames < 1:
        raise ValueError(f"a clip has at least one frame, got {n_frames}")
    if not 1 <= leg_frames[0] <= leg_frames[1]:
        raise ValueError(f"leg_frames must be [low, high] with 1 <= low <= high, got {list(leg_frames)}")
    if not 0.0 <= reach <= 1.0:
        raise ValueError(f"reach is a fraction of each joint's range in [0, 1], got {reach}")
    span = reach * (upper - lower)
    low, high = np.maximum(lower, start - span), np.minimum(upper, start + span)
    path, here = [start[None]], start
    while sum(len(p) for p in path) < n_frames:
        there = rng.uniform(low, high)
        steps = int(rng.integers(leg_frames[0], leg_frames[1] + 1))
        s = np.arange(1, steps + 1) / steps
        ease = 0.5 - 0.5 * np.cos(np.pi * s)
        path.append(here + ease[:, None] * (there - here))
        here = there
    return np.concatenate(path)[:n_frames]
