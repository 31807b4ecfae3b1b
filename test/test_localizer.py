"""The light localizer (issue 30): the whole-image pass of detection run 2D-only (presence and DREAM's keypoints
from their fit heatmaps; the default), optionally at a lower input than the crop's. At the crop's size it is the full pass's
2D output exactly, for both heads; at a lower size the shipped model still finds the robot and bounds it; its ONNX
export computes what torch computes; bad sizes and networks without fit heatmaps are refused."""

import numpy as np
import pytest
import torch

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import generate
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.geometry.crop import CROP_MARGIN, crop_box_from_keypoints
from holo_pose_ros.model.network import HolisticNet, load_model_config
from holo_pose_ros.model.onnx_runtime import OnnxNetwork, cached_export
from holo_pose_ros.model.weights import load_model
from holo_pose_ros.robots.kinematics import RobotModel
from small_model import SMALL

PYRAMID_SMALL = {**SMALL, "name": "test-small-pyramid", "head": "pyramid", "head_channels": 16, "segmentation": True,
                 "skip_connections": True}


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    folder = tmp_path_factory.mktemp("localizer_frames")
    generate("panda", 4, folder, seed=5151, workers=1, progress=False)
    reader = DreamReader(folder, "panda")
    return [(reader.load_image(f), f.K) for f in reader]


@pytest.mark.parametrize("config", [SMALL, PYRAMID_SMALL], ids=["deconv", "pyramid"])
def test_the_localize_pass_at_the_crop_size_is_the_full_passs_2d_output(config):
    robot = RobotModel("panda")
    torch.manual_seed(3)
    net = HolisticNet(load_model_config(config), robot).eval()
    S, N = net.cfg.input_size, robot.n_keypoints
    image = torch.rand(2, 3, S, S)
    K = torch.tensor([[S, 0.0, S / 2], [0.0, S, S / 2], [0.0, 0.0, 1.0]]).repeat(2, 1, 1)
    with torch.inference_mode():
        full, light = net(image, K), net.localize(image)
        lower = net.localize(torch.rand(2, 3, S // 2, S // 2))
    assert set(light) == {"presence_logit", "uv", "confidence"}
    torch.testing.assert_close(light["presence_logit"], full["presence_logit"])
    torch.testing.assert_close(light["uv"], full["fit_uv"][:, :N])
    torch.testing.assert_close(light["confidence"], full["fit_confidence"][:, :N])
    assert lower["uv"].shape == (2, N, 2) and lower["confidence"].shape == (2, N)
    border = 2.0 * 4  # a peak on the map's border decodes up to 1.5 cells (stride 4) beyond it
    assert float(lower["uv"].min()) > -border and float(lower["uv"].max()) < S // 2 + border  # px of the smaller input


def test_the_shipped_model_finds_and_bounds_the_robot_at_a_lower_input(frames):
    full = Estimator.from_model("panda", localize_size=0)
    same = Estimator.from_model("panda")  # the default: 2D-only at the crop's size
    light = Estimator.from_model("panda", localize_size=160)
    assert full.localizer is None and same.localize_size == full.size and light.localize_size == 160
    for image, K in frames:
        H, W = image.shape[:2]
        p_full, uv_full = full.localize(image, K)
        p_same, uv_same = same.localize(image, K)
        p_light, uv_light = light.localize(image, K)
        assert p_same == pytest.approx(p_full, abs=1e-6)
        np.testing.assert_allclose(uv_same, uv_full, atol=1e-3)
        assert p_light > 0.5
        a = crop_box_from_keypoints(uv_full, W, H, CROP_MARGIN)
        b = crop_box_from_keypoints(uv_light, W, H, CROP_MARGIN)
        assert abs(b[2] / a[2] - 1.0) < 0.25, (a, b)                      # the box's side
        assert np.linalg.norm((b[:2] + b[2] / 2) - (a[:2] + a[2] / 2)) < 0.15 * a[2], (a, b)  # and its centre
        assert light.estimate(image, K).found


def test_the_localizers_onnx_export_computes_what_torch_computes(small_model_card):
    net, _, _ = load_model(small_model_card)
    path = cached_export(net, small_model_card, 32)
    assert path != cached_export(net, small_model_card) and "localize32" in path.name
    session = OnnxNetwork(path)
    image = torch.rand(3, 3, 32, 32)  # batch of 3: dynamic
    with torch.inference_mode():
        expected = net.localize(image)
    got = session(image)
    assert set(got) == set(expected)
    for key in expected:
        np.testing.assert_allclose(got[key].numpy(), expected[key].numpy(), atol=1e-3, err_msg=key)
    with pytest.raises(ValueError, match="takes 1 inputs"):
        session(image, image)
    estimator = Estimator.from_model(small_model_card, backend="onnxruntime", localize_size=32)
    assert isinstance(estimator.localizer, OnnxNetwork)


def test_bad_localizer_sizes_and_networks_without_fit_heatmaps_are_refused(small_model_card):
    for size in (100, -32):
        with pytest.raises(ValueError, match="multiple of 32"):
            Estimator.from_model(small_model_card, localize_size=size)
    robot = RobotModel("panda")
    net = HolisticNet(load_model_config({**SMALL, "fit_heatmaps": False}), robot).eval()
    with pytest.raises(ValueError, match="no fit heatmaps"):
        net.localize(torch.rand(1, 3, 64, 64))
    with pytest.raises(ValueError, match="no fit heatmaps"):
        Estimator(net, robot, localize_size=32)
    assert Estimator(net, robot).localizer is None  # such a network localizes with its full pass
