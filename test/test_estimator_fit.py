"""The estimator's fitting stage with the shipped Panda model and its lifter, on frames it never saw: the fit can
only lower the reprojection cost of its starts, `known_joints` fixes the joints, `fit=False` is the paper's
feed-forward estimate, and tracking adds the previous frame as a start."""

import numpy as np
import pytest

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import generate
from holo_pose_ros.estimator import METHODS, Estimator
from holo_pose_ros.geometry.camera import in_image


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fit_frames")
    generate("panda", 4, folder, seed=4242, workers=1, progress=False)
    reader = DreamReader(folder, "panda")
    return [(reader.load_image(f), f) for f in reader]


@pytest.fixture(scope="module")
def estimator():
    return Estimator.from_model("panda", min_confidence=0.0, fit=True)


def test_the_shipped_panda_model_has_heatmaps_and_a_lifter(estimator):
    assert estimator.lifter is not None and estimator.net.cfg.fit_heatmaps
    assert estimator.lifter.robot.n_fit_keypoints == estimator.robot.n_fit_keypoints


def test_a_card_that_names_no_lifter_fits_with_the_robots_shipped_lifter(tmp_path, estimator, frames):
    """A training run's card names no lifter: evaluating it must fit as its validation did, not lose the lifter."""
    import shutil

    import yaml

    from holo_pose_ros.model.cards import read_card

    card_path, card = read_card("panda")
    shutil.copy(card_path.parent / card["weights"], tmp_path / card["weights"])
    run_card = {k: v for k, v in card.items() if k != "lifter"}
    (tmp_path / "best.yaml").write_text(yaml.safe_dump(run_card, sort_keys=False))
    run = Estimator.from_model(tmp_path / "best.yaml", min_confidence=0.0, fit=True)
    assert run.lifter is not None
    image, frame = frames[0]
    ours, shipped = run.estimate_methods(image, frame.K), estimator.estimate_methods(image, frame.K)
    assert ours["lifter"].found
    np.testing.assert_allclose(ours["fitted"].T_cam_base, shipped["fitted"].T_cam_base, atol=1e-9)


def test_the_default_method_is_the_one_the_card_validated():
    from holo_pose_ros.model.cards import read_card

    validated = read_card("panda")[1]["estimator"]
    assert Estimator.from_model("panda").fit == validated["fit"]
    assert Estimator.from_model("panda", fit=not validated["fit"]).fit == (not validated["fit"])
    assert set(validated["validation"]) >= {"feed-forward", "lifter", "fitted"}
    for robot in ("panda", "kuka"):
        assert Estimator.from_model(robot).parts == bool(read_card(robot)[1]["estimator"].get("parts", False))
    assert Estimator.from_model("kuka", parts=False).parts is False


def test_the_cards_fit_settings_reach_the_fitter_under_the_callers(tmp_path):
    """A card's `estimator.fit_config` (fit settings its validation chose, e.g. the depth prior's weight) is what the
    fitter runs with; a `fit_config` given by the caller wins key by key; a card without one fits with
    config/fitting.yaml."""
    import shutil

    import yaml

    from holo_pose_ros.fitting.solver import load_fitting_config
    from holo_pose_ros.model.cards import read_card

    defaults = load_fitting_config(None)
    card_path, card = read_card("kuka")
    shutil.copy(card_path.parent / card["weights"], tmp_path / card["weights"])
    shutil.copy(card_path.parent / card["lifter"], tmp_path / card["lifter"])
    lifter_weights = yaml.safe_load((card_path.parent / card["lifter"]).read_text())["weights"]
    shutil.copy(card_path.parent / lifter_weights, tmp_path / lifter_weights)
    estimator = {k: v for k, v in card["estimator"].items() if k != "fit_config"}
    plain = {**card, "estimator": estimator}
    chosen = {**card, "estimator": {**estimator, "fit_config": {"depth_prior_weight": 4.0, "iterations": 7}}}
    (tmp_path / "plain.yaml").write_text(yaml.safe_dump(plain, sort_keys=False))
    (tmp_path / "chosen.yaml").write_text(yaml.safe_dump(chosen, sort_keys=False))
    assert Estimator.from_model(tmp_path / "plain.yaml").fitter.config == defaults
    config = Estimator.from_model(tmp_path / "chosen.yaml").fitter.config
    assert (config["depth_prior_weight"], config["iterations"]) == (4.0, 7)
    assert {k: v for k, v in config.items() if k not in ("depth_prior_weight", "iterations")} == \
        {k: v for k, v in defaults.items() if k not in ("depth_prior_weight", "iterations")}
    config = Estimator.from_model(tmp_path / "chosen.yaml", fit_config={"depth_prior_weight": 20.0}).fitter.config
    assert (config["depth_prior_weight"], config["iterations"]) == (20.0, 7)


