"""Choose, for a shipped fitted model, the weight of the fit's depth prior (DepthNet's root depth pulling the fitted
depth; config/fitting.yaml `depth_prior_weight`) on generated validation folders (never a test set): each folder
detected once, fitted with every weight of the grid, the mean fitted ADD AUC over the folders decides (a tie within
0.05 goes to the higher mean on the unseen look's folders, the stand-in for a user's camera). Writes the card's
`estimator.fit_config.depth_prior_weight` and its evidence (`depth_prior_validation`: the mean and each folder's AUC
per weight, `depth_prior_chosen_on`); the weights and every other card section stay as they are. How much the prior
should weigh depends on how good the model's DepthNet is against its 2D keypoints, so each model chooses its own;
scripts/ship_model.py makes the same choice on its `--validation` folders when it ships a model.

With `--known-joints W,W,...` the same detections also choose the weight when the joints are known (the node's
calibration mode; `fit_config.known_joints_depth_prior_weight`): each frame fitted with its true joints, only the
pose free, so the 2D points alone fix the depth far better and the prior should weigh less.

    python scripts/choose_depth_prior.py panda --validation data/panda_val_1012 \
        --validation data/panda_val_unseen_1013 [--weights 3,5,10,20,30] [--known-joints 0,1,3,10,30] [--frames N]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import SETTINGS_FILE
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.evaluation.metrics import add_auc, add_per_frame
from holo_pose_ros.fitting import Fitter
from holo_pose_ros.model.cards import read_card, rewrite_card

TIE_AUC = 0.05  # mean AUC differences below this are ties, broken by the unseen look's folders
UNSEEN_LOOK = "unseen"  # config/generate/unseen.yaml: never named by a training config (ship_model uses it too)


Detections = list  # [(DreamFrame, Detection | None)] of one folder


def detect_folder(estimator: Estimator, folder: str, frames: int | None) -> Detections:
    """The network's detections of a folder's first `frames` frames, computed once for every weight."""
    reader = DreamReader(folder, estimator.robot)
    return [(f, estimator.detect(reader.load_image(f), f.K))
            for f in tqdm(list(reader)[:frames], desc=f"detect {Path(folder).name}", unit="frame")]


def folder_aucs(estimator: Estimator, detections: Detections, weights: list[float],
                known_joints: bool = False) -> dict[float, float]:
    """Fitted ADD AUC of one folder's detections per depth prior weight; with `known_joints`, fitted with each
    frame's true joints (the calibration mode) and the weight of that mode."""
    key = "known_joints_depth_prior_weight" if known_joints else "depth_prior_weight"
    if known_joints and any(f.joints is None for f, _ in detections):
        raise ValueError(f"{detections[0][0].image_path.parent}: frames without joint states cannot choose the "
                         "known-joints weight")
    original = estimator.fitter
    aucs = {}
    for weight in weights:
        estimator.fitter = Fitter(original.robot, {**original.config, key: float(weight)})
        add = []
        for frame, detection in detections:
            fitted = estimator.estimate_detection(detection, frame.K, frame.joints if known_joints else None,
                                                  methods=("fitted",), static_camera_step=False)["fitted"]
            add.append(float(add_per_frame(fitted.keypoints_3d, frame.keypoints_3d)) if fitted.found else np.inf)
        aucs[weight] = round(float(add_auc(np.array(add))), 2)
    estimator.fitter = original
    return aucs


def weight_grid(text: str) -> list[float]:
    """The weights of a comma-separated grid ("3,5,10"; "" is none)."""
    return [float(w) for w in text.split(",") if w]


def is_unseen_look(folder: str) -> bool:
    """Whether a generated folder was made with the unseen look (its generator settings file says so)."""
    settings = Path(folder) / SETTINGS_FILE
    return settings.exists() and Path(json.loads(settings.read_text()).get("config", "")).stem == UNSEEN_LOOK


