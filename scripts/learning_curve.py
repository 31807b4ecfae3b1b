"""Regenerate docs/learning_curve.png and the learning-curve table of docs/campaign.md from the training logs.

    python scripts/learning_curve.py            # docs/training_logs/*.csv -> docs/learning_curve.png + the table

Each training run's `log.csv` (runs/<name>/log.csv) is copied into docs/training_logs/<name>.csv when its model
ships, so the curve survives the run folder. One line per robot: validation median 2D error of the network's
keypoints (pixels of the 640 x 480 frame; DREAM's and all fit keypoints) and validation ADD AUC through the
deployed estimator (feed-forward, and fitted where the log has it), against cumulative training views and wall-clock training hours on the 2-core CPU; the
shipped model's point is marked (its card's `training.cumulative_views`). Where a robot's current recipe (its newest
run's name without the run number) has two or more runs, a dotted power law through their kept points says where
the curve is going: its exponent in the recipe's own views (those since its first run started) and the views and
hours it would take to reach `--target-px`.
"""

from __future__ import annotations

import argparse
import csv
import math
import re
from pathlib import Path

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
BEGIN, END = "<!-- learning-curve:begin -->", "<!-- learning-curve:end -->"
PANELS_IN = 5.2  # height of the three panels, inches; the legend below them adds its own


def read_log(path: Path) -> list[dict]:
    """Rows of a training log with a validation 2D error, numbers as floats (None where empty)."""
    rows = []
    with open(path) as f:
        for row in csv.DictReader(f):
            parsed = {k: _number(v) for k, v in row.items()}
            if parsed.get("val_kp2d_fit_median_px") is not None and parsed.get("views") is not None:
                rows.append(parsed)
    return rows


def _number(value: str | None):
    try:
        return float(value)
    except (TypeError, ValueError):
        return value or None


def shipped_card(robot: str) -> dict:
    """The card of `robot`'s shipped model ({} when none ships)."""
    card = ROOT / "holo_pose_ros" / "weights" / f"{robot}.yaml"
    return (yaml.safe_load(card.read_text()) or {}) if card.exists() else {}


def shipped_point(robot: str) -> dict | None:
    """(views, validation 2D error, AUC) of the shipped model of `robot`, from its card."""
    data = shipped_card(robot)
    training, validation = data.get("training") or {}, data.get("validation") or {}
    if "kp2d_fit_median_px" not in validation:
        return None
    return {"views": training.get("cumulative_views"), "hours": training.get("cumulative_train_hours"),
            "fit": validation["kp2d_fit_median_px"], "dream": validation.get("kp2d_dream_median_px"),
            "auc": validation.get("add_auc")}


def shipped_run(robot: str) -> str | None:
    """The training run of `robot`'s shipped model (its card's `training.config.out` folder name), or None."""
    out = ((shipped_card(robot).get("training") or {}).get("config") or {}).get("out")
    return Path(out).name if out else None


def kept_row(rows: list[dict]) -> dict:
    """The validation row a run keeps: its lowest median 2D error of the fit keypoints (the trainer's `best`)."""
    return min(rows, key=lambda r: r["val_kp2d_fit_median_px"])