def test_tracked_frames_search_by_parts_only_where_the_card_chose_it():
    """A tracked frame also starts from the previous frame's fit: it is searched by parts only with
    `parts_tracked`, which the card's tracking validation sets (scripts/choose_tracked_search.py)."""
    from holo_pose_ros.fitting.parts import PartsFitter
    from holo_pose_ros.model.cards import read_card

    for robot in ("panda", "kuka"):
        chosen = read_card(robot)[1]["estimator"]
        estimator = Estimator.from_model(robot)
        assert estimator.parts_tracked == bool(chosen.get("parts_tracked", True))
        assert set(chosen["tracking_validation"][chosen["tracking_chosen_on"][0]]) == {
            "by parts on every frame", "by parts on untracked frames"}
    afresh_only = Estimator.from_model("panda", parts=True, parts_tracked=False)
    assert isinstance(afresh_only.search(), PartsFitter)
    assert afresh_only.search(from_previous=True) is afresh_only.fitter
    everywhere = Estimator.from_model("panda", parts=True, parts_tracked=True)
    assert isinstance(everywhere.search(from_previous=True), PartsFitter)
    plain = Estimator.from_model("panda", parts=False)
    assert plain.search() is plain.fitter and plain.search(from_previous=True) is plain.fitter


def test_tracked_frames_search_by_parts_every_nth_frame(frames):
    """With `parts_tracked`, a tracked frame is searched by parts every `parts_tracked_every`-th frame (the fit
    config) and fitted plainly between; an untracked frame always searches. The same image over and over is a
    tracked stream of a robot standing still."""
    from holo_pose_ros.fitting.parts import PartsFitter

    estimator = Estimator.from_model("panda", min_confidence=0.0, fit=True, parts=True, parts_tracked=True,
                                     tracking=True, fit_config={"parts_tracked_every": 3})
    assert [isinstance(estimator.search(True, n), PartsFitter) for n in (None, 0, 1, 2, 5)] == [
        True, False, False, True, True]
    assert isinstance(estimator.search(False, 0), PartsFitter)
    image, frame = frames[0]
    plain_since_search = []
    for _ in range(7):
        assert estimator.estimate(image, frame.K).found
        plain_since_search.append(estimator._plain_since_search)
    assert plain_since_search == [0, 1, 2, 0, 1, 2, 0]
    every_frame = Estimator.from_model("panda", parts=True, parts_tracked=True, fit_config={"parts_tracked_every": 1})
    assert all(isinstance(every_frame.search(True, n), PartsFitter) for n in (0, 1, 7))


def test_the_search_by_parts_never_ends_above_the_plain_fit(frames):
    """The same detections fitted plainly and searched by parts (fitting/parts.py): the search's reprojection cost
    is never higher."""
    from holo_pose_ros.fitting.parts import PartsFitter

    plain = Estimator.from_model("panda", min_confidence=0.0, fit=True, parts=False)
    searched = Estimator.from_model("panda", min_confidence=0.0, fit=True, parts=True)
    assert isinstance(searched.search(), PartsFitter) and searched.search() is searched.search()
    for image, frame in frames[:2]:
        a, b = plain.estimate(image, frame.K), searched.estimate(image, frame.K)
        np.testing.assert_array_equal(a.detected_2d, b.detected_2d)
        w = plain.fit_weights(a.detected_confidence)
        costs = plain.fitter.cost(a.detected_2d, w, frame.K, np.stack([a.joints, b.joints]),
                                  np.stack([a.T_cam_base, b.T_cam_base]))
        assert costs[1] <= costs[0] * (1 + 1e-9)


