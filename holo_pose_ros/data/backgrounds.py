"""Procedural backgrounds for synthetic frames: blended layers of gradients, smooth colour noise, stripes,
checkers and random shapes, so the network never learns a background prior. numpy + OpenCV, a few ms a frame."""

from __future__ import annotations

import cv2
import numpy as np


def _random_colour(rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(0, 255, 3).astype(np.float32)


def _gradient(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A linear two-colour gradient in a random direction."""
    angle = rng.uniform(0, 2 * np.pi)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    t = (x * np.cos(angle) + y * np.sin(angle))
    t = (t - t.min()) / max(float(np.ptp(t)), 1.0)
    return (1 - t)[..., None] * _random_colour(rng) + t[..., None] * _random_colour(rng)


def _colour_noise(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Smooth colour noise: a small random grid upsampled with bicubic interpolation."""
    cells = int(rng.integers(2, 24))
    small = rng.uniform(0, 255, (cells, max(2, cells * w // h), 3)).astype(np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def _stripes_or_checker(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Rotated stripes or a checkerboard of two random colours."""
    period = rng.uniform(8, 120)
    angle = rng.uniform(0, np.pi)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    u = x * np.cos(angle) + y * np.sin(angle)
    v = -x * np.sin(angle) + y * np.cos(angle)
    mask = (np.floor(u / period) % 2).astype(bool)
    if rng.random() < 0.5:
        mask ^= (np.floor(v / period) % 2).astype(bool)
    return np.where(mask[..., None], _random_colour(rng), _random_colour(rng))


def _shapes(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Random filled circles, rectangles and polygons on a random base colour."""
    img = np.empty((h, w, 3), np.float32)
    img[:] = _random_colour(rng)
    for _ in range(int(rng.integers(3, 25))):
        colour = tuple(float(c) for c in _random_colour(rng))
        kind = rng.integers(3)
        if kind == 0:
            centre = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            cv2.circle(img, centre, int(rng.integers(5, max(h, w) // 3)), colour, -1)
        elif kind == 1:
            p = rng.integers(0, [w, h, w, h])
            cv2.rectangle(img, (int(p[0]), int(p[1])), (int(p[2]), int(p[3])), colour, -1)
        else:
            pts = rng.integers(0, [w, h], size=(int(rng.integers(3, 7)), 2)).astype(np.int32)
            cv2.fillPoly(img, [pts], colour)
    return img


LAYERS = {"gradient": _gradient, "noise": _colour_noise, "stripes": _stripes_or_checker, "shapes": _shapes}


def random_background(rng: np.random.Generator, height: int, width: int, layers: tuple[int, int] = (1, 3),
                      kinds: tuple[str, ...] = tuple(LAYERS)) -> np.ndarray:
    """(H, W, 3) float32 background in [0, 255]: `layers` procedural layers of the given kinds, alpha-blended."""
    unknown = set(kinds) - set(LAYERS)
    if unknown or not kinds:
        raise ValueError(f"background kinds must be among {sorted(LAYERS)}, got {list(kinds)}")
    pick = lambda: LAYERS[kinds[rng.integers(len(kinds))]](rng, height, width)  # noqa: E731
    img = pick()
    for _ in range(int(rng.integers(layers[0], layers[1] + 1)) - 1):
        alpha = rng.uniform(0.2, 0.7)
        img = (1 - alpha) * img + alpha * pick()
    return img
