"""The estimator node fuzzed through a real graph (holo_pose_ros/nodes/fuzz.py): the node as its own process on
the shared-memory profile, a few hundred seeded messages of every kind of wrongness, each valid frame right after
a wrong one. It must stay alive, answer every valid frame, and count in /diagnostics exactly what was sent; its log
must stay throttled (its throttle is tested in test_log_throttle.py). Plus the stream generator and the log
analysis."""

from __future__ import annotations

from collections import Counter

import numpy as np

from holo_pose_ros.nodes.estimator_node import LOG_PERIOD_S
from holo_pose_ros.nodes.fuzz import expected_counters, format_fuzz, fuzz_stream, log_stats, run_fuzz, unaccounted


def test_the_stream_is_deterministic_and_covers_every_kind():
    a, b = fuzz_stream(400, seed=3), fuzz_stream(400, seed=3)
    assert [(c.kind, c.expect, c.raw) for c in a] == [(c.kind, c.expect, c.raw) for c in b]
    assert [c.kind for c in fuzz_stream(400, seed=4)] != [c.kind for c in a]
    kinds = {c.kind for c in fuzz_stream(3000, seed=0)}
    for kind in ["Image: unsupported encoding", "Image: step too short", "Image: data shorter", "Image: data longer",
                 "Image: width 0", "Image: huge width/height", "Image: is_bigendian 2..255",
                 "Image: random field values", "Image: valid mono8", "Image: undecodable bytes",
                 "CameraInfo: fx NaN", "CameraInfo: fy inf", "CameraInfo: fx negative", "CameraInfo: K all zeros",
                 "CameraInfo: size of another camera", "CameraInfo: stamp backwards/equal"]:
        assert kind in kinds, kind
    expects = Counter(c.expect for c in a)
    assert {"answer", "image", "camera_info", "camera", "undeliverable"} <= set(expects), expects
    # every expected answer has its own (stamp, frame_id), and each comes right after something wrong
    keys = [c.key for c in a if c.expect == "answer"]
    assert len(keys) == len(set(keys))
    closing = [i for i, c in enumerate(a) if c.kind == "Image: valid frame (closes a round)" and i > 3]
    assert len(closing) > 50
    assert all(a[i - 1].kind == "CameraInfo: valid" for i in closing)
    assert all(any(c.expect not in ("answer", "camera") for c in a[i + 1:j]) for i, j in zip(closing, closing[1:]))


def test_log_stats_counts_lines_per_reason_and_period():
    lines = [f"[WARN] [{100 + t:.3f}] [holo_pose_estimator]: image error #{t}, skipped: data is {t} bytes"
             for t in (0.0, 1.0, 2.0, 6.0)] + ["", ">>> [rcutils|error_handling.c:108] rcutils_set_error_state()"]
    stats = log_stats("\n".join(lines), since=100.5)
    assert stats == {"lines": 3, "reasons": 1, "max_per_reason_per_period": 2, "other_lines": 1}


def test_the_node_survives_a_seeded_fuzz_and_counts_what_was_sent(small_model_card, tmp_path):
    # 150 ms after each message: on this busy CPU, 50 ms let ~0.2 % of the messages be replaced in the node's
    # depth-1 queue before its executor took them (scripts/fuzz_node.py reports those as "not received")
    result = run_fuzz(small_model_card, messages=200, seed=7, log=tmp_path / "estimator.log", gap_s=0.15)
    report = format_fuzz(result)
    assert result["alive"], report
    assert result["answered"] == result["answers_expected"] > 40, report
    assert result["counted"] == result["expected"], report
    assert unaccounted(result["counted"]) == 0, report
    assert result["log"]["max_per_reason_per_period"] <= 1, report
    assert result["log"]["lines"] <= result["log"]["reasons"] * (1 + result["stream_s"] / LOG_PERIOD_S), report
    assert expected_counters(fuzz_stream(200, 7))["frames_received"] == result["counted"]["frames_received"]
    assert np.isfinite(result["peak_rss_mb"]) and result["peak_rss_mb"] > 0