def test_fit_never_raises_the_reprojection_cost_of_its_starts(estimator, frames):
    for image, frame in frames:
        r = estimator.estimate_methods(image, frame.K, None, METHODS)
        fitted, ff = r["fitted"], r["feed-forward"]
        assert fitted.found and ff.found and fitted.fit_rms_px is not None and np.isfinite(fitted.fit_rms_px)
        w = estimator.fit_weights(fitted.detected_confidence)
        lower, upper = estimator.robot.lower.cpu().numpy(), estimator.robot.upper.cpu().numpy()
        # the paper's heads may leave the joint limits; the fit starts from their projection onto them
        ff_q = np.clip(ff.joints, lower, upper)
        costs = estimator.fitter.cost(fitted.detected_2d, w, frame.K, np.stack([fitted.joints, ff_q, r["lifter"].joints]),
                                      np.stack([fitted.T_cam_base, ff.T_cam_base, r["lifter"].T_cam_base]))
        assert costs[0] <= costs[1] * (1 + 1e-6) and costs[0] <= costs[2] * (1 + 1e-6)
        # the limits are float32 here, float64 in the fit: equal to within float32 rounding
        assert (fitted.joints >= lower - 1e-6).all() and (fitted.joints <= upper + 1e-6).all()
        assert "fit" in fitted.timings_ms and "lifter" in fitted.timings_ms


def test_known_joints_fit_only_the_pose(estimator, frames):
    image, frame = frames[0]
    estimate = estimator.estimate(image, frame.K, known_joints=frame.joints)
    np.testing.assert_array_equal(estimate.joints, frame.joints)
    free = estimator.estimate(image, frame.K)
    assert not np.array_equal(free.joints, frame.joints)


def test_fit_false_gives_the_feed_forward_estimate(frames):
    image, frame = frames[1]
    plain = Estimator.from_model("panda", min_confidence=0.0, fit=False).estimate(image, frame.K)
    ff = Estimator.from_model("panda", min_confidence=0.0, fit=True).estimate_methods(image, frame.K, None, ("feed-forward",))
    np.testing.assert_allclose(plain.joints, ff["feed-forward"].joints)
    np.testing.assert_allclose(plain.T_cam_base, ff["feed-forward"].T_cam_base)
    assert plain.fit_rms_px is None and "fit" not in plain.timings_ms


def test_tracking_starts_the_fit_from_the_previous_frame(frames):
    estimator = Estimator.from_model("panda", min_confidence=0.0, tracking=True, fit=True)
    image, frame = frames[2]
    first = estimator.estimate(image, frame.K)
    second = estimator.estimate(image, frame.K)
    assert first.found and not first.tracked and second.found and second.tracked
    assert "localize" not in second.timings_ms
    # the previous frame's answer is a start: on the same image, the tracked fit explains it at least as well
    assert second.fit_rms_px <= first.fit_rms_px * 1.5
    # a tracked frame starts from it and the paper heads' estimate: the lifter runs only on frames fitted afresh,
    # unless asked for on tracked frames too (tracked_lifter_starts) or for its own estimate
    assert "lifter" in first.timings_ms and "lifter" not in second.timings_ms
    with_lifter = Estimator.from_model("panda", min_confidence=0.0, tracking=True, fit=True, tracked_lifter_starts=2)
    with_lifter.estimate(image, frame.K)
    assert "lifter" in with_lifter.estimate(image, frame.K).timings_ms
    assert estimator.estimate_methods(image, frame.K, None, ("lifter", "fitted"))["lifter"].found


