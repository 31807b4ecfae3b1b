"""Network inputs cut from the user's images exactly as the deployed estimator cuts them: the whole letterboxed
frame (the localizer's pass) and crops around the robot (the crop pass), jittered in position and scale as
training's views are, so that statistics and losses see what deployment sees."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import torch

from holo_pose_ros.geometry.crop import crop_affine, crop_image, full_image_box

SCALE_JITTER = (0.9, 1.15)   # crop side factor range, of the deployed box
SHIFT_JITTER = 0.04          # crop centre jitter sigma, in box sides


def jittered_box(box: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A copy of a square crop box (x0, y0, side) px moved and scaled by the jitter above."""
    side = box[2] * rng.uniform(*SCALE_JITTER)
    centre = box[:2] + box[2] / 2 + rng.normal(0.0, SHIFT_JITTER * box[2], 2)
    return np.array([centre[0] - side / 2, centre[1] - side / 2, side])


def network_input(image: np.ndarray, K: np.ndarray, box: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(3, S, S) float32 crop in [0, 1] and its (3, 3) float32 intrinsics, as the estimator's pass computes them."""
    crop = crop_image(image, box, size).transpose(2, 0, 1).astype(np.float32) * np.float32(1 / 255)
    return crop, (crop_affine(box, size) @ K).astype(np.float32)


def deployed_inputs(frames, boxes: list[np.ndarray | None], size: int, crops_per_frame: int,
                    rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 3, S, S) inputs and (N, 3, 3) intrinsics: for each frame its letterboxed whole image and, where a box
    was detected (None: no robot found), `crops_per_frame` jittered crops around it."""
    images, Ks = [], []
    for frame, box in zip(frames, boxes):
        H, W = frame.image.shape[:2]
        chosen = [full_image_box(W, H)] + ([] if box is None else [jittered_box(box, rng) for _ in range(crops_per_frame)])
        for b in chosen:
            x, K = network_input(frame.image, frame.K, b, size)
            images.append(x)
            Ks.append(K)
    return torch.from_numpy(np.stack(images)), torch.from_numpy(np.stack(Ks))


def batches(images: torch.Tensor, Ks: torch.Tensor, batch_size: int,
            generator: torch.Generator | None = None) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """The inputs in shuffled batches (BatchNorm statistics must not see one frame's crops together)."""
    order = torch.randperm(len(images), generator=generator)
    for i in range(0, len(images), batch_size):
        chosen = order[i:i + batch_size]
        yield images[chosen], Ks[chosen]
