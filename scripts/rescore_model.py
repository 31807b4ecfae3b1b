"""Score a shipped model again on held-out test folders and rewrite its card's `test` and `domain_shift` sections;
the weights, the lifter and every other card section stay as they are (the weights' hash is checked on loading).
For when the evaluation gains a measure that older cards lack (the depth diagnostics, the truncation and
apparent-size tables) or a model gets a new test look. Same scoring as scripts/ship_model.py: the card's validated
method (`estimator.fit`, `estimator.parts`), then the ablation when the model has a lifter.

    python scripts/rescore_model.py kuka --test data/kuka_test_randomized_seed3031:randomized \\
        --test data/kuka_test_photo_seed3032:photo --test data/kuka_test_unseen_seed3033:unseen
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from ship_model import domain_shift, score_tests  # noqa: E402

from holo_pose_ros.model.cards import read_card, rewrite_card  # noqa: E402
from holo_pose_ros.model.lifter import load_lifter  # noqa: E402
from holo_pose_ros.model.weights import load_model  # noqa: E402
from holo_pose_ros.resources import weights_dir  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", help="a shipped model's name (panda) or its card's path")
    parser.add_argument("--test", action="append", required=True, help="DIR:LOOK of a held-out DREAM folder, repeatable")
    parser.add_argument("--keep-other-looks", action="store_true",
                        help="keep the card's test looks that no --test names (default: the card lists only these)")
    args = parser.parse_args(argv)
    card_path, card = read_card(args.name)
    net, robot, _ = load_model(card_path)
    lifter = load_lifter(card_path.parent / card["lifter"]) if "lifter" in card else None
    estimator_card = card.get("estimator") or {}
    name = card_path.stem if card_path.parent.resolve() == weights_dir().resolve() else str(card_path)
    metrics = score_tests(net, robot, name, lifter, estimator_card.get("fit"), bool(estimator_card.get("parts")),
                          args.test, bool(estimator_card.get("close_ups")), estimator_card.get("fit_config"))
    tests = {**(card.get("test") or {}), **metrics} if args.keep_other_looks else metrics
    card = {**card, "test": tests}
    shift = domain_shift(tests)
    if shift:
        card["domain_shift"] = shift
    rewrite_card(card_path, card)
    print(f"rewrote {card_path}: test looks {', '.join(tests)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