def test_the_depth_prior_pulls_the_fit_towards_the_paper_heads_depth(frames):
    """With `depth_prior` the fitted robot's depth (the prior's: config depth_prior_on) lies nearer the
    feed-forward estimate's."""
    def mean_depth(est, e):
        return est.fitter.prior_depth(e.joints, e.T_cam_base)

    gaps = {}
    for prior in (False, True):
        est = Estimator.from_model("panda", min_confidence=0.0, fit=True, depth_prior=prior)
        gaps[prior] = []
        for image, frame in frames:
            r = est.estimate_methods(image, frame.K, None, ("feed-forward", "fitted"))
            gaps[prior].append(abs(mean_depth(est, r["fitted"]) - mean_depth(est, r["feed-forward"])))
    assert np.mean(gaps[True]) < np.mean(gaps[False])
    assert max(gaps[True]) < 0.2


def test_unknown_methods_are_refused(estimator, frames):
    image, frame = frames[0]
    with pytest.raises(ValueError, match="unknown estimation methods"):
        estimator.estimate_methods(image, frame.K, None, ("magic",))


def test_a_cached_detection_gives_the_estimate_of_its_image(estimator, frames):
    image, frame = frames[1]
    direct = estimator.estimate_methods(image, frame.K, None, ("feed-forward", "fitted"))
    detection = estimator.detect(image, frame.K)
    cached = estimator.estimate_detection(detection, frame.K, None, ("feed-forward", "fitted"))
    for method in ("feed-forward", "fitted"):
        assert cached[method].found
        np.testing.assert_allclose(cached[method].joints, direct[method].joints, atol=1e-6)
        np.testing.assert_allclose(cached[method].T_cam_base, direct[method].T_cam_base, atol=1e-6)
    nothing = estimator.estimate_detection(None, frame.K, None, ("fitted",))["fitted"]
    assert not nothing.found and nothing.confidence == 0.0
    with pytest.raises(ValueError, match="unknown estimation methods"):
        estimator.estimate_detection(detection, frame.K, None, ("magic",))


def test_evaluate_ablation_reports_every_method_on_the_same_frames(tmp_path, capsys):
    import json

    from holo_pose_ros.cli import main

    generate("panda", 3, tmp_path / "frames", seed=777, workers=1, progress=False)
    assert main(["evaluate", "--model", "panda", "--data", str(tmp_path / "frames"), "--ablation", "--quiet",
                 "--out", str(tmp_path / "ablation.json")]) == 0
    reports = json.loads((tmp_path / "ablation.json").read_text())
    assert list(reports) == [*METHODS, "fitted, known joints"]
    for report in reports.values():
        assert report["n_frames"] == 3 and report["kp2d_fit_median_px"] > 0
        per_keypoint = report["kp2d_dream_median_px_per_keypoint"]   # the network's, one per DREAM keypoint
        assert len(per_keypoint) == 7 and all(v is None or v >= 0 for v in per_keypoint)
        assert list(report["keypoint_error_px"]) == ["panda_link0", *[f"panda_link{i}" for i in (2, 3, 4, 6, 7)], "panda_hand"]
    assert reports["fitted, known joints"]["joint_error_deg"]["mean"] == 0.0
    printed = capsys.readouterr().out
    assert "| fitted |" in printed and "fit keypoints" in printed and "2D error, network   panda_link0" in printed


def test_without_off_image_evidence_keypoints_outside_the_image_weigh_nothing(estimator, frames):
    """Keypoints moved into the crop's padding (beyond the image border) change today's fit; with
    off_image_evidence=False the fit is exactly the one in which they have no confidence at all."""
    import dataclasses

    image, frame = frames[2]
    detection = estimator.detect(image, frame.K)
    W, H = detection.image_size
    assert (W, H) == (image.shape[1], image.shape[0])
    moved = detection.uv.copy()
    outside = np.argsort(-detection.confidence)[:6]  # the most confident ones: their pull is the largest
    moved[outside] = [-40.0, H / 2]
    pushed = dataclasses.replace(detection, uv=moved)
    silenced = dataclasses.replace(pushed, confidence=np.where(np.isin(np.arange(len(moved)), outside), 0.0,
                                                               detection.confidence))
    fit = lambda d: estimator.estimate_detection(d, frame.K, None, ("fitted",))["fitted"]  # noqa: E731
    kept = fit(pushed)
    estimator.off_image_evidence = False
    try:
        gated, reference = fit(pushed), fit(silenced)
    finally:
        estimator.off_image_evidence = True
    np.testing.assert_allclose(gated.joints, reference.joints, atol=1e-9)
    assert np.abs(kept.joints - gated.joints).max() > 1e-3


