"""Evaluation metrics, report and plots on hand-made examples whose answers are worked out by hand."""

import json
import math

import numpy as np
import pytest

from holo_pose_ros.evaluation import metrics
from holo_pose_ros.evaluation.plots import plot_add_curve, plot_frames_grid
from holo_pose_ros.evaluation.report import FrameResult, build_report, format_report, per_frame_add, write_report

REQUIRED_KEYS = {"n_frames", "n_not_found", "add_auc", "add_mean_mm", "add_median_mm", "add_below_mm",
                 "joint_error_deg", "rotation_error_deg", "depth_error_mm", "reproj_error_px", "keypoint_error_px", "fps",
                 "truncation", "apparent_size", "n_found_for_means"}


def rot_z(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# The grid has 10,000 thresholds 0, 1e-5, ..., 0.09999 m: 9,999 trapezoid intervals of 1e-5 m over a 0.1 m range.
def test_auc_of_perfect_estimates_is_one_interval_short_of_100():
    # acc = 1 everywhere: 9999 * 1e-5 / 0.1 * 100 = 99.99
    assert metrics.add_auc(np.zeros(5)) == pytest.approx(99.99, abs=1e-9)


def test_auc_of_constant_50mm_is_about_50():
    # acc = 0 below threshold index 5000 and 1 from it: half an interval rises, then 4999 full ones -> 49.995
    assert metrics.add_auc(np.full(4, 0.05)) == pytest.approx(49.995, abs=1e-9)


def test_frames_not_found_lower_auc_proportionally():
    found = np.array([True, True, True, False])
    assert metrics.add_auc(np.zeros(4), found) == pytest.approx(0.75 * 99.99, abs=1e-9)
    assert metrics.add_auc(np.zeros(4), np.zeros(4, bool)) == 0.0


def test_fraction_below_counts_not_found_as_failures():
    add = np.array([0.005, 0.01, 0.03, 0.05, 0.0])
    found = np.array([True, True, True, True, False])
    assert metrics.fraction_below(add, found) == {"10": 40.0, "20": 40.0, "40": 60.0, "60": 80.0}


def test_add_per_frame_by_hand():
    gt = np.zeros((1, 2, 3))
    pred = np.array([[[3.0, 4.0, 0.0], [0.0, 0.0, 1.0]]])  # distances 5 and 1
    np.testing.assert_allclose(metrics.add_per_frame(pred, gt), [3.0])


def test_joint_errors_degrees_and_millimetres():
    gt = np.zeros((2, 3))
    pred = np.array([[math.radians(2.0), -math.radians(4.0), 0.010],
                     [math.radians(4.0), 0.0, -0.030]])
    errors = metrics.joint_errors(pred, gt, ["revolute", "continuous", "prismatic"])
    np.testing.assert_allclose(errors["per_joint"], [3.0, 2.0, 20.0])
    assert errors["mean_deg"] == pytest.approx(2.5)
    assert errors["mean_mm"] == pytest.approx(20.0)
    assert "mean_mm" not in metrics.joint_errors(pred[:, :2], gt[:, :2], ["revolute", "revolute"])
    with pytest.raises(ValueError):
        metrics.joint_errors(pred, gt, ["revolute", "revolute", "fixed"])


def test_geodesic_rotation_error_of_30_degrees():
    R = rot_z(10.0) @ np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    errors = metrics.rotation_error_deg(np.stack([R, R]), np.stack([R @ rot_z(30.0), R]))
    np.testing.assert_allclose(errors, [30.0, 0.0], atol=1e-6)


def test_depth_and_reprojection_errors():
    np.testing.assert_allclose(metrics.depth_error_mm(np.array([1.0, 2.0]), np.array([1.01, 1.995])), [10.0, 5.0])
    gt = np.zeros((2, 3, 2))
    pred = np.array([[[3.0, 4.0], [0.0, 1.0], [100.0, 0.0]], [[1.0, 0.0]] * 3])
    inside = np.array([[True, True, False], [False, False, False]])
    err = metrics.reprojection_error_px(pred, gt, inside)
    assert err[0] == pytest.approx(3.0) and np.isnan(err[1])


def test_truncation_table_rows_and_counts():
    add = np.array([0.0, 0.05, np.nan, 0.02, 0.04])
    found = np.array([True, True, False, True, True])
    rows = metrics.truncation_table(add, found, np.array([7, 7, 7, 4, 4]), n_keypoints=7)
    assert [(r["n_in_image"], r["n_frames"], r["n_not_found"]) for r in rows] == [(4, 2, 0), (7, 3, 1)]
    assert rows[0]["add_mean_mm"] == pytest.approx(30.0)
    assert rows[1]["add_mean_mm"] == pytest.approx(25.0)
    assert rows[1]["add_auc"] == pytest.approx((99.99 + 49.995) / 3, abs=1e-9)
    with pytest.raises(ValueError):
        metrics.truncation_table(add, found, np.array([8, 7, 7, 4, 4]), n_keypoints=7)


def test_apparent_size_is_the_in_image_keypoints_box_and_the_size_table_bins_it():
    uv = np.array([[10.0, 20.0], [130.0, 60.0], [900.0, 900.0]])
    assert metrics.apparent_size_px(uv, np.array([True, True, False])) == pytest.approx(120.0)
    assert metrics.apparent_size_px(uv, np.array([True, False, False])) == 0.0  # one point has no extent
    add = np.array([0.01, 0.03, np.nan, 0.2, 0.05])
    found = np.array([True, True, False, True, True])
    rows = metrics.size_table(add, found, np.array([50.0, 120.0, 140.0, 120.0, 400.0]), (0.0, 100.0, 200.0, 300.0, np.inf))
    assert [(r["min_px"], r["n_frames"], r["n_not_found"]) for r in rows] == [(0.0, 1, 0), (100.0, 3, 1), (300.0, 1, 0)]
    assert rows[1]["add_mean_mm"] == pytest.approx(115.0)  # the found ones: 30 and 200 mm
    assert rows[1]["add_auc"] == pytest.approx(metrics.add_auc(add[1:4], found[1:4]))
    assert rows[0]["add_auc"] > rows[1]["add_auc"]
    with pytest.raises(ValueError):
        metrics.size_table(add, found, np.ones(5), (100.0, 50.0))


def frame(name: str, offset_m: float | None, n_in: int = 3) -> FrameResult:
    """A 3-keypoint, 2-joint frame; offset_m shifts every predicted keypoint along x (None: not found)."""
    gt = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0], [0.2, 0.0, 1.0]])
    found = offset_m is not None
    return FrameResult(
        name=name, found=found,
        pred_keypoints_3d=gt + [offset_m, 0.0, 0.0] if found else None, gt_keypoints_3d=gt,
        pred_joints=np.array([math.radians(1.0), 0.012]) if found else None, gt_joints=np.array([0.0, 0.01]),
        pred_R=rot_z(6.0) if found else None, gt_R=np.eye(3),
        pred_root_depth_m=1.004 if found else None, gt_root_depth_m=1.0,
        pred_uv=np.full((3, 2), 2.0) if found else None, gt_uv=np.zeros((3, 2)),
        in_image=np.arange(3) < n_in, seconds=0.05)


