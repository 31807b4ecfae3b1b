"""The README's table of every shipped model on its three test looks side by side, read from the model cards (what
scripts/ship_model.py and scripts/rescore_model.py measured): per look the fitted ADD AUC and mean ADD, the
ablation (feed-forward, fitted, fitted without the depth prior, fitted with the true joints), and the depth diagnostics (DepthNet's root depth,
the fit without the depth prior and the shipped estimate, median signed error in % of the true depth; the
detected keypoints' median scale about the true centroid). Then the truncation table: the fitted AUC of the frames
that show the whole robot and of those with one or two, or three or more, of DREAM's keypoints out of the image.
A card that lacks a look or a measure shows "-".

    python scripts/looks_table.py            # rewrites the block between the markers in README.md
    python scripts/looks_table.py --print    # only prints it
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from holo_pose_ros.model.cards import read_card
from holo_pose_ros.resources import weights_dir
from holo_pose_ros.robots.spec import load_robot_spec

ROOT = Path(__file__).resolve().parent.parent
BEGIN, END = "<!-- looks-table:begin -->", "<!-- looks-table:end -->"
LOOKS = ("randomized", "photo", "unseen")  # the two training looks, then the one no training config names
MODELS = ("panda", "kuka", "baxter")


def _get(section: dict | None, *keys):
    """section[k0][k1]..., None where any level is missing."""
    for key in keys:
        if not isinstance(section, dict) or section.get(key) is None:
            return None
        section = section[key]
    return section


def _f(value, spec: str, suffix: str = "") -> str:
    return "-" if value is None else format(value, spec) + suffix


def look_cells(test: dict | None) -> list[str]:
    """The table's cells of one model on one look (its card's test entry; None: not measured)."""
    if not test:
        return ["-"] * 4
    ablation = test.get("ablation") or {}
    depth = test.get("depth_diagnostics") or {}
    error = depth.get("root_depth_error") or {}
    fitted = _f(test.get("add_auc"), ".1f") + " / " + _f(test.get("add_mean_mm"), ".0f")
    methods = " / ".join([_f(_get(ablation, m, "add_auc"), ".1f") for m in ("feed-forward", "fitted")]
                         + [_f(_get(depth, "add_auc", "fit_no_prior"), ".1f"),
                            _f(_get(ablation, "fitted, known joints", "add_auc"), ".1f")])
    relative = " / ".join(_f(_get(error, s, "relative_median_percent"), "+.1f")
                          for s in ("depthnet", "fit_no_prior", "shipped"))
    scale = _f(_get(depth, "keypoint_scale", "detected", "median"), ".3f")
    return [fitted, methods, relative, scale]


def truncation_cells(rows: list[dict] | None, n_keypoints: int) -> list[str]:
    """'AUC (frames)' of the whole views, of those missing 1-2 keypoints and of those missing 3 or more, from a
    card's truncation rows (one per in-image count). AUC is a mean over frames, so a group's is the frame-weighted
    mean of its rows'."""
    groups = ((n_keypoints, n_keypoints), (n_keypoints - 2, n_keypoints - 1), (0, n_keypoints - 3))
    cells = []
    for lo, hi in groups:
        chosen = [r for r in rows or [] if lo <= r["n_in_image"] <= hi and r.get("add_auc") is not None]
        frames = sum(r["n_frames"] for r in chosen)
        auc = sum(r["add_auc"] * r["n_frames"] for r in chosen) / frames if frames else None
        cells.append("-" if auc is None else f"{auc:.1f} ({frames})")
    return cells if rows else ["-"] * 3


def table(models: tuple[str, ...] = MODELS) -> list[str]:
    """Markdown lines: one row per shipped model and look, then the truncation table."""
    lines = ["| model | look | fitted AUC / mean ADD mm | AUC: feed-forward / fitted / fitted without the depth prior / "
             "fitted with the true joints | "
             "root depth error %: DepthNet / fit without prior / shipped | detected keypoints' scale |",
             "|---|---|---|---|---|---|"]
    cards = {name: read_card(weights_dir() / f"{name}.yaml")[1] for name in models
             if (weights_dir() / f"{name}.yaml").exists()}
    tests = {name: card.get("test") or {} for name, card in cards.items()}
    for name in cards:
        for look in LOOKS:
            lines.append(f"| `{name}` | {look} | " + " | ".join(look_cells(tests[name].get(look))) + " |")
    lines += ["", "| model | look | whole robot in view: AUC (frames) | 1-2 keypoints out | 3 or more out |",
              "|---|---|---|---|---|"]
    for name, card in cards.items():
        n = len(load_robot_spec(card["robot"]).keypoints)
        for look in LOOKS:
            rows = (tests[name].get(look) or {}).get("truncation")
            lines.append(f"| `{name}` | {look} | " + " | ".join(truncation_cells(rows, n)) + " |")
    return lines


def rewrite(page: Path, lines: list[str]) -> None:
    """Replace the block between BEGIN and END in `page` with `lines`."""
    text = page.read_text()
    if BEGIN not in text or END not in text:
        raise SystemExit(f"{page}: no {BEGIN} ... {END} block to rewrite")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    page.write_text(head + BEGIN + "\n" + "\n".join(lines) + "\n" + END + tail)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--page", default=str(ROOT / "README.md"), help="the page whose looks-table block is rewritten")
    parser.add_argument("--print", action="store_true", help="print the table, rewrite nothing")
    args = parser.parse_args(argv)
    lines = table()
    print("\n".join(lines))
    if not args.print:
        rewrite(Path(args.page), lines)
        print(f"updated the table in {args.page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
