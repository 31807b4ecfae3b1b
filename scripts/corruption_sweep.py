"""Corruption sweep of the data readers: damage copies of a generated DREAM folder and of its bags in every way a
disk, a copy or another tool can, run `holo-pose evaluate` / `holo-pose bag-eval` on each (as processes, as a
user does), and print what happened: good frames read, bad ones named (file + field) and skipped, or one clear
error naming the file when nothing can be read; never a traceback.

    python scripts/corruption_sweep.py [--frames 6] [--model panda] [--out runs/corruption] [--json sweep.json]

Exit status 1 when a case ends otherwise than expected (a traceback, a good frame lost, a bad one not named).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from holo_pose_ros.bags import IMAGE_TOPIC  # noqa: E402
from holo_pose_ros.data.generator import generate  # noqa: E402

DAMAGED = "000001"  # the frame every per-frame case damages (frame 0 stays good)


# -- DREAM folder damage: each edits a copy in place and returns the file it damaged ----------------------------------
def _json(folder: Path) -> Path:
    return folder / f"{DAMAGED}.json"


def _edit_json(folder: Path, edit: Callable[[dict], None]) -> Path:
    path = _json(folder)
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))  # json writes NaN as the bare NaN token, as some tools do
    return path


def truncated_json(folder: Path) -> Path:
    path = _json(folder)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    return path


def wrong_type(folder: Path) -> Path:
    return _edit_json(folder, lambda d: d["objects"][0].__setitem__("keypoints", "a string, not a list"))


def missing_key(folder: Path) -> Path:
    return _edit_json(folder, lambda d: d["objects"][0].pop("keypoints"))


def nan_values(folder: Path) -> Path:
    return _edit_json(folder, lambda d: d["objects"][0]["keypoints"][2].__setitem__("location", [float("nan")] * 3))


def _image(folder: Path) -> Path:
    return folder / f"{DAMAGED}.rgb.jpg"


def image_truncated(folder: Path) -> Path:
    path = _image(folder)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 4])
    return path


def image_zero_bytes(folder: Path) -> Path:
    _image(folder).write_bytes(b"")
    return _image(folder)


def image_wrong_size(folder: Path) -> Path:
    cv2.imwrite(str(_image(folder)), np.zeros((60, 80, 3), np.uint8))
    return _image(folder)


def image_not_an_image(folder: Path) -> Path:
    _image(folder).write_bytes(np.random.default_rng(0).bytes(5000))
    return _image(folder)


def names_do_not_pair(folder: Path) -> Path:
    """The damaged frame's image renamed away: a JSON without its image, and an image without its JSON."""
    _image(folder).rename(folder / "999999.rgb.jpg")
    return _json(folder)


def settings_missing(folder: Path) -> Path:
    (folder / "_camera_settings.json").unlink()
    return folder / "_camera_settings.json"


def settings_wrong(folder: Path) -> Path:
    path = folder / "_camera_settings.json"
    data = json.loads(path.read_text())
    data["camera_settings"][0]["intrinsic_settings"]["fx"] = "six hundred"
    path.write_text(json.dumps(data))
    return path


DREAM_CASES: dict[str, tuple[Callable[[Path], Path], str]] = {  # name -> (damage, expected: 'skip' | 'error')
    "truncated JSON": (truncated_json, "skip"),
    "wrong type": (wrong_type, "skip"),
    "missing key": (missing_key, "skip"),
    "NaN values": (nan_values, "skip"),
    "image truncated": (image_truncated, "skip"),
    "image zero bytes": (image_zero_bytes, "skip"),
    "image wrong size": (image_wrong_size, "skip"),
    "image not an image": (image_not_an_image, "skip"),
    "names do not pair": (names_do_not_pair, "skip"),
    "settings file missing": (settings_missing, "error"),
    "settings file wrong": (settings_wrong, "error"),
}


# -- bag damage -----------------------------------------------------------------------------------------------------
def _storage_file(bag: Path) -> Path:
    return next(p for p in bag.iterdir() if p.suffix in (".mcap", ".db3"))


def truncate_bag(bag: Path) -> Path:
    path = _storage_file(bag)
    path.write_bytes(path.read_bytes()[: int(path.stat().st_size * 0.6)])
    return path


def empty_bag(bag: Path) -> Path:
    path = _storage_file(bag)
    path.write_bytes(b"")
    return path


