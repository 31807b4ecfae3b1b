"""scripts/choose_depth_prior.py on a copy of the shipped Kuka card and frames generated here: it writes the
weight with the best mean AUC over the folders (with --known-joints, the calibration mode's too), its evidence per
folder, and leaves the weights and every other card section as they were; the estimator then fits with those
weights. A tie goes to the unseen look's folders; a card that does not fit is refused with the reason."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

from holo_pose_ros.data.generator import SETTINGS_FILE, generate
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.model.cards import read_card

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = str(ROOT / "scripts" / "choose_depth_prior.py")
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
sys.path.insert(0, str(ROOT / "scripts"))

from choose_depth_prior import choose  # noqa: E402


def _copy_card(name: str, folder: Path) -> Path:
    """The shipped card of `name`, its weights and its lifter, copied into `folder`; the copy's card path."""
    card_path, card = read_card(name)
    lifter = yaml.safe_load((card_path.parent / card["lifter"]).read_text())
    for file in (card["weights"], card["lifter"], lifter["weights"]):
        shutil.copy(card_path.parent / file, folder / file)
    shutil.copy(card_path, folder / card_path.name)
    return folder / card_path.name


def test_the_best_weight_is_written_with_its_evidence_and_nothing_else_moves(tmp_path):
    card = _copy_card("kuka", tmp_path)
    before = yaml.safe_load(card.read_text())
    folders = []
    for seed, look in ((51, "randomized"), (52, "unseen")):
        folder = tmp_path / f"kuka_{look}"
        generate("kuka", 3, folder, seed=seed, workers=1, config=look, progress=False)
        folders += ["--validation", str(folder)]
    result = subprocess.run([sys.executable, SCRIPT, str(card), *folders, "--weights", "3,30", "--known-joints",
                             "0,30", "--backend", "torch"], capture_output=True, text=True, env=ENV, timeout=600)
    assert result.returncode == 0, result.stderr
    after = yaml.safe_load(card.read_text())
    chosen = after["estimator"]["fit_config"]["depth_prior_weight"]
    evidence = after["estimator"]["depth_prior_validation"]
    assert set(evidence) == {3.0, 30.0} and chosen in evidence
    assert after["estimator"]["depth_prior_chosen_on"] == folders[1::2]
    means = {w: e["mean_add_auc"] for w, e in evidence.items()}
    assert means[chosen] >= max(means.values()) - 0.05
    for w, e in evidence.items():
        assert abs(sum(e["by_folder"].values()) / 2 - e["mean_add_auc"]) < 0.01
    assert {k: v for k, v in after.items() if k != "estimator"} == {k: v for k, v in before.items() if k != "estimator"}
    known = after["estimator"]["known_joints_depth_prior_validation"]
    assert set(known) == {0.0, 30.0}
    assert after["estimator"]["fit_config"]["known_joints_depth_prior_weight"] == choose(
        {folder: {w: e["by_folder"][folder] for w, e in known.items()} for folder in folders[1::2]})[0]
    written = ("fit_config", "depth_prior_validation", "depth_prior_chosen_on", "known_joints_depth_prior_validation")
    assert {k: v for k, v in after["estimator"].items() if k not in written} == \
        {k: v for k, v in before["estimator"].items() if k not in written}
    config = Estimator.from_model(card).fitter.config
    assert (config["depth_prior_weight"], config["known_joints_depth_prior_weight"]) == \
        (chosen, after["estimator"]["fit_config"]["known_joints_depth_prior_weight"])
    assert f"depth_prior_weight = {chosen:g}" in result.stdout


def test_a_tie_goes_to_the_unseen_looks_folders_and_a_card_that_does_not_fit_is_refused(tmp_path):
    own, unseen = tmp_path / "own", tmp_path / "unseen"
    for folder, look in ((own, "randomized"), (unseen, "unseen")):
        folder.mkdir()
        (folder / SETTINGS_FILE).write_text(json.dumps({"config": look}))
    tied = {str(own): {3.0: 60.0, 30.0: 62.0}, str(unseen): {3.0: 42.0, 30.0: 40.0}}
    assert choose(tied) == (3.0, {3.0: 51.0, 30.0: 51.0})
    clear = {str(own): {3.0: 60.0, 30.0: 64.0}, str(unseen): {3.0: 42.0, 30.0: 40.0}}
    assert choose(clear)[0] == 30.0
    card = _copy_card("kuka", tmp_path)
    plain = yaml.safe_load(card.read_text())
    plain["estimator"]["fit"] = False
    card.write_text(yaml.safe_dump(plain, sort_keys=False))
    result = subprocess.run([sys.executable, SCRIPT, str(card), "--validation", str(own)], capture_output=True,
                            text=True, env=ENV, timeout=300)
    assert result.returncode == 1 and "not a fitted model" in result.stderr
    assert yaml.safe_load(card.read_text()) == plain
