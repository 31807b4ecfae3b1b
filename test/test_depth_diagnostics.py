"""The depth and scale diagnostics of `holo-pose evaluate` (evaluation/depth.py): the radial scale estimator and the
signed-error summary on hand-made points whose answers are known, then the shipped Panda model on frames it never
saw, through the command line, as a user runs it."""

import json
import math

import numpy as np
import pytest

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import generate
from holo_pose_ros.evaluation.depth import (
    DEPTH_SOURCES,
    MIN_SCALE_KEYPOINTS,
    SCALE_ROWS,
    radial_scale,
    scale_summary,
    signed_error_summary,
)

TRUE_PX = np.array([[100.0, 200.0], [300.0, 180.0], [220.0, 400.0], [150.0, 320.0], [260.0, 260.0]])
CENTRE_PX = TRUE_PX.mean(axis=0)


def test_noise_free_points_have_scale_one():
    assert radial_scale(TRUE_PX, TRUE_PX, CENTRE_PX) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("s", [0.5, 0.97, 1.0, 1.25])
def test_points_scaled_about_the_centre_give_that_scale(s):
    assert radial_scale(CENTRE_PX + s * (TRUE_PX - CENTRE_PX), TRUE_PX, CENTRE_PX) == pytest.approx(s, abs=1e-12)


def test_points_shrunk_towards_the_centroid_give_less_than_one():
    rng = np.random.default_rng(5)
    shrunk = TRUE_PX + 0.2 * (CENTRE_PX - TRUE_PX) + rng.normal(0.0, 1.0, TRUE_PX.shape)  # 20 % inwards, 1 px noise
    assert 0.75 < radial_scale(shrunk, TRUE_PX, CENTRE_PX) < 0.85


def test_a_shift_of_every_point_leaves_the_scale_about_their_own_centroid_alone():
    assert radial_scale(TRUE_PX + [7.0, -3.0], TRUE_PX, CENTRE_PX) == pytest.approx(1.0, abs=1e-12)


def test_too_few_points_or_no_spread_give_no_scale():
    few = TRUE_PX[:MIN_SCALE_KEYPOINTS - 1]
    assert math.isnan(radial_scale(few, few, CENTRE_PX))
    same = np.repeat(CENTRE_PX[None], 4, axis=0)
    assert math.isnan(radial_scale(same + 1.0, same, CENTRE_PX))


def test_signed_error_summary_by_hand():
    true_m = np.array([1.0, 2.0, 1.5, 1.0, np.nan])
    pred_m = np.array([1.01, 1.98, 1.53, np.nan, 1.2])  # +10, -20, +30 mm; the last two frames have no pair
    summary = signed_error_summary(pred_m, true_m)
    assert summary["n_frames"] == 3
    assert summary["median_mm"] == pytest.approx(10.0)
    assert summary["mean_mm"] == pytest.approx(20.0 / 3)
    assert summary["abs_median_mm"] == pytest.approx(20.0)
    assert summary["relative_median_percent"] == pytest.approx(1.0)  # +1 %, -1 %, +2 %
    assert signed_error_summary(np.array([np.nan]), np.array([1.0])) == {
        "n_frames": 0, "median_mm": None, "mean_mm": None, "abs_median_mm": None, "relative_median_percent": None}


def test_scale_summary_leaves_unmeasured_frames_out():
    scales = np.concatenate([np.linspace(0.9, 1.1, 11), [np.nan, np.nan]])
    summary = scale_summary(scales, np.array([1.0, 2.0, 9.0]))
    assert summary["n_frames"] == 11
    assert summary["median"] == pytest.approx(1.0)
    assert (summary["p10"], summary["p90"]) == pytest.approx((0.92, 1.08))
    assert summary["error_median_px"] == pytest.approx(2.0)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """Five rendered Panda frames (the randomized look) the shipped model never saw."""
    out = tmp_path_factory.mktemp("depth_frames")
    generate("panda", 5, out, seed=77, workers=1, progress=False)
    return out