def test_build_report_keys_json_and_not_found_frames(tmp_path):
    results = [frame("a", 0.005), frame("b", 0.03), frame("c", None, n_in=1), frame("d", 0.05, n_in=0)]
    report = build_report(results, ["j1", "finger"], ["revolute", "prismatic"], ["k0", "k1", "k2"])
    assert set(report) == REQUIRED_KEYS | {"extra"}
    json.dumps(report, allow_nan=False)
    assert (report["n_frames"], report["n_not_found"], report["n_found_for_means"]) == (4, 1, 3)
    assert report["add_mean_mm"] == pytest.approx(85.0 / 3) and report["add_median_mm"] == pytest.approx(30.0)
    assert report["add_below_mm"] == pytest.approx({"10": 25.0, "20": 25.0, "40": 50.0, "60": 75.0})
    add, found = per_frame_add(results)
    assert report["add_auc"] == pytest.approx(0.75 * metrics.add_auc(add[found]), abs=1e-9)  # 1 of 4 missed
    joints = report["joint_error_deg"]
    assert joints["j1"] == pytest.approx(1.0) and joints["finger"] == pytest.approx(2.0)
    assert joints["mean"] == pytest.approx(1.0) and joints["units"]["finger"] == "mm"
    assert report["rotation_error_deg"]["mean"] == pytest.approx(6.0)
    assert report["depth_error_mm"]["median"] == pytest.approx(4.0)
    # frame "d" has no in-image keypoint: its NaN reprojection error leaves the mean
    assert report["reproj_error_px"]["mean"] == pytest.approx(math.sqrt(8.0))
    assert report["extra"]["n_frames_used"]["reproj_error"] == 2
    assert report["keypoint_error_px"] == pytest.approx({"k0": math.sqrt(8.0), "k1": math.sqrt(8.0), "k2": math.sqrt(8.0)})
    assert report["fps"] == pytest.approx(20.0)
    assert [r["n_in_image"] for r in report["truncation"]] == [0, 1, 3]
    assert report["truncation"][1]["add_mean_mm"] is None  # the only 1-keypoint frame was not found
    assert [(r["min_px"], r["n_frames"]) for r in report["apparent_size"]] == [(0.0, 4)]  # every true uv is (0, 0)
    write_report(report, tmp_path / "out" / "report.json")
    assert json.loads((tmp_path / "out" / "report.json").read_text()) == report
    assert "ADD AUC" in format_report(report) and "robot size px" in format_report(report)