def choose(by_folder: dict[str, dict[float, float]]) -> tuple[float, dict[float, float]]:
    """The weight with the highest mean AUC over the folders (ties: the higher mean on the unseen look's folders)
    and the mean per weight."""
    weights = list(next(iter(by_folder.values())))
    mean = {w: float(np.mean([a[w] for a in by_folder.values()])) for w in weights}
    unseen = [a for folder, a in by_folder.items() if is_unseen_look(folder)] or list(by_folder.values())
    unseen_mean = {w: float(np.mean([a[w] for a in unseen])) for w in weights}
    best = max(mean.values())
    tied = [w for w in weights if mean[w] >= best - TIE_AUC]
    return max(tied, key=lambda w: unseen_mean[w]), mean


def _table(title: str, by_folder: dict[str, dict[float, float]], mean: dict[float, float]) -> None:
    print(f"| {title} | mean AUC | " + " | ".join(Path(f).name for f in by_folder) + " |")
    print("|---:|---:|" + "---:|" * len(by_folder))
    for w in mean:
        print(f"| {w:g} | {mean[w]:.2f} | " + " | ".join(f"{a[w]:.1f}" for a in by_folder.values()) + " |")


def depth_prior_choice(estimator: Estimator, folders: list[str], weights: list[float],
                       frames: int | None = None, known_joints_weights: list[float] | None = None) -> dict:
    """The card's `estimator` entries of the choice: `fit_config` (the chosen `depth_prior_weight` unless `weights`
    is empty, and with `known_joints_weights` the chosen `known_joints_depth_prior_weight`; the caller merges it
    over the card's other fit settings), `depth_prior_chosen_on` and each grid's evidence (`depth_prior_validation`,
    `known_joints_depth_prior_validation`); prints the tables."""
    detections = {folder: detect_folder(estimator, folder, frames) for folder in folders}
    result: dict = {"fit_config": {}, "depth_prior_chosen_on": list(folders)}
    grids = [(name, grid, known) for name, grid, known in (("depth_prior", weights, False),
                                                          ("known_joints_depth_prior", known_joints_weights, True))
             if grid]
    for name, grid, known in grids:
        by_folder = {folder: folder_aucs(estimator, d, grid, known) for folder, d in detections.items()}
        chosen, mean = choose(by_folder)
        _table(f"{name.replace('_', ' ')} weight", by_folder, mean)
        result["fit_config"][f"{name}_weight"] = chosen
        result[f"{name}_validation"] = {w: {"mean_add_auc": round(mean[w], 2), "by_folder": {
            f: a[w] for f, a in by_folder.items()}} for w in grid}
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", help="a shipped model's name (panda) or its card's path")
    parser.add_argument("--validation", action="append", required=True, help="generated validation folder, repeatable")
    parser.add_argument("--weights", default="3,5,10,20,30",
                        help="the grid of depth prior weights ('': keep the card's, e.g. to choose only --known-joints)")
    parser.add_argument("--known-joints", default="", metavar="W,W,...",
                        help="also choose the weight with the joints known (calibration mode) from this grid, "
                             "e.g. 0,1,3,10,30 (default: not chosen)")
    parser.add_argument("--frames", type=int, default=None, help="the first N frames of each folder (default: all)")
    parser.add_argument("--backend", default="onnxruntime", choices=("torch", "onnxruntime"))
    args = parser.parse_args(argv)
    card_path, card = read_card(args.name)
    estimator_card = card.get("estimator") or {}
    if not estimator_card.get("fit") or "lifter" not in card:
        print(f"error: {card_path} is not a fitted model (estimator.fit and a lifter): no depth prior to weigh",
              file=sys.stderr)
        return 1
    estimator = Estimator.from_model(card_path, backend=args.backend)
    choice = depth_prior_choice(estimator, args.validation, weight_grid(args.weights), args.frames,
                                weight_grid(args.known_joints))
    chosen = choice.pop("fit_config")
    card["estimator"] = {**estimator_card, "fit_config": {**(estimator_card.get("fit_config") or {}), **chosen},
                         **choice}
    rewrite_card(card_path, card)
    print(f"rewrote {card_path}: " + ", ".join(f"estimator.fit_config.{k} = {v:g}" for k, v in chosen.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