def test_fit_keypoints_the_fit_puts_out_of_view_lose_their_confidence_and_the_frame_is_fitted_again(tmp_path):
    """On truncated frames (the truncated look: the robot cut by the image border) the fit keypoints that the first
    fit puts outside the image or within in_view_margin_px of its border weigh 0 in a second fit, from the first
    fit and its starts; the estimate reports exactly that evidence, and its cost there is no higher than the first
    fit's. With the margin negative the step is off and the estimate is the first fit's."""
    generate("panda", 3, tmp_path, seed=77, workers=1, config="truncated", progress=False)
    reader = DreamReader(tmp_path, "panda")
    off = Estimator.from_model("panda", min_confidence=0.0, fit=True, fit_config={"in_view_margin_px": -1.0})
    on = Estimator.from_model("panda", min_confidence=0.0, fit=True)
    margin = on.fitter.config["in_view_margin_px"]
    assert margin > 0
    refitted = 0
    for frame in reader:
        image = reader.load_image(frame)
        H, W = image.shape[:2]
        detection = off.detect(image, frame.K)
        first = off.estimate_detection(detection, frame.K, None, ("fitted",))["fitted"]
        assert "in_view" not in first.timings_ms
        uv = on.fitter.project(first.joints, first.T_cam_base, frame.K)
        out = ~in_image(uv, W, H, margin_px=margin)
        second = on.estimate_detection(detection, frame.K, None, ("fitted",))["fitted"]
        if not (out & (on.fit_weights(detection.confidence) > 0)).any():
            np.testing.assert_allclose(second.T_cam_base, first.T_cam_base, atol=1e-12)
            continue
        refitted += 1
        assert "in_view" in second.timings_ms
        np.testing.assert_array_equal(second.detected_confidence, np.where(out, 0.0, detection.confidence))
        w = on.fit_weights(second.detected_confidence)
        costs = on.fitter.cost(detection.uv, w, frame.K, np.stack([second.joints, first.joints]),
                               np.stack([second.T_cam_base, first.T_cam_base]))
        assert costs[0] <= costs[1] * (1 + 1e-9)
    assert refitted >= 2  # truncated frames: the step ran


@pytest.mark.parametrize("robot", ["panda", "kuka", "baxter"])
def test_feed_forward_pose_is_the_paper_heads_forward_kinematics(robot):
    """The estimator's numpy forward kinematics of the heads (joints, root pose [R | t]) gives the base pose that
    model/network.py add_kinematics (pytorch-kinematics, what training uses) gives, also with known joints."""
    import torch

    from holo_pose_ros.geometry.rotation import rot6d_to_matrix
    from holo_pose_ros.model.network import add_kinematics

    estimator = Estimator.from_model(robot, min_confidence=0.0)
    model = estimator.robot
    rng = np.random.default_rng(7)
    q = torch.from_numpy(rng.uniform(model.lower.numpy(), model.upper.numpy(), (1, model.n_joints))).float()
    out = {"joints": q, "R": rot6d_to_matrix(torch.randn(1, 6)), "t": torch.tensor([[0.1, -0.2, 2.0]]),
           "depth": torch.tensor([2.0]), "keypoint_confidence": torch.rand(1, model.n_keypoints)}
    ours = estimator._kinematics(out, None, {})
    reference = add_kinematics(model, dict(out))["T_cam_base"][0].double().numpy()
    np.testing.assert_allclose(ours["T_cam_base"], reference, atol=1e-5)
    known = rng.uniform(model.lower.numpy(), model.upper.numpy())
    ours = estimator._kinematics(out, known, {})
    reference = add_kinematics(model, {**out, "joints": torch.from_numpy(known)[None].float()})["T_cam_base"][0]
    np.testing.assert_allclose(ours["joints"], known)
    np.testing.assert_allclose(ours["T_cam_base"], reference.double().numpy(), atol=1e-5)