def rewrite_bag(bag: Path, keep: Callable[[str, int], bool], extra: Callable | None = None) -> Path:
    """Rewrite the (mcap) bag keeping the messages `keep(topic, index_on_topic)` accepts; `extra(writer, add)`
    may add more. Returns the bag folder."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer

    from holo_pose_ros.bags import jazzy_typestore

    typestore = jazzy_typestore()
    tmp = bag.with_name(bag.name + ".rewritten")
    with AnyReader([bag], default_typestore=typestore) as reader:
        writer = Writer(tmp, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.open()
        conns, counts, image_times = {}, {}, []
        for conn, t_ns, raw in reader.messages():
            i = counts[conn.topic] = counts.get(conn.topic, -1) + 1
            image_times += [t_ns] if conn.topic == IMAGE_TOPIC else []
            if not keep(conn.topic, i):
                continue
            if conn.topic not in conns:
                conns[conn.topic] = writer.add_connection(conn.topic, conn.msgtype, typestore=typestore)
            writer.write(conns[conn.topic], t_ns, raw)
        if extra is not None:
            extra(writer, typestore, image_times)
        writer.close()
    shutil.rmtree(bag)
    tmp.rename(bag)
    return bag


def camera_info_missing_first(bag: Path) -> Path:
    return rewrite_bag(bag, lambda topic, i: not (topic.endswith("camera_info") and i < 2))


def other_type_on_image_topic(bag: Path) -> Path:
    """A second connection on the image topic carrying std_msgs/String (another tool publishing there)."""
    def extra(writer, typestore, image_times):
        String = typestore.types["std_msgs/msg/String"]
        conn = writer.add_connection(IMAGE_TOPIC, "std_msgs/msg/String", typestore=typestore)
        for k, t_ns in enumerate(image_times):  # one between each two images
            writer.write(conn, t_ns + 1000, typestore.serialize_cdr(String(data=f"not an image {k}"),
                                                                    "std_msgs/msg/String"))
    return rewrite_bag(bag, lambda topic, i: True, extra)


BAG_CASES: dict[str, tuple[str, Callable[[Path], Path], str]] = {  # name -> (storage, damage, expected)
    "mcap truncated": ("mcap", truncate_bag, "skip_or_error"),   # rosbags needs the mcap footer: a clear error
    "sqlite3 truncated": ("sqlite3", truncate_bag, "skip_or_error"),
    "mcap zero bytes": ("mcap", empty_bag, "error"),
    "CameraInfo missing for the first frames": ("mcap", camera_info_missing_first, "skip"),
    "another type on the image topic": ("mcap", other_type_on_image_topic, "skip"),
}


# -- running the CLI ------------------------------------------------------------------------------------------------
@dataclass
class Outcome:
    case: str
    target: str                # evaluate | bag-eval
    damaged: str               # the damaged file, relative to the case folder
    expected: str              # skip | error | skip_or_error
    exit_status: int
    frames_read: int | None    # frames estimated (evaluate) / images read (bag-eval)
    skipped: int | None
    named: bool                # the damaged file (or its frame) is named in the output
    traceback: bool
    message: str               # the first line naming the problem
    ok: bool = False


IN_PROCESS = False  # --in-process: call holo_pose_ros.cli.main here (the test's mode: no interpreter start per case)


def _cli(args: list[str]) -> subprocess.CompletedProcess:
    """`holo-pose ARGS` as a process (what a user runs), or in this process with its output captured; an
    exception escaping main() is printed as the traceback a user would see."""
    if not IN_PROCESS:
        return subprocess.run([sys.executable, "-m", "holo_pose_ros.cli", *args], capture_output=True, text=True,
                              cwd=ROOT, timeout=900)
    import contextlib
    import io
    import logging
    import traceback

    from holo_pose_ros.cli import main as cli_main

    out, err = io.StringIO(), io.StringIO()
    handler = logging.StreamHandler(err)
    logging.getLogger().addHandler(handler)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                status = cli_main(args)
            except SystemExit as e:  # argparse
                status = e.code if isinstance(e.code, int) else 1
            except Exception:  # noqa: BLE001 - what escapes is what the sweep looks for
                traceback.print_exc()
                status = 1
    finally:
        logging.getLogger().removeHandler(handler)
    return subprocess.CompletedProcess(args, status, out.getvalue(), err.getvalue())


def _problem_line(text: str, needles: list[str]) -> str:
    for line in text.splitlines():
        if any(n in line for n in needles):
            return line.strip()[:200]
    return ""


def run_dream_case(name: str, damage, expected: str, clean: Path, work: Path, model: str, n_frames: int) -> Outcome:
    folder = work / "dream" / name.replace(" ", "_")
    shutil.copytree(clean, folder)
    damaged = damage(folder)
    report_path = folder.with_suffix(".report.json")
    run = _cli(["evaluate", "--model", model, "--data", str(folder), "--no-fit", "--quiet", "--out", str(report_path)])
    text = run.stdout + run.stderr
    needles = [damaged.name, DAMAGED]
    read = skipped = None
    if report_path.exists():
        report = json.loads(report_path.read_text())
        read, skipped = report["n_frames"], report.get("n_skipped", 0)
    outcome = Outcome(name, "evaluate", damaged.name, expected, run.returncode, read, skipped,
                      any(n in text for n in needles), "Traceback" in text, _problem_line(text, needles))
    if expected == "skip":
        outcome.ok = run.returncode == 0 and read == n_frames - 1 and skipped >= 1 and outcome.named
    else:
        outcome.ok = run.returncode != 0 and outcome.named and "error" in text
    outcome.ok &= not outcome.traceback
    return outcome


def run_bag_case(name: str, storage: str, damage, expected: str, clean: Path, work: Path, model: str,
                 n_frames: int) -> Outcome:
    bag = work / "bags" / name.replace(" ", "_")
    r = _cli(["dream-to-bag", str(clean), str(bag), "--storage", storage, "--quiet"])
    if r.returncode != 0:
        raise RuntimeError(f"dream-to-bag failed: {r.stderr}")
    damaged = damage(bag)
    out = bag.with_name(bag.name + ".estimates")
    run = _cli(["bag-eval", "--bag", str(bag), "--model", model, "--out", str(out), "--no-fit", "--quiet"])
    text = run.stdout + run.stderr
    read = skipped = None
    for line in run.stdout.splitlines():
        if " images: " in line and " skipped" in line:
            words = line.replace(",", "").split()
            read, skipped = int(words[0]), int(words[words.index("skipped;") - 1])
    needles = [damaged.name, "truncated", "CameraInfo", "ignored"]
    outcome = Outcome(name, "bag-eval", damaged.name, expected, run.returncode, read, skipped,
                      any(n in text for n in [damaged.name, str(damaged)]) or (read is not None and skipped > 0),
                      "Traceback" in text, _problem_line(text, needles))
    finished = run.returncode == 0 and read is not None
    if expected == "skip":  # the damaged messages skipped or ignored, and said so; the other images estimated
        outcome.ok = finished and (skipped >= 1 or "ignored" in text) and read - skipped >= n_frames - 2
    elif expected == "error":
        outcome.ok = run.returncode != 0 and damaged.name in text
    else:  # truncated: what can be read is, with a warning, or one clear error naming the file
        outcome.ok = (finished and "truncated" in text) or (run.returncode != 0 and damaged.name in text)
    outcome.ok &= not outcome.traceback
    return outcome


def format_table(outcomes: list[Outcome]) -> str:
    lines = ["| case | tool | damaged | expected | exit | read | skipped | named | traceback | ok | first line |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for o in outcomes:
        lines.append(f"| {o.case} | {o.target} | {o.damaged} | {o.expected} | {o.exit_status} | "
                     f"{'-' if o.frames_read is None else o.frames_read} | {'-' if o.skipped is None else o.skipped} | "
                     f"{'yes' if o.named else 'no'} | {'YES' if o.traceback else 'no'} | {'ok' if o.ok else 'FAIL'} | "
                     f"{o.message.replace('|', '/')} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=6, help="frames of the generated folder (>= 3)")
    parser.add_argument("--model", default="panda", help="model name or card")
    parser.add_argument("--out", default="runs/corruption", help="work folder (emptied first)")
    parser.add_argument("--json", default=None, help="also write the outcomes as JSON here")
    parser.add_argument("--only", default=None, choices=["dream", "bags"], help="run one half of the sweep")
    parser.add_argument("--in-process", action="store_true", help="run the CLI in this process (faster; tests)")
    args = parser.parse_args(argv)
    global IN_PROCESS
    IN_PROCESS = args.in_process
    work = Path(args.out)
    shutil.rmtree(work, ignore_errors=True)
    clean = work / "clean"
    generate("panda", args.frames, clean, seed=77, workers=1, width=320, height=240, progress=False)
    outcomes = []
    if args.only in (None, "dream"):
        for name, (damage, expected) in DREAM_CASES.items():
            outcomes.append(run_dream_case(name, damage, expected, clean, work, args.model, args.frames))
            print(f"{name}: {'ok' if outcomes[-1].ok else 'FAIL'}", flush=True)
    if args.only in (None, "bags"):
        for name, (storage, damage, expected) in BAG_CASES.items():
            outcomes.append(run_bag_case(name, storage, damage, expected, clean, work, args.model, args.frames))
            print(f"{name}: {'ok' if outcomes[-1].ok else 'FAIL'}", flush=True)
    print(format_table(outcomes))
    failed = [o.case for o in outcomes if not o.ok]
    print(f"{len(outcomes) - len(failed)}/{len(outcomes)} cases as expected" + (f"; failed: {failed}" if failed else ""))
    if args.json:
        Path(args.json).write_text(json.dumps([asdict(o) for o in outcomes], indent=1))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
