"""Ship a trained model: score its kept checkpoint on held-out generated test folders (never seen in training or
validation) through the deployed estimator, and write holo_pose_ros/weights/<name>.safetensors (float16) with a
model card that records the training, the metrics and the commands that measured them. With `--lifter`, the
lifter ships beside it (<name>_lifter.*, named in the card) and each test set also gets the ablation (feed-forward
/ lifter / fitted / fitted with the true joints); `--log` keeps the run's learning curve in docs/training_logs/.
A test folder of the unseen look (config/generate/unseen.yaml) also becomes the card's `domain_shift` figure.
The validation folders choose the default method (`estimator.fit`) and whether the fit searches by parts
(`estimator.parts`, fitting/parts.py) and, for a run trained with close-up views, whether it adds the close-up pass
(`estimator.close_ups`), and the weight of the fit's depth prior (`estimator.fit_config`,
scripts/choose_depth_prior.py); the tests and their ablation then run with that choice. With the search
and `--validation-video` (generated videos, config/generate/video.yaml), tracking them chooses whether tracked
frames search too (`estimator.parts_tracked`; scripts/choose_tracked_search.py does it for a shipped card).

    python scripts/ship_model.py runs/panda_heatmap_cpu/best.yaml panda --lifter runs/lifter/panda_lifter.yaml \
        --validation data/panda_val_1012 --validation data/panda_val_unseen_1013 \
        --test data/panda_test_dr:randomized --test data/panda_test_photo:photo --test data/panda_test_unseen:unseen \
        --log runs/panda_heatmap_cpu/log.csv --validation-video data/panda_val_video_1015
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import torch

from choose_depth_prior import UNSEEN_LOOK, depth_prior_choice, weight_grid

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import SETTINGS_FILE
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.evaluation.run import evaluate_folder, evaluate_methods, format_ablation
from holo_pose_ros.model.lifter import load_lifter, save_lifter
from holo_pose_ros.model.weights import load_model, save_model
from holo_pose_ros.resources import weights_dir

KEPT = ("n_frames", "n_not_found", "add_auc", "add_mean_mm", "add_median_mm", "add_below_mm", "joint_error_deg",
        "joint_error_modulo_symmetry_deg", "rotation_error_deg", "depth_error_mm", "reproj_error_px", "fps",
        "kp2d_dream_median_px", "kp2d_fit_median_px", "depth_diagnostics", "truncation", "apparent_size")
ROOT = Path(__file__).resolve().parent.parent
BY_PARTS = "fitted by parts"  # the validation's fourth row: the fit searched by parts (fitting/parts.py)
TRACKED_ROWS = {True: "by parts on every frame", False: "by parts on untracked frames"}  # tracking validation
TRACKED_SEARCH_MIN_GAIN = 1.0  # AUC points the search on tracked frames must gain on the validation videos to stay


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("card", help="the trained model card (runs/<name>/best.yaml, or the snapshot that "
                                     "scripts/choose_snapshot.py chose)")
    parser.add_argument("name", help="shipped name (holo_pose_ros/weights/<name>.*)")
    parser.add_argument("--test", action="append", required=True, help="DIR:LOOK of a held-out DREAM folder")
    parser.add_argument("--lifter", default=None, help="lifter card to ship with the model (holo-pose train-lifter)")
    parser.add_argument("--log", default=None, help="the run's log.csv, kept as docs/training_logs/<run>.csv")
    parser.add_argument("--resume-config", default=None, help="the training recipe the next run resumes with "
                                                              "(default: config/train/<run folder name>.yaml)")
    parser.add_argument("--validation", action="append", default=[],
                        help="generated validation folder (never a test set), repeatable (one per look: the unseen "
                             "look's too); the ablation's mean AUC over them chooses the default: fitted or feed-forward")
    parser.add_argument("--validation-video", action="append", default=[],
                        help="generated validation video (never a test set), repeatable: tracked with and without "
                             "the search by parts on tracked frames, it chooses estimator.parts_tracked")
    parser.add_argument("--tracked-search-min-gain", type=float, default=TRACKED_SEARCH_MIN_GAIN, metavar="AUC",
                        help="AUC points the search on tracked frames must gain on the videos to be chosen "
                             f"(default {TRACKED_SEARCH_MIN_GAIN}: it costs tracking frame rate)")
    parser.add_argument("--depth-prior-weights", default="3,5,10,20,30", metavar="W,W,...",
                        help="the grid the validation folders choose the fit's depth prior weight from "
                             "(scripts/choose_depth_prior.py; '' keeps config/fitting.yaml's)")
    parser.add_argument("--known-joints-depth-prior-weights", default="0,1,3,10,30", metavar="W,W,...",
                        help="the grid the same folders choose that weight from when the joints are known (the "
                             "calibration mode; '' keeps depth_prior_weight for it)")
    args = parser.parse_args(argv)
    net, robot, card = load_model(args.card)
    lifter = load_lifter(args.lifter) if args.lifter else None
    extra = {}
    if lifter is not None:
        lifter_card = weights_dir() / f"{args.name}_lifter.yaml"
        if Path(args.lifter).resolve() != lifter_card.resolve():  # the shipped lifter itself is not written again
            lifter_card = save_lifter(lifter, weights_dir() / f"{args.name}_lifter",
                                      {k: v for k, v in lifter.card.items() if k in ("training", "validation")},
                                      dtype=torch.float16)
        extra["lifter"] = lifter_card.name
        lifter = load_lifter(lifter_card)  # score what ships (float16)
    if lifter is not None and args.validation:
        ablations = {}
        for folder in args.validation:
            ablations[folder] = evaluate_methods(Estimator(net, robot, lifter=lifter), DreamReader(folder, robot),
                                                 known_joints=False)
            ablations[folder][BY_PARTS], _, _ = evaluate_folder(Estimator(net, robot, lifter=lifter, fit=True, parts=True),
                                                                DreamReader(folder, robot))
            print(f"validation {folder}:\n{format_ablation(ablations[folder])}")
        mean_auc = {m: sum(a[m]["add_auc"] for a in ablations.values()) / len(ablations) for m in next(iter(ablations.values()))}
        fit = bool(max(mean_auc["fitted"], mean_auc[BY_PARTS]) >= mean_auc["feed-forward"])
        extra["estimator"] = {"fit": fit, "parts": bool(fit and mean_auc[BY_PARTS] > mean_auc["fitted"]),
                              "chosen_on": args.validation,
                              "validation": {m: {"add_auc": auc} for m, auc in mean_auc.items()},  # mean over the folders
                              "validation_by_folder": {folder: {m: {"add_auc": r["add_auc"], "add_mean_mm": r["add_mean_mm"]}
                                                                for m, r in a.items()} for folder, a in ablations.items()}}
        print(f"default: {'fitted' if fit else 'feed-forward'}{' by parts' if extra['estimator']['parts'] else ''}")
        if fit and trained_with_close_ups(card):
            extra["estimator"].update(close_ups_choice(net, robot, lifter, args.validation, extra["estimator"]))
        if fit and args.depth_prior_weights:
            chosen = extra["estimator"]
            choice = depth_prior_choice(Estimator(net, robot, lifter=lifter, fit=True, parts=chosen["parts"],
                                                  close_ups=bool(chosen.get("close_ups"))),
                                        args.validation, weight_grid(args.depth_prior_weights),
                                        known_joints_weights=weight_grid(args.known_joints_depth_prior_weights))
            extra["estimator"].update(**choice)
        if extra["estimator"]["parts"] and args.validation_video:
            extra["estimator"].update(tracked_search_choice(net, robot, lifter, args.validation_video,
                                                            args.tracked_search_min_gain,
                                                            extra["estimator"].get("fit_config")))
        elif args.validation_video:
            print("validation videos not tracked: the search by parts is off, so tracked frames fit plainly anyway")
    fit, parts = extra.get("estimator", {}).get("fit"), bool(extra.get("estimator", {}).get("parts"))
    chosen = extra.get("estimator", {})
    metrics = score_tests(net, robot, args.name, lifter, fit, parts, args.test, bool(chosen.get("close_ups")),
                          chosen.get("fit_config"))
    if args.log:
        run = run_folder(args.card).name
        (ROOT / "docs" / "training_logs").mkdir(parents=True, exist_ok=True)
        shutil.copy(args.log, ROOT / "docs" / "training_logs" / f"{run}.csv")
    shipped = {k: card[k] for k in ("training", "validation") if k in card}
    run_config = ROOT / (args.resume_config or Path("config") / "train" / f"{run_folder(args.card).name}.yaml")
    out_dir = (shipped.get("training") or {}).get("config", {}).get("out")
    if out_dir and Path(out_dir).is_absolute() and Path(out_dir).resolve().is_relative_to(ROOT.resolve()):
        shipped["training"]["config"]["out"] = str(Path(out_dir).resolve().relative_to(ROOT.resolve()))  # no host paths
    if "training" in shipped and run_config.exists():  # the next run of the campaign warm-starts from this card
        shipped["training"]["resume_command"] = f"holo-pose train --config {run_config.relative_to(ROOT)}"
    shift = domain_shift(metrics)
    if shift:
        extra["domain_shift"] = shift
    out = save_model(net, robot.name, weights_dir() / args.name, {**extra, **shipped, "test": metrics},
                     dtype=torch.float16)
    print(f"shipped: {out}")
    return 0


def trained_with_close_ups(card: dict) -> bool:
    """Whether a run's card was trained with close-up views (its recipe's fourth mode probability is > 0)."""
    probabilities = (((card.get("training") or {}).get("config") or {}).get("views") or {}).get("mode_probabilities")
    return bool(probabilities and len(probabilities) == 4 and probabilities[3] > 0)


def close_ups_choice(net, robot, lifter, folders: list[str], chosen: dict) -> dict:
    """The card's `estimator.close_ups` and its evidence: the validation folders estimated as chosen (fitted, by
    parts or not) with the close-up pass, kept where it raises the mean AUC over the folders (it costs a network
    pass per part)."""
    rows = {}
    for folder in folders:
        estimator = Estimator(net, robot, lifter=lifter, fit=True, parts=bool(chosen["parts"]), close_ups=True)
        report, _, _ = evaluate_folder(estimator, DreamReader(folder, robot), depth_diagnostics=False)
        rows[folder] = {"add_auc": report["add_auc"], "add_mean_mm": report["add_mean_mm"]}
    without = BY_PARTS if chosen["parts"] else "fitted"
    mean_with = sum(r["add_auc"] for r in rows.values()) / len(rows)
    choice = bool(mean_with > chosen["validation"][without]["add_auc"])
    print(f"close-ups: {'on' if choice else 'off'} (mean AUC {mean_with:.2f} with, "
          f"{chosen['validation'][without]['add_auc']:.2f} without)")
    return {"close_ups": choice, "close_ups_validation": rows}


def run_folder(card: str | Path) -> Path:
    """The training run a kept card comes from: its folder, or the folder above for a snapshot (snapshots/)."""
    folder = Path(card).resolve().parent
    return folder.parent if folder.name == "snapshots" else folder


def tracked_search_choice(net, robot, lifter, videos: list[str], min_gain_auc: float = TRACKED_SEARCH_MIN_GAIN,
                          fit_config: dict | None = None) -> dict:
    """The card's `estimator.parts_tracked` and its evidence: each validation video tracked (fitted by parts on
    its untracked frames) with and without the search on tracked frames; the search stays on them only where it
    raises the mean AUC by more than `min_gain_auc`. A tracked frame also starts from the previous frame's fit, so
    the search may add nothing there but time (on every `parts_tracked_every`-th tracked frame, config/fitting.yaml:
    about 5 ms a searched frame on Panda), and a 360-frame video's AUC moves by a point or more between settings that
    hardly differ. `fit_config`: the card's fit settings."""
    auc = {}
    for video in videos:
        for tracked in (True, False):
            estimator = Estimator(net, robot, lifter=lifter, fit=True, parts=True, parts_tracked=tracked,
                                  tracking=True, fit_config=fit_config)
            report, _, _ = evaluate_folder(estimator, DreamReader(video, robot), depth_diagnostics=False)
            auc.setdefault(video, {})[TRACKED_ROWS[tracked]] = {"add_auc": report["add_auc"]}
    mean = {row: sum(a[row]["add_auc"] for a in auc.values()) / len(auc) for row in TRACKED_ROWS.values()}
    choice = bool(mean[TRACKED_ROWS[True]] > mean[TRACKED_ROWS[False]] + min_gain_auc)
    print(f"tracking: the search by parts on {'every frame' if choice else 'untracked frames only'} ({mean}; "
          f"it must gain more than {min_gain_auc} AUC)")
    return {"parts_tracked": choice, "tracking_chosen_on": list(videos), "tracking_validation": auc,
            "tracking_min_gain_auc": min_gain_auc}


