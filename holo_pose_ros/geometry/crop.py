"""Square crops of an image and their intrinsics. A box (x0, y0, side) is in edge coordinates (the image spans
[0, W] x [0, H]); its crop is resized to S x S network pixels. Points use pixel-centre coordinates ((0, 0) is the
centre of the top-left pixel) in both images, and K' = A K with A the affine map image -> crop. Pixels."""

from __future__ import annotations

import cv2
import numpy as np

from holo_pose_ros.geometry.camera import in_image

CROP_MARGIN = 0.3  # the crop recipe of training and inference: keypoint extent grown by this on each side
MIN_CLOSE_UP_POINTS = 3  # a close-up part with fewer fit keypoints in the image is not cropped on its own


def crop_affine(box: np.ndarray, size: int) -> np.ndarray:
    """3x3 map from image pixels to crop pixels for box (x0, y0, side): u' = (u - x0 + 0.5) * S / side - 0.5."""
    x0, y0, side = (float(v) for v in box)
    s = size / side
    return np.array([[s, 0.0, (0.5 - x0) * s - 0.5], [0.0, s, (0.5 - y0) * s - 0.5], [0.0, 0.0, 1.0]])


def crop_intrinsics(K: np.ndarray, box: np.ndarray, size: int) -> np.ndarray:
    """K' of the crop: the camera whose image is the S x S crop of box."""
    return crop_affine(box, size) @ K


def crop_image(image: np.ndarray, box: np.ndarray, size: int, border_value: int = 0) -> np.ndarray:
    """The S x S crop of `image` for box (x0, y0, side); outside the image is filled with `border_value`."""
    A = crop_affine(box, size)[:2]
    interp = cv2.INTER_AREA if box[2] > size else cv2.INTER_LINEAR
    if interp == cv2.INTER_AREA:  # warpAffine has no area filter: pre-shrink, then warp the rest of the way
        factor = int(box[2] // size)
        if factor >= 2:
            h, w = image.shape[0] // factor, image.shape[1] // factor
            small = cv2.resize(image[:h * factor, :w * factor], (w, h), interpolation=cv2.INTER_AREA)
            scale = np.array([[factor, 0, 0.5 * (factor - 1)], [0, factor, 0.5 * (factor - 1)], [0, 0, 1.0]])
            A = (crop_affine(box, size) @ scale)[:2]
            image = small
        interp = cv2.INTER_LINEAR
    return cv2.warpAffine(image, A, (size, size), flags=interp, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=(border_value,) * 3)


def full_image_box(width: int, height: int) -> np.ndarray:
    """The square box that letterboxes the whole image (centred, side = the longer image side)."""
    side = float(max(width, height))
    return np.array([(width - side) / 2.0, (height - side) / 2.0, side])


def box_from_points(uv: np.ndarray, margin: float = 0.3, min_side: float = 32.0) -> np.ndarray:
    """Square box around 2D points (N, 2 pixels): their extent grown by `margin` of its size on each side
    (the paper's crop recipe), made square about its centre."""
    lo, hi = uv.min(0) + 0.5, uv.max(0) + 0.5  # pixel centres -> edge coordinates
    centre = (lo + hi) / 2.0
    side = max(float((hi - lo).max()) * (1.0 + 2.0 * margin), min_side)
    return np.array([centre[0] - side / 2.0, centre[1] - side / 2.0, side])


def crop_box_from_keypoints(uv: np.ndarray, width: int, height: int, margin: float = CROP_MARGIN) -> np.ndarray:
    """The estimator's crop box: in-image keypoints (N, 2 pixels; clipped to the frame when fewer than two are
    inside) grown by `margin`. Training draws its crop views around the same box."""
    inside = in_image(uv, width, height)
    pts = uv[inside] if inside.sum() >= 2 else np.clip(uv, [0, 0], [width, height])
    return box_from_points(pts, margin)


def grid_to_frame_mask(logits: np.ndarray, box: np.ndarray, size: int, width: int, height: int) -> np.ndarray:
    """(height, width) bool frame mask of a crop's (G, G) foreground logits: cell j is centred on crop pixel
    (j + 0.5) size / G - 0.5, the crop on `box` (x0, y0, side) of the frame; logits are interpolated bilinearly
    and thresholded at 0 (probability 0.5). Frame pixels outside the crop are background."""
    G = logits.shape[-1]
    cell = size / G
    grid_to_crop = np.array([[cell, 0.0, 0.5 * cell - 0.5], [0.0, cell, 0.5 * cell - 0.5], [0.0, 0.0, 1.0]])
    frame_to_grid = np.linalg.inv(np.linalg.inv(crop_affine(box, size)) @ grid_to_crop)[:2]
    warped = cv2.warpAffine(np.ascontiguousarray(logits, np.float32), frame_to_grid, (width, height),
                            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT,
                            borderValue=-1.0)
    x0, y0, side = (float(v) for v in box)
    cols, rows = np.arange(width), np.arange(height)
    in_box = ((rows[:, None] >= y0 - 0.5) & (rows[:, None] <= y0 + side - 0.5)
              & (cols[None] >= x0 - 0.5) & (cols[None] <= x0 + side - 0.5))
    return (warped > 0.0) & in_box