def trend(runs: dict[str, list[dict]], robot: str, n_runs: int, target_px: float) -> dict | None:
    """Power law px = c * views^-alpha through the kept points (lowest fit-keypoint error) of the last `n_runs` runs
    of `robot`'s current recipe (runs named like its shipped model's run, else its newest, up to the run number and a
    `_not_shipped`), and the views and training
    hours (at those runs' mean views/s) at which it reaches `target_px`; None with fewer than two such runs."""
    names = [name for name in runs if name.split("_")[0] == robot]
    if not names:
        return None
    run_number = r"\d*(_not_shipped)?"  # a run that lost to the shipped one is still a point of its recipe's curve
    shipped = shipped_run(robot)  # a new recipe's views may restart at 0 (another robot's donor): the shipped run says
    recipe = re.sub(run_number + "$", "", shipped if shipped in names else names[-1])
    every = [name for name in names if re.fullmatch(re.escape(recipe) + run_number, name)]
    family = every[-n_runs:]
    if len(family) < 2:
        return None
    origin = recipe_origin(runs[every[0]])
    kept = [kept_row(runs[name]) for name in family]
    views = np.array([r["views"] for r in kept]) - origin
    px = np.array([r["val_kp2d_fit_median_px"] for r in kept])
    slope, intercept = np.polyfit(np.log(views), np.log(px), 1)
    speed = float(np.mean([r["images_per_s"] for name in family for r in runs[name] if r.get("images_per_s")]))
    needed = math.exp((math.log(target_px) - intercept) / slope) if slope < 0 else math.inf
    return {"recipe": recipe, "runs": family, "views": views, "px": px, "alpha": -slope, "intercept": intercept,
            "origin": origin, "views_needed": needed, "hours_needed": max(needed - views[-1], 0.0) / speed / 3600,
            "views_s": speed}


def recipe_origin(rows: list[dict]) -> float:
    """The cumulative view count at which a recipe's first run started (its warm-start model's views): its first
    logged row's views less that row's steps at the run's views per step. The power law counts the recipe's own
    views: a new head warm-started on a long-trained backbone would otherwise look like a steep curve far along."""
    first, second = rows[0], rows[1] if len(rows) > 1 else None
    if second is None or second["step"] == first["step"]:
        return 0.0
    per_step = (second["views"] - first["views"]) / (second["step"] - first["step"])
    return max(first["views"] - first["step"] * per_step, 0.0)


