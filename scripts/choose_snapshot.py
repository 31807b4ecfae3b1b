"""Choose which of a training run's validated models to ship, on validation folders of several looks.

The trainer keeps its `best.yaml` by the fit keypoints' 2D error on its own look's 48 frames, a criterion blind to
what matters most: the look no training config names (config/generate/unseen.yaml, the stand-in for a user's
camera). With `validation.snapshots: true` it also keeps every validated model (runs/<run>/snapshots/); this scores
each of them, and optionally the shipped model as the bar, through the deployed estimator fitted by parts on the
first `--frames` frames of each generated validation folder (never a test set), with the fit settings of the
robot's shipped card (`estimator.fit_config`: the depth prior's weight it deploys; `--fit-config default` for
config/fitting.yaml's), and chooses the one of the best mean ADD AUC over the folders (ties: the earliest), or with
`--criterion median_add` the lowest median ADD averaged over the folders (for a robot whose AUCs are all near 0,
e.g. Baxter's today, where the AUC only ranks noise). It
writes snapshots/choice.json and choice.png (the criterion's figure by step, one line per folder, the bar dashed)
and prints the chosen card for scripts/ship_model.py. A snapshot (or the bar) already in choice.json with the same
weights (sha256), frames, lifter, folders and fit settings is not scored again, so it can run while the run trains;
a run started afresh over old snapshots is scored afresh.

    python scripts/choose_snapshot.py runs/kuka_pyramid224_cpu2 --baseline kuka \\
        --validation data/kuka_val_1012 --validation data/kuka_val_unseen_1013 --validation data/kuka_val_unseen_1014
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from tqdm import tqdm  # noqa: E402

from holo_pose_ros.data.dream import DreamReader  # noqa: E402
from holo_pose_ros.estimator import Estimator  # noqa: E402
from holo_pose_ros.evaluation.run import evaluate_folder  # noqa: E402
from holo_pose_ros.model.cards import file_sha256, read_card  # noqa: E402
from holo_pose_ros.model.lifter import load_lifter, shipped_lifter  # noqa: E402
from holo_pose_ros.model.weights import load_model  # noqa: E402


def score(card_path: Path, lifter, folders: list[str], frames: int | None, fit_config: dict) -> dict:
    """ADD AUC and mean ADD (mm) of one model card on each folder, fitted by parts with the given (loaded) lifter
    and fit settings (over config/fitting.yaml's)."""
    net, robot, _ = load_model(card_path)
    scores = {}
    for folder in folders:
        estimator = Estimator(net, robot, lifter=lifter, fit=True, parts=True, fit_config=dict(fit_config))
        report, _, _ = evaluate_folder(estimator, DreamReader(folder, robot), limit=frames, depth_diagnostics=False,
                                       progress=False)
        scores[folder] = {"add_auc": report["add_auc"], "add_mean_mm": report["add_mean_mm"],
                          "add_median_mm": report["add_median_mm"], "n_not_found": report["n_not_found"],
                          "n_frames": report["n_frames"]}
    return scores


def weights_digest(card: str | Path) -> str:
    """The sha256 of a model card's weights file: what a score belongs to (a snapshot's path is reused when a run
    is started afresh)."""
    card_path, content = read_card(card)
    return file_sha256(card_path.parent / content["weights"])


def shipped_fit_config(robot: str) -> dict:
    """The fit settings that the robot's shipped card deploys (`estimator.fit_config`, e.g. its depth prior's
    weight); {} when it has none or no model of that name ships."""
    try:
        _, card = read_card(robot)
    except (FileNotFoundError, ValueError):
        return {}
    return dict((card.get("estimator") or {}).get("fit_config") or {})


def scored_before(path: Path, frames: int, lifter: Path, folders: list[str], fit_config: dict) -> dict:
    """Scores of an earlier choice.json made with the same frames, lifter, folders and fit settings, by weights
    digest (the snapshots' and the bar's): a run's snapshots can be scored while it trains and only the new ones
    scored at its end. Keyed by (weights sha256, lifter path)."""
    if not path.exists():
        return {}
    before = json.loads(path.read_text())
    if (before.get("frames"), before.get("lifter"), before.get("validation"), before.get("fit_config")) != (
            frames, str(lifter), folders, fit_config):
        return {}
    rows = [*before.get("snapshots", []), *([before["baseline"]] if before.get("baseline") else [])]
    return {(row["sha256"], row.get("lifter", str(lifter))): row["scores"] for row in rows
            if "sha256" in row and all("add_median_mm" in s for s in row["scores"].values())}


# criterion name: (the folder figure it averages, the row's key of that average, higher is better, its words for
# the json)
CRITERIA = {"auc": ("add_auc", "mean_add_auc", True, "mean ADD AUC over the validation folders, fitted by parts"),
            "median_add": ("add_median_mm", "mean_median_add_mm", False,
                           "median ADD (mm) averaged over the validation folders, fitted by parts")}


def summary(scores: dict) -> dict:
    """A model's figures over the folders: mean ADD AUC and mean of the folders' median ADD (mm; NaN where a folder
    has no estimate)."""
    medians = [math.nan if s["add_median_mm"] is None else s["add_median_mm"] for s in scores.values()]
    return {"mean_add_auc": sum(s["add_auc"] for s in scores.values()) / len(scores),
            "mean_median_add_mm": sum(medians) / len(medians)}


def rank(row: dict, criterion: str) -> float:
    """The criterion's value of a row, oriented so that higher is better (a model that found no robot in a folder,
    whose median ADD is NaN, ranks last)."""
    _, mean_key, higher_better, _ = CRITERIA[criterion]
    value = row[mean_key] if higher_better else -row[mean_key]
    return -math.inf if math.isnan(value) else value


def plot(path: Path, steps: list[int], rows: list[dict], folders: list[str], baseline: dict | None,
         criterion: str) -> None:
    """The criterion's figure (AUC or median ADD) by training step for each folder and their mean; the shipped
    model's figures dashed."""
    key, mean_key, _, _ = CRITERIA[criterion]
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    for i, folder in enumerate([*folders, "mean"]):
        values = [r[mean_key] if folder == "mean" else r["scores"][folder][key] for r in rows]
        line, = ax.plot(steps, values, marker="o", lw=2.2 if folder == "mean" else 1.2, label=Path(folder).name,
                        color="black" if folder == "mean" else f"C{i}")
        if baseline:
            bar = baseline[mean_key] if folder == "mean" else baseline["scores"][folder][key]
            ax.axhline(bar, ls="--", lw=1, color=line.get_color())
    ax.set_xlabel("training step")
    ax.set_ylabel("ADD AUC, fitted by parts" if key == "add_auc" else "median ADD (mm), fitted by parts")
    ax.set_title(f"{path.parent.parent.name}: validated models" + (f" (dashed: shipped `{baseline['card']}`)"
                                                                    if baseline else ""), fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", help="a training run folder with snapshots/ (validation.snapshots: true)")
    parser.add_argument("--validation", action="append", required=True,
                        help="generated validation folder (never a test set), repeatable; one per look")
    parser.add_argument("--frames", type=int, default=160, help="frames of each folder scored (default 160)")
    parser.add_argument("--since", type=int, default=0, help="only snapshots from this training step on")
    parser.add_argument("--baseline", default=None, help="a shipped model's name or card, scored as the bar")
    parser.add_argument("--lifter", default=None, help="lifter card (default: the robot's shipped lifter)")
    parser.add_argument("--criterion", choices=sorted(CRITERIA), default="auc",
                        help="auc (default): the best mean ADD AUC; median_add: the lowest mean of the folders' "
                             "median ADD (for a robot whose AUCs are all near 0)")
    parser.add_argument("--fit-config", choices=("shipped", "default"), default="shipped",
                        help="shipped (default): score with the fit settings of the robot's shipped card (its depth "
                             "prior's weight), as deployed; default: config/fitting.yaml's")
    args = parser.parse_args(argv)
    folder = Path(args.run) / "snapshots"
    cards = sorted(p for p in folder.glob("step_*.yaml") if int(p.stem.split("_")[1]) >= args.since)
    if not cards:
        print(f"error: no snapshots in {folder} (train with `validation.snapshots: true`)", file=sys.stderr)
        return 1
    robot = read_card(cards[0])[1]["robot"]
    lifter = Path(args.lifter) if args.lifter else shipped_lifter(robot)
    if lifter is None:
        print(f"error: no shipped lifter for {robot}: name one with --lifter", file=sys.stderr)
        return 1
    fit_config = shipped_fit_config(robot) if args.fit_config == "shipped" else {}
    done = scored_before(folder / "choice.json", args.frames, lifter, args.validation, fit_config)
    print(f"fit settings over config/fitting.yaml's: {fit_config or 'none'}")
    baseline = None
    if args.baseline:
        base_path, base_card = read_card(args.baseline)
        base_lifter = base_path.parent / base_card["lifter"] if "lifter" in base_card else lifter
        digest = weights_digest(base_path)
        before = done.get((digest, str(base_lifter)))
        scores = before or score(base_path, load_lifter(base_lifter), args.validation, args.frames, fit_config)
        baseline = {"card": args.baseline, "sha256": digest, "lifter": str(base_lifter), "scores": scores,
                    **summary(scores)}
        print(f"bar {args.baseline}: mean AUC {baseline['mean_add_auc']:.2f}, median ADD "
              f"{baseline['mean_median_add_mm']:.0f} mm; "
              + " ".join(f"{Path(f).name} {s['add_auc']:.1f}" for f, s in scores.items())
              + (" (scored before)" if before else ""))
    snapshot_lifter = load_lifter(lifter)  # one lifter for every snapshot: loaded once
    rows = []
    for card in tqdm(cards, desc="snapshots", unit="model"):
        digest = weights_digest(card)
        before = done.get((digest, str(lifter)))
        scores = before or score(card, snapshot_lifter, args.validation, args.frames, fit_config)
        rows.append({"card": str(card), "step": int(card.stem.split("_")[1]), "sha256": digest, "scores": scores,
                     **summary(scores)})
        tqdm.write(f"{card.stem}: mean AUC {rows[-1]['mean_add_auc']:.2f}, median ADD "
                   f"{rows[-1]['mean_median_add_mm']:.0f} mm; "
                   + " ".join(f"{Path(f).name} {s['add_auc']:.1f}" for f, s in scores.items())
                   + (" (scored before)" if before else ""))
    chosen = max(rows, key=lambda r: (rank(r, args.criterion), -r["step"]))
    result = {"criterion": CRITERIA[args.criterion][3], "frames": args.frames,
              "lifter": str(lifter), "validation": args.validation, "fit_config": fit_config, "baseline": baseline,
              "snapshots": rows,
              "chosen": chosen["card"],
              "beats_baseline": None if baseline is None else rank(chosen, args.criterion) > rank(baseline,
                                                                                                  args.criterion)}
    (folder / "choice.json").write_text(json.dumps(result, indent=1))
    plot(folder / "choice.png", [r["step"] for r in rows], rows, args.validation, baseline, args.criterion)
    verdict = "" if baseline is None else (" - beats the bar" if result["beats_baseline"] else " - does NOT beat the bar")
    print(f"chosen: {chosen['card']} (mean AUC {chosen['mean_add_auc']:.2f}, median ADD "
          f"{chosen['mean_median_add_mm']:.0f} mm){verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
