"""What a person wants to see of a DREAM folder: its statistics and a grid of frames with the ground-truth
skeleton (and the robot mask, when the folder has masks)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.visualization import draw_skeleton, image_grid, label_colours


@dataclass
class DatasetStats:
    """Summary numbers of a DREAM folder (metres, pixels)."""

    folder: str
    n_frames: int
    n_problems: int
    units: str
    width: int
    height: int
    K: np.ndarray
    keypoints_in_image_mean: float
    truncated_fraction: float
    base_distance_m: tuple[float, float, float]
    n_keypoints: int

    def report(self) -> str:
        lo, med, hi = self.base_distance_m
        return "\n".join([
            f"folder            {self.folder}",
            f"frames            {self.n_frames} good, {self.n_problems} skipped as malformed",
            f"units in files    {self.units}",
            f"image             {self.width} x {self.height} px, fx {self.K[0, 0]:.1f} fy {self.K[1, 1]:.1f} "
            f"cx {self.K[0, 2]:.1f} cy {self.K[1, 2]:.1f}",
            f"keypoints         {self.keypoints_in_image_mean:.2f} of {self.n_keypoints} in the image on average",
            f"truncated frames  {100 * self.truncated_fraction:.1f} % (some keypoint outside the image)",
            f"camera distance   {lo:.2f} / {med:.2f} / {hi:.2f} m (min / median / max, to the robot base)",
        ])


def dataset_preview(folder: str | Path, robot: str, out: str | Path, n: int = 12, units: str = "auto") -> DatasetStats:
    """Compute the folder's statistics and save a PNG grid of `n` evenly spaced frames to `out`."""
    reader = DreamReader(folder, robot, units=units)
    frames = list(reader)
    if not frames:
        raise ValueError(f"{folder}: no readable frame")
    visible = np.array([f.in_image.sum() for f in frames])
    distances = np.array([np.linalg.norm(f.T_cam_base[:3, 3] if f.T_cam_base is not None else f.keypoints_3d.mean(0))
                          for f in frames])
    parents = reader.robot.keypoint_parents
    tiles = []
    for idx in np.linspace(0, len(frames) - 1, min(n, len(frames))).round().astype(int):
        frame = frames[idx]
        image = draw_skeleton(reader.load_image(frame), frame.keypoints_2d, parents, visible=frame.in_image)
        mask = reader.load_mask(frame)
        if mask is not None:
            image = np.concatenate([image, label_colours(mask)], axis=1)
        cv2.putText(image, frame.name, (8, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.9, (255, 255, 255), 2, cv2.LINE_AA)
        tiles.append(image)
    columns = 2 if tiles[0].shape[1] > tiles[0].shape[0] * 1.6 else 4
    grid = image_grid(tiles, columns=columns, cell_width=640 if columns == 2 else 320)
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))
    first = frames[0]
    return DatasetStats(
        folder=str(folder), n_frames=len(frames), n_problems=len(reader.problems), units=reader.units,
        width=first.width, height=first.height, K=first.K, keypoints_in_image_mean=float(visible.mean()),
        truncated_fraction=float((visible < len(first.keypoint_names)).mean()),
        base_distance_m=(float(distances.min()), float(np.median(distances)), float(distances.max())),
        n_keypoints=len(first.keypoint_names),
    )
