"""The shipped models, loaded by name as users do: each finds its robot in rendered frames it never saw and says
"not found" on images without a robot. The ADD checks compare with an untrained network of the same configuration
on the same frames (metres off: about 2 m for Baxter, 15 m for the others; 80 px): they catch weights that do not
load or a broken pipeline; the per-robot bounds catch a regression. Neither is the accuracy target, which the
current CPU-trained weights are far from."""

import numpy as np
import pytest
import torch

from holo_pose_ros.data.backgrounds import random_background
from holo_pose_ros.data.dream import DreamReader, decode_image
from holo_pose_ros.data.generator import generate
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.evaluation.run import evaluate_folder
from holo_pose_ros.geometry.crop import crop_box_from_keypoints
from holo_pose_ros.model.network import HolisticNet
from holo_pose_ros.model.cards import shipped_models

SHIPPED = shipped_models()
N_FRAMES = 48  # 6 frames were noise (a model better on 600 held-out frames read 87 -> 100 mm on them)
REGRESSION_BOUND_MM = {"panda": 50.0, "kuka": 65.0, "baxter": 280.0}  # measured 43.3 / 56.0 / 251.4 mm on these
# frames (Panda run 14 at 224 px; run 13: 40.9, run 10: 46.4; before: 57.3 / 78.8 / 245.2, with the old crop box
# 71.8 / 70.1 / 288.8). Panda's bound went 45 -> 50 mm (the campaign issue's) on 6 December 2026: the pyramid224 run
# 9 model reads 45.4 mm here, these being photo-look frames, where it gave up 2 mm of held-out mean ADD (41 -> 43) for
# 59 mm on the unseen look (166 -> 107); docs/campaign.md. It tightens again as the shipped models improve.
UNSEEN_LOOK_BOUND_MM = {"panda": 150.0, "kuka": 160.0, "baxter": 500.0}  # mean ADD on 48 frames of the unseen look
# (never trained on), measured 129.7 / 139.0 / 441.3 mm on 6 December 2026 (Panda run 9; run 8 read 202.1 there):
# the look that matters guards against regressions next to the training looks' bounds above
MAX_NOT_FOUND = {"baxter": 1}  # of N_FRAMES, 0 for the others. Baxter misses frame 000022 on this VM with the
# code and weights of the session before too (fa3abad: 1 not found, 240.6 mm); its held-out rate is 4-5 of 300


def test_every_robot_has_shipped_weights():
    assert SHIPPED == ["baxter", "kuka", "panda"]


@pytest.fixture(scope="module", params=SHIPPED)
def estimator(request):
    return Estimator.from_model(request.param)


def test_shipped_model_finds_its_robot_in_unseen_frames(tmp_path, estimator):
    robot = estimator.robot.name
    generate(robot, N_FRAMES, tmp_path, seed=31337, workers=1, config="photo", progress=False)
    report, _, _ = evaluate_folder(estimator, DreamReader(tmp_path, robot), progress=False)
    torch.manual_seed(0)
    untrained = Estimator(HolisticNet(estimator.net.cfg, estimator.robot), estimator.robot, min_confidence=0.0)
    baseline, _, _ = evaluate_folder(untrained, DreamReader(tmp_path, robot), progress=False)
    assert report["n_not_found"] <= MAX_NOT_FOUND.get(robot, 0)
    assert report["add_mean_mm"] < min(1000.0, 0.2 * baseline["add_mean_mm"])
    assert report["add_mean_mm"] < REGRESSION_BOUND_MM.get(robot, 1000.0)
    assert report["reproj_error_px"]["median"] < 0.75 * baseline["reproj_error_px"]["median"]


def test_shipped_model_holds_its_accuracy_on_the_unseen_look(tmp_path, estimator):
    """On frames of the unseen look (config/generate/unseen.yaml, which no training config names) the shipped model
    finds nearly every robot and stays under its regression bound."""
    robot = estimator.robot.name
    generate(robot, N_FRAMES, tmp_path, seed=31337, workers=1, config="unseen", progress=False)
    report, _, _ = evaluate_folder(estimator, DreamReader(tmp_path, robot), progress=False)
    assert report["n_not_found"] <= 4
    assert report["add_mean_mm"] < UNSEEN_LOOK_BOUND_MM[robot]


def test_deployed_crop_follows_the_training_crop_recipe(tmp_path, estimator):
    """The crop the estimator finds by itself frames the robot as training framed its views (DREAM's keypoints
    grown by the crop margin): a box of every fit keypoint was a quarter larger and shrank the robot in the crop."""
    robot = estimator.robot.name
    generate(robot, 16, tmp_path, seed=4242, workers=1, progress=False)
    ratios, offsets = [], []
    for frame in DreamReader(tmp_path, robot):
        detection = estimator.detect(decode_image(frame.image_path), frame.K)
        assert detection is not None
        recipe = crop_box_from_keypoints(frame.keypoints_2d, frame.width, frame.height)
        ratios.append(detection.box[2] / recipe[2])
        offsets.append(np.linalg.norm(detection.box[:2] - recipe[:2] + (detection.box[2] - recipe[2]) / 2) / recipe[2])
    assert 0.9 < np.median(ratios) < 1.12, ratios
    assert np.median(offsets) < 0.06, offsets


def test_images_without_a_robot_are_not_found(estimator):
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    images = [random_background(np.random.default_rng(100 + i), 480, 640).astype(np.uint8) for i in range(6)]
    images.append(np.full((480, 640, 3), 128, np.uint8))
    images.append(np.zeros((480, 640, 3), np.uint8))   # a covered lens (Panda's presence head says 0.6: the fit refuses)
    for image in images:
        estimate = estimator.estimate(image, K)
        assert not estimate.found and estimate.confidence < 0.5 and estimate.joints is None
