"""Choose, for a shipped model that fits by parts, whether tracked frames search by parts too: track generated
validation videos (never a test set) both ways and write the card's `estimator.parts_tracked` with its evidence
(`tracking_validation`, `tracking_chosen_on`, `tracking_min_gain_auc`: the search must gain more than that, by
default 1 AUC point, since it costs tracking frame rate; with it a tracked frame searches every
`parts_tracked_every`-th frame, config/fitting.yaml); the weights and every other card section stay as
they are.
scripts/ship_model.py makes the same choice with `--validation-video` when it ships a model.

    python scripts/choose_tracked_search.py panda --video data/panda_val_video_1015
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from ship_model import TRACKED_SEARCH_MIN_GAIN, tracked_search_choice  # noqa: E402

from holo_pose_ros.model.cards import read_card, rewrite_card  # noqa: E402
from holo_pose_ros.model.lifter import load_lifter  # noqa: E402
from holo_pose_ros.model.weights import load_model  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", help="a shipped model's name (panda) or its card's path")
    parser.add_argument("--video", action="append", required=True, help="generated validation video, repeatable")
    parser.add_argument("--min-gain", type=float, default=TRACKED_SEARCH_MIN_GAIN, metavar="AUC",
                        help="AUC points the search on tracked frames must gain to be chosen (default "
                             f"{TRACKED_SEARCH_MIN_GAIN}: it costs tracking frame rate)")
    args = parser.parse_args(argv)
    card_path, card = read_card(args.name)
    estimator_card = card.get("estimator") or {}
    if not (estimator_card.get("fit") and estimator_card.get("parts")) or "lifter" not in card:
        print(f"error: {card_path} does not fit by parts (estimator.parts): nothing to choose", file=sys.stderr)
        return 1
    net, robot, _ = load_model(card_path)
    lifter = load_lifter(card_path.parent / card["lifter"])
    card["estimator"] = {**estimator_card, **tracked_search_choice(net, robot, lifter, args.video, args.min_gain,
                                                                         estimator_card.get("fit_config"))}
    rewrite_card(card_path, card)
    print(f"rewrote {card_path}: estimator.parts_tracked = {card['estimator']['parts_tracked']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
