"""Evaluation figures written straight to PNG files through matplotlib's Agg canvas (no pyplot, never a GUI)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from holo_pose_ros.evaluation.metrics import add_accuracy_curve, add_auc
from holo_pose_ros.visualization import draw_skeleton

GT_COLOUR = (0, 255, 0)  # RGB green
PRED_COLOUR = (255, 0, 0)  # RGB red


def _save(fig: Figure, path: str | Path) -> None:
    """Render `fig` with the Agg canvas to a PNG at `path`, creating the parent folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig).print_png(str(path))


def plot_add_curve(add_m: np.ndarray, found: np.ndarray | None, path: str | Path, label: str | None = None) -> None:
    """PNG of the fraction of frames with ADD <= threshold (0-100 mm), the AUC (percent) in the legend."""
    thresholds, acc = add_accuracy_curve(add_m, found)
    auc = add_auc(add_m, found)
    fig = Figure(figsize=(5, 4), dpi=100)
    ax = fig.add_subplot()
    ax.plot(thresholds * 1000.0, acc, label=f"{label or 'estimate'} (AUC {auc:.2f})")
    ax.set(xlim=(0, 100), ylim=(0, 1), xlabel="ADD threshold (mm)", ylabel="accuracy")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    _save(fig, path)


def plot_frames_grid(images: list[np.ndarray], pred_uv: list[np.ndarray | None], gt_uv: list[np.ndarray],
                     parents: list[int], path: str | Path, titles: list[str] | None = None,
                     columns: int = 4) -> None:
    """PNG grid of RGB frames with the true skeleton (pixels) in green and the estimated one in red."""
    if not images:
        raise ValueError("plot_frames_grid needs at least one image")
    columns = min(columns, len(images))
    rows = -(-len(images) // columns)
    fig = Figure(figsize=(4 * columns, 3.2 * rows), dpi=100)
    for k, (image, pred, gt) in enumerate(zip(images, pred_uv, gt_uv)):
        drawn = draw_skeleton(image, np.asarray(gt, float), parents, GT_COLOUR)
        if pred is not None:
            drawn = draw_skeleton(drawn, np.asarray(pred, float), parents, PRED_COLOUR)
        title = titles[k] if titles else f"frame {k}"
        ax = fig.add_subplot(rows, columns, k + 1)
        ax.imshow(drawn)
        ax.set_title(title if pred is not None else f"{title} (not found)", fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    _save(fig, path)


def plot_before_after(images: list[np.ndarray], before: list[np.ndarray | None], after: list[np.ndarray | None],
                      parents: list[int], path: str | Path, titles: list[str] | None = None) -> None:
    """PNG grid, one row per frame: the estimated skeleton (pixels) of the model before (left) and after (right)
    adaptation, in red; 'not found' where an estimate is None."""
    if not images:
        raise ValueError("plot_before_after needs at least one image")
    fig = Figure(figsize=(8, 3.2 * len(images)), dpi=100)
    for k, image in enumerate(images):
        for column, (uv, when) in enumerate(((before[k], "before"), (after[k], "after"))):
            ax = fig.add_subplot(len(images), 2, 2 * k + column + 1)
            ax.imshow(image if uv is None else draw_skeleton(image, np.asarray(uv, float), parents, PRED_COLOUR))
            name = titles[k] if titles else f"frame {k}"
            ax.set_title(f"{name}: {when}" + (" (not found)" if uv is None else ""), fontsize=9)
            ax.axis("off")
    fig.tight_layout()
    _save(fig, path)


def plot_loss_curves(curves: dict[str, np.ndarray], path: str | Path, xlabel: str = "step") -> None:
    """PNG of loss curves (name -> values a step), each smoothed over a window of a tenth of its length."""
    fig = Figure(figsize=(6, 4), dpi=100)
    ax = fig.add_subplot()
    for name, values in curves.items():
        values = np.asarray(values, float)
        window = max(len(values) // 10, 1)
        smooth = np.convolve(values, np.ones(window) / window, mode="valid") if len(values) else values
        ax.plot(np.arange(len(smooth)) + window - 1, smooth, label=name)
    ax.set(xlabel=xlabel, ylabel="loss")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right")
    fig.tight_layout()
    _save(fig, path)
