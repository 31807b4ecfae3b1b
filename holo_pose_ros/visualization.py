"""Drawing for people: skeletons over images and image grids (OpenCV; RGB uint8 arrays, pixels)."""

from __future__ import annotations

import cv2
import numpy as np

_PALETTE = np.array([
    [230, 25, 75], [60, 180, 75], [255, 225, 25], [0, 130, 200], [245, 130, 48], [145, 30, 180], [70, 240, 240],
    [240, 50, 230], [210, 245, 60], [250, 190, 212], [0, 128, 128], [220, 190, 255], [170, 110, 40], [255, 250, 200],
    [128, 0, 0], [170, 255, 195], [128, 128, 0],
], dtype=np.uint8)


def label_colours(labels: np.ndarray) -> np.ndarray:
    """(H, W) label mask -> (H, W, 3) RGB: a colour per link, black background, grey distractors (255)."""
    out = _PALETTE[(labels.astype(np.int64) - 1) % len(_PALETTE)]
    out[labels == 0] = 0
    out[labels == 255] = 128
    return out


def draw_skeleton(image: np.ndarray, uv: np.ndarray, parents: list[int], colour=(0, 255, 0),
                  visible: np.ndarray | None = None, thickness: int = 2) -> np.ndarray:
    """A copy of `image` with keypoints (N, 2 pixels) joined along the kinematic tree; keypoints outside the
    image are drawn as far as OpenCV clips them, invisible ones (visible=False) hollow."""
    out = np.ascontiguousarray(image.copy())
    pts = [tuple(int(round(c)) for c in p) for p in np.nan_to_num(uv, nan=-1e4).clip(-1e4, 1e4)]
    for i, parent in enumerate(parents):
        if parent >= 0:
            cv2.line(out, pts[parent], pts[i], colour, thickness, cv2.LINE_AA)
    for i, p in enumerate(pts):
        fill = -1 if visible is None or visible[i] else 1
        cv2.circle(out, p, thickness + 2, tuple(int(c) for c in _PALETTE[i % len(_PALETTE)]), fill, cv2.LINE_AA)
    return out


def image_grid(images: list[np.ndarray], columns: int = 4, cell_width: int = 320) -> np.ndarray:
    """Tile RGB images (resized to `cell_width` wide, keeping aspect) into one RGB image."""
    if not images:
        raise ValueError("image_grid needs at least one image")
    cells = []
    for img in images:
        h = int(round(img.shape[0] * cell_width / img.shape[1]))
        cells.append(cv2.resize(img, (cell_width, h), interpolation=cv2.INTER_AREA))
    cell_h = max(c.shape[0] for c in cells)
    rows = -(-len(cells) // columns)
    grid = np.zeros((rows * cell_h, columns * cell_width, 3), np.uint8)
    for k, c in enumerate(cells):
        r, col = divmod(k, columns)
        grid[r * cell_h:r * cell_h + c.shape[0], col * cell_width:(col + 1) * cell_width] = c
    return grid