def _cell(value) -> str:
    """A table cell: one decimal, or a dash where the log has no value (runs before the column existed)."""
    return "—" if value is None else f"{value:.1f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", default=str(ROOT / "docs" / "training_logs"), help="folder of <run>.csv logs")
    parser.add_argument("--out", default=str(ROOT / "docs" / "learning_curve.png"))
    parser.add_argument("--page", default=str(ROOT / "docs" / "campaign.md"),
                        help="the Markdown page whose learning-curve block is rewritten")
    parser.add_argument("--trend-runs", type=int, default=3, help="runs of the current recipe the power law goes through")
    parser.add_argument("--target-px", type=float, default=3.0, help="fit-keypoint error the projection is for (px)")
    args = parser.parse_args()
    runs = {p.stem: read_log(p) for p in sorted(Path(args.logs).glob("*.csv"))}
    runs = dict(sorted(((name, rows) for name, rows in runs.items() if rows), key=lambda run: run[1][0]["views"]))
    if not runs:
        raise SystemExit(f"no training logs with a 2D validation in {args.logs}")
    fig, axes = plt.subplots(1, 3, figsize=(16, PANELS_IN))
    colours = plt.get_cmap("tab10" if len(runs) <= 10 else "tab20").colors  # one colour per run in every panel
    table = ["| run | robot | views | train hours | val 2D median px (DREAM / fit kps) | val ADD AUC (feed-forward / fitted) |",
             "|---|---|---|---|---|---|"]
    starred = set()  # robots whose shipped model is already marked (once each)
    for index, (name, rows) in enumerate(runs.items()):
        robot, c = name.split("_")[0], colours[index % len(colours)]
        views = [r["views"] / 1e3 for r in rows]
        hours = [r.get("train_hours") or math.nan for r in rows]
        axes[0].plot(views, [r["val_kp2d_fit_median_px"] for r in rows], "-o", ms=3, color=c)
        axes[0].plot(views, [r["val_kp2d_dream_median_px"] for r in rows], "--", color=c)
        axes[1].plot(hours, [r["val_kp2d_fit_median_px"] for r in rows], "-o", ms=3, color=c, label=name)
        axes[2].plot(views, [r.get("val_add_auc") or 0.0 for r in rows], "--o", ms=3, color=c)
        fitted = [(v, r["val_fitted_add_auc"]) for v, r in zip(views, rows) if r.get("val_fitted_add_auc") is not None]
        if fitted:
            axes[2].plot(*zip(*fitted), "-s", ms=3, color=c)
        point = shipped_point(robot) if robot not in starred else None
        starred.add(robot)
        if point and point["views"]:
            axes[0].plot([point["views"] / 1e3], [point["fit"]], "k*", ms=14, label="shipped model" if len(starred) == 1
                         else None)
            if point.get("hours"):
                axes[1].plot([point["hours"]], [point["fit"]], "k*", ms=14)
        last = rows[-1]
        best = kept_row(rows)
        for r, tag in ((best, "best"), (last, "last")):
            table.append(f"| {name} ({tag}) | {robot} | {int(r['views']):,} | {r.get('train_hours') or math.nan:.2f} | "
                         f"{r['val_kp2d_dream_median_px']:.1f} / {r['val_kp2d_fit_median_px']:.1f} | "
                         f"{(r.get('val_add_auc') or 0.0):.1f} / {_cell(r.get('val_fitted_add_auc'))} |")
    trends = []
    for robot in dict.fromkeys(name.split("_")[0] for name in runs):
        t = trend(runs, robot, args.trend_runs, args.target_px)
        if t is None:
            continue
        reach = (f"{t['views_needed'] / 1e6:,.2f} M views of the recipe, {t['hours_needed']:,.0f} more training hours at "
                 f"{t['views_s']:.0f} views/s" if t["hours_needed"] < 1e5 else "beyond 100,000 training hours")
        trends.append(f"- {robot}, `{t['recipe']}*` ({', '.join(t['runs'])}): px ~ views^-{t['alpha']:.2f}; "
                      f"{args.target_px:g} px: {reach}")
        x = np.geomspace(t["views"][0], t["views"][-1] * 1.5, 20)
        axes[0].plot((x + t["origin"]) / 1e3, np.exp(t["intercept"]) * x ** -t["alpha"], "k:", lw=1.5,
                     label="power law of the current recipe" if len(trends) == 1 else None)
    if trends:
        table += ["", f"Where the curves go (a power law through the kept points of each robot's last "
                      f"{args.trend_runs} runs of its current recipe):", *trends]
    axes[0].set(xlabel="training views (thousands, cumulative: the warm-start model's included)", ylabel="validation median 2D error (px, 640x480)",
                yscale="log", title="2D error vs views (solid: fit keypoints, dashed: DREAM's)")
    axes[1].set(xlabel="wall-clock training hours (2-core CPU)", ylabel="fit keypoints, median px", yscale="log",
                title="2D keypoint error vs time")
    axes[2].set(xlabel="training views (thousands)", ylabel="ADD AUC (%)",
                title="validation AUC (solid: fitted, dashed: feed-forward)")
    for ax in axes[:2]:  # plain numbers on the log axes
        ax.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        ax.yaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%.0f"))
    for ax in axes:
        ax.grid(alpha=0.3, which="both")
    handles = axes[1].get_legend_handles_labels()[0] + axes[0].get_legend_handles_labels()[0]
    columns = min(len(handles), 5)
    fig.legend(handles=handles, loc="lower center", ncol=columns, fontsize=8, frameon=False)
    legend_in = 0.17 * -(-len(handles) // columns) + 0.6  # its rows, and the panels' axis labels above it
    fig.set_size_inches(16, PANELS_IN + legend_in)
    fig.tight_layout(rect=(0, legend_in / (PANELS_IN + legend_in), 1, 1))  # room for the runs' legend below the panels
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")
    page = Path(args.page)
    text = page.read_text()
    if BEGIN in text and END in text:
        head, rest = text.split(BEGIN, 1)
        _, tail = rest.split(END, 1)
        page.write_text(head + BEGIN + "\n" + "\n".join(table) + "\n" + END + tail)
        print(f"updated the table in {page}")
    print("\n".join(table))


if __name__ == "__main__":
    main()