def test_evaluate_reports_the_depth_diagnostics(folder, tmp_path, capsys):
    from holo_pose_ros.cli import main

    assert main(["evaluate", "--model", "panda", "--data", str(folder), "--quiet", "--out",
                 str(tmp_path / "report.json")]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    section = report["depth_diagnostics"]
    assert section["shipped_method"] == "fitted"
    depth = section["root_depth_error"]
    assert list(depth) == list(DEPTH_SOURCES) and list(section["keypoint_scale"]) == list(SCALE_ROWS)
    for source, row in depth.items():
        assert row["n_frames"] == 5, source
        assert all(math.isfinite(row[k]) for k in ("median_mm", "mean_mm", "abs_median_mm", "relative_median_percent"))
    for name in ("detected", "detected_confident", "fit_no_prior", "shipped"):
        row = section["keypoint_scale"][name]
        assert row["n_frames"] == 5 and 0.8 < row["p10"] <= row["median"] <= row["p90"] < 1.2, name
        assert 0.0 < row["error_median_px"] < 20.0, name
    # the shipped rows are the report's own estimate, measured the same way
    assert depth["shipped"]["abs_median_mm"] == pytest.approx(report["depth_error_mm"]["median"], abs=1e-6)
    assert section["add_auc"]["shipped"] == pytest.approx(report["add_auc"], abs=1e-9)
    # the depth prior changes the fit: without it the robot lands elsewhere
    assert abs(depth["fit_no_prior"]["mean_mm"] - depth["shipped"]["mean_mm"]) > 1.0
    assert section["add_auc"]["fit_no_prior"] != pytest.approx(section["add_auc"]["shipped"], abs=1e-6)
    printed = capsys.readouterr().out
    assert "fit, no depth prior" in printed and "2D keypoint scale" in printed and "shipped (fitted)" in printed


def test_the_fit_without_prior_is_the_estimator_built_without_it(folder):
    from holo_pose_ros.estimator import Estimator

    estimator = Estimator.from_model("panda", min_confidence=0.0, fit=True)
    frame = next(iter(DreamReader(folder, "panda")))
    detection = estimator.detect(DreamReader(folder, "panda").load_image(frame), frame.K)
    switched = estimator.estimate_detection(detection, frame.K, None, ("fitted",), depth_prior=False)["fitted"]
    shipped = estimator.estimate_detection(detection, frame.K, None, ("fitted",))["fitted"]
    estimator.depth_prior = False
    built_without = estimator.estimate_detection(detection, frame.K, None, ("fitted",))["fitted"]
    np.testing.assert_array_equal(switched.joints, built_without.joints)
    np.testing.assert_array_equal(switched.T_cam_base, built_without.T_cam_base)
    assert not np.allclose(switched.T_cam_base, shipped.T_cam_base)


def test_the_ablation_carries_the_same_section(folder):
    from holo_pose_ros.estimator import Estimator
    from holo_pose_ros.evaluation.run import evaluate_methods, format_ablation

    reports = evaluate_methods(Estimator.from_model("panda"), DreamReader(folder, "panda"), limit=2, progress=False,
                               known_joints=False)
    section = reports["fitted"]["depth_diagnostics"]
    assert all(r["depth_diagnostics"] == section for r in reports.values())
    assert section["add_auc"]["shipped"] == pytest.approx(reports["fitted"]["add_auc"], abs=1e-9)
    assert section["root_depth_error"]["depthnet"]["n_frames"] == 2
    assert "fit, no depth prior" in format_ablation(reports)
    without = evaluate_methods(Estimator.from_model("panda"), DreamReader(folder, "panda"), limit=1, progress=False,
                               known_joints=False, depth_diagnostics=False)
    assert "depth_diagnostics" not in without["fitted"]


def test_a_tracking_evaluation_has_them_only_when_asked_and_then_refuses(folder):
    from holo_pose_ros.estimator import Estimator
    from holo_pose_ros.evaluation.run import evaluate_folder

    estimator = Estimator.from_model("panda", tracking=True)
    with pytest.raises(ValueError, match="untracked frames"):
        evaluate_folder(estimator, DreamReader(folder, "panda"), progress=False, depth_diagnostics=True)
    report, _, _ = evaluate_folder(estimator, DreamReader(folder, "panda"), limit=1, progress=False)
    assert "depth_diagnostics" not in report