def score_tests(net, robot, name: str, lifter, fit: bool | None, parts: bool, tests: list[str],
                close_ups: bool = False, fit_config: dict | None = None) -> dict:
    """The card's `test` section: each DIR:LOOK folder scored through the deployed estimator (the report's KEPT
    keys, depth diagnostics included; `fit_config`: the card's fit settings) and, with a lifter, its ablation;
    `name` is the model as users call it."""
    metrics = {}
    for item in tests:
        folder, _, look = item.partition(":")
        reader = DreamReader(folder, robot)
        estimator = Estimator(net, robot, lifter=lifter, fit=fit, parts=parts, close_ups=close_ups,
                              fit_config=fit_config)
        report, _, _ = evaluate_folder(estimator, reader)
        metrics[look or Path(folder).name] = {
            "data": _provenance(folder, len(reader)),
            "command": f"holo-pose evaluate --model {name} --data {folder} --out report.json",
            "method": ("fitted" if estimator.fit else "feed-forward") + (" by parts" if estimator.fit and parts else "")
                      + (", close-ups" if close_ups else ""),
            **{k: report[k] for k in KEPT if k in report},
        }
        print(f"{folder}: AUC {report['add_auc']:.1f}, mean ADD {report['add_mean_mm']} mm, "
              f"not found {report['n_not_found']}/{report['n_frames']}")
        if lifter is not None:
            ablation = evaluate_methods(Estimator(net, robot, lifter=lifter, parts=parts, close_ups=close_ups,
                                                  fit_config=fit_config), reader, depth_diagnostics=False)
            print(format_ablation(ablation))
            metrics[look or Path(folder).name]["ablation"] = {
                "command": f"holo-pose evaluate --model {name} --data {folder} --ablation",
                **{method: {k: r[k] for k in ("add_auc", "add_mean_mm", "add_median_mm", "n_not_found")}
                   | {"joint_error_mean_deg": r["joint_error_deg"]["mean"],
                      "rotation_error_mean_deg": r["rotation_error_deg"]["mean"]}
                   for method, r in ablation.items()}}
    return metrics


def domain_shift(metrics: dict) -> dict | None:
    """The card's domain-shift figure: the test AUC on the unseen look (a look no training config names, the
    stand-in for a user's camera) beside the training looks', and what the new look costs; None without one."""
    unseen = {look: m for look, m in metrics.items() if m.get("data", {}).get("look") == UNSEEN_LOOK}
    if not unseen:
        return None
    own = {look: m["add_auc"] for look, m in metrics.items() if look not in unseen}
    look, m = next(iter(unseen.items()))
    return {"look": look, "add_auc": m["add_auc"], "add_mean_mm": m["add_mean_mm"], "own_looks_add_auc": own,
            "auc_lost": {k: round(v - m["add_auc"], 2) for k, v in own.items()}}


def _provenance(folder: str, frames: int) -> dict:
    """How a generated test folder was made (its _generator_settings.json), for the model card."""
    path = Path(folder) / SETTINGS_FILE
    if not path.exists():
        return {"folder": folder, "frames": frames}
    settings = json.loads(path.read_text())
    return {"frames": frames, "robot": settings["robot"], "seed": settings["seed"], "look": settings["config"],
            "command": settings["command"]}


if __name__ == "__main__":
    sys.exit(main())