def test_a_symmetric_joints_error_is_also_reported_modulo_its_period():
    """A hand whose roll is off by about half a turn reads ~180 deg in joint_error_deg but ~0 modulo its symmetry."""
    results = [frame("a", 0.0), frame("b", 0.0), frame("c", None)]
    results[0].pred_joints[0] = math.radians(181.0)  # the true value is 0: half a turn and 1 deg
    results[1].pred_joints[0] = math.radians(-100.0)  # 100 deg off, 80 deg modulo half a turn
    report = build_report(results, ["j1", "finger"], ["revolute", "prismatic"], ["k0", "k1", "k2"],
                          {"j1": math.pi})
    assert report["joint_error_deg"]["j1"] == pytest.approx((181.0 + 100.0) / 2)
    modulo = report["joint_error_modulo_symmetry_deg"]
    assert modulo["j1"] == pytest.approx((1.0 + 80.0) / 2) and modulo["period_deg"] == {"j1": pytest.approx(180.0)}
    assert "(40.50 modulo its 180 deg symmetry)" in format_report(report)
    assert "joint_error_modulo_symmetry_deg" not in build_report(results, ["j1", "finger"],
                                                                 ["revolute", "prismatic"], ["k0", "k1", "k2"])
    with pytest.raises(ValueError, match="'finger' is not a revolute"):
        build_report(results, ["j1", "finger"], ["revolute", "prismatic"], ["k0", "k1", "k2"], {"finger": 0.1})


def test_keypoint_error_is_each_keypoints_median_over_the_frames_where_it_is_in_the_image():
    gt = np.zeros((3, 3, 2))
    pred = gt.copy()
    pred[:, 0, 0] = [1.0, 2.0, 30.0]        # keypoint 0: 1, 2, 30 px -> median 2
    pred[:, 1, 1] = [4.0, 100.0, 6.0]       # keypoint 1: its 100 px frame has it outside the image -> median 5
    pred[:, 2] = 7.0                        # keypoint 2: never in the image -> NaN
    in_image = np.array([[True, True, False], [True, False, False], [True, True, False]])
    errors = metrics.keypoint_error_px(pred, gt, in_image)
    assert errors[:2] == pytest.approx([2.0, 5.0]) and np.isnan(errors[2])


def test_plots_write_png_files(tmp_path):
    plot_add_curve(np.array([0.01, 0.02, np.nan]), np.array([True, True, False]), tmp_path / "add.png", "test")
    images = [np.zeros((48, 64, 3), np.uint8) for _ in range(3)]
    gt = [np.array([[10.0, 10.0], [30.0, 20.0], [50.0, 40.0]])] * 3
    pred = [gt[0] + 2.0, None, gt[0] - 3.0]
    plot_frames_grid(images, pred, gt, [-1, 0, 1], tmp_path / "grid.png", titles=["a", "b", "c"])
    for name in ("add.png", "grid.png"):
        data = (tmp_path / name).read_bytes()
        assert data.startswith(b"\x89PNG") and len(data) > 1000
