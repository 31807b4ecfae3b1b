"""scripts/rescore_model.py on a copy of the shipped Panda model and three generated unseen-look frames: the card's
test section is rewritten with the depth diagnostics and the size and truncation tables, the rest of the card and
the weights are untouched; scripts/looks_table.py reads such cards into the README's table and rewrites only its
block; scripts/choose_tracked_search.py writes only a card's choice of the search on tracked frames."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

from holo_pose_ros.data.generator import generate
from holo_pose_ros.model.cards import file_sha256
from holo_pose_ros.resources import weights_dir

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "scripts"))

import looks_table  # noqa: E402


def shipped_copy(name: str, tmp_path: Path) -> tuple[Path, dict]:
    """A copy of shipped model `name` (card, weights, lifter) in tmp_path/models, and its card as shipped."""
    models = tmp_path / "models"
    models.mkdir()
    for suffix in (".yaml", ".safetensors", "_lifter.yaml", "_lifter.safetensors"):
        shutil.copy(weights_dir() / f"{name}{suffix}", models / f"{name}{suffix}")
    return models, yaml.safe_load((models / f"{name}.yaml").read_text())


def test_rescore_rewrites_only_the_test_section_with_the_depth_diagnostics(tmp_path):
    models, before = shipped_copy("panda", tmp_path)
    generate("panda", 3, tmp_path / "unseen", seed=4242, workers=1, progress=False, config="unseen")
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "rescore_model.py"), str(models / "panda.yaml"),
                          "--test", f"{tmp_path / 'unseen'}:unseen"], capture_output=True, text=True, cwd=ROOT,
                         timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    after = yaml.safe_load((models / "panda.yaml").read_text())
    assert list(after["test"]) == ["unseen"]  # only the looks asked for
    unseen = after["test"]["unseen"]
    assert unseen["n_frames"] == 3 and unseen["data"]["look"] == "unseen" and unseen["data"]["seed"] == 4242
    depth = unseen["depth_diagnostics"]
    assert set(depth["root_depth_error"]) == {"depthnet", "fit_no_prior", "shipped"}
    assert depth["root_depth_error"]["depthnet"]["n_frames"] >= 1
    assert sum(row["n_frames"] for row in unseen["apparent_size"]) == 3
    assert sum(row["n_frames"] for row in unseen["truncation"]) == 3
    assert {"feed-forward", "fitted", "fitted, known joints"} <= set(unseen["ablation"])
    assert after["domain_shift"]["look"] == "unseen" and after["domain_shift"]["add_auc"] == unseen["add_auc"]
    assert {k: v for k, v in after.items() if k not in ("test", "domain_shift")} == \
        {k: v for k, v in before.items() if k not in ("test", "domain_shift")}
    assert file_sha256(models / "panda.safetensors") == before["weights_sha256"]
    assert not list(models.glob("*.tmp"))
    whole, few, many = looks_table.truncation_cells(unseen["truncation"], 7)
    assert sum(int(c.split("(")[1].rstrip(")")) for c in (whole, few, many) if c != "-") == 3
    cells = looks_table.look_cells(unseen)
    assert cells[0].startswith(f"{unseen['add_auc']:.1f} / ")
    assert cells[2].count("/") == 2 and "-" != cells[2].split(" / ")[0]  # DepthNet's relative error is there


def test_looks_table_has_every_shipped_model_and_look_and_rewrites_only_its_block(tmp_path):
    lines = looks_table.table()
    rows = [line for line in lines[2:lines.index("")] if line.startswith("| `")]
    assert len(rows) == len(looks_table.MODELS) * len(looks_table.LOOKS)
    truncation = [line for line in lines[lines.index(""):] if line.startswith("| `")]
    assert len(truncation) == len(rows) and all(line.count("|") == 6 for line in truncation)
    assert all(line.count("|") == 7 for line in rows)
    panda_randomized = next(line for line in rows if line.startswith("| `panda` | randomized"))
    card = yaml.safe_load((weights_dir() / "panda.yaml").read_text())
    assert f"{card['test']['randomized']['add_auc']:.1f} / " in panda_randomized
    assert looks_table.look_cells(None) == ["-"] * 4
    assert looks_table.look_cells({"add_auc": 50.0, "add_mean_mm": 60.0})[1] == "- / - / - / -"
    rows_by_count = [{"n_in_image": 7, "n_frames": 3, "add_auc": 60.0}, {"n_in_image": 6, "n_frames": 1, "add_auc": 20.0},
                     {"n_in_image": 5, "n_frames": 1, "add_auc": 40.0}, {"n_in_image": 2, "n_frames": 2, "add_auc": 0.0}]
    assert looks_table.truncation_cells(rows_by_count, 7) == ["60.0 (3)", "30.0 (2)", "0.0 (2)"]
    page = tmp_path / "page.md"
    page.write_text(f"intro\n{looks_table.BEGIN}\nold table\n{looks_table.END}\noutro\n")
    looks_table.rewrite(page, lines)
    text = page.read_text()
    assert text.startswith("intro\n") and text.endswith("outro\n") and "old table" not in text
    assert panda_randomized in text


def test_choose_tracked_search_writes_the_choice_and_its_evidence_only(tmp_path):
    """scripts/choose_tracked_search.py on a copy of the shipped Kuka model (fitted by parts) and a short generated
    video: estimator.parts_tracked and its evidence are written, nothing else; a card that does not search by parts
    is refused with a message and left as it was."""
    models, before = shipped_copy("kuka", tmp_path)
    generate("kuka", 4, tmp_path / "video", seed=4243, workers=1, progress=False, config="video")
    script = [sys.executable, str(ROOT / "scripts" / "choose_tracked_search.py")]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = subprocess.run(script + [str(models / "kuka.yaml"), "--video", str(tmp_path / "video")],
                         capture_output=True, text=True, cwd=ROOT, timeout=600, env=env)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    after = yaml.safe_load((models / "kuka.yaml").read_text())
    chosen = after["estimator"]
    scores = chosen["tracking_validation"][str(tmp_path / "video")]
    assert chosen["tracking_chosen_on"] == [str(tmp_path / "video")]
    assert chosen["tracking_min_gain_auc"] == 1.0
    assert chosen["parts_tracked"] == (scores["by parts on every frame"]["add_auc"]
                                       > scores["by parts on untracked frames"]["add_auc"] + 1.0)
    kept = ("parts_tracked", "tracking_chosen_on", "tracking_validation", "tracking_min_gain_auc")
    assert {k: v for k, v in chosen.items() if k not in kept} == \
        {k: v for k, v in before["estimator"].items() if k not in kept}
    assert {k: v for k, v in after.items() if k != "estimator"} == {k: v for k, v in before.items() if k != "estimator"}
    plain = {**after, "estimator": {**after["estimator"], "parts": False}}
    (models / "kuka.yaml").write_text(yaml.safe_dump(plain, sort_keys=False))
    refused = subprocess.run(script + [str(models / "kuka.yaml"), "--video", str(tmp_path / "video")],
                             capture_output=True, text=True, cwd=ROOT, timeout=600, env=env)
    assert refused.returncode == 1 and "does not fit by parts" in refused.stderr
    assert yaml.safe_load((models / "kuka.yaml").read_text()) == plain
