"""The holistic network's modules, its training signal, the weights format and the estimator, on real
components (pretrained EfficientNet-Lite0, real URDF FK, rendered views)."""

import numpy as np
import pytest
import torch

from holo_pose_ros.data.generator import load_generator_config
from holo_pose_ros.data.training import RenderedViews, SampleConfig
from holo_pose_ros.estimator import Estimator
from holo_pose_ros.model.heads import DepthHead, reference_depth, soft_argmax_3d
from holo_pose_ros.model.network import HolisticNet, add_kinematics, load_model_config
from holo_pose_ros.model.weights import load_model, save_model
from holo_pose_ros.robots.kinematics import RobotModel
from holo_pose_ros.train.losses import supervised_losses, total_loss
from small_model import SMALL

WEIGHTS = {"joints": 1.0, "rotation": 1.0, "translation": 1.0, "depth": 1.0, "kp2d_reg": 10.0, "kp3d_reg": 10.0,
           "kp2d_fk": 10.0, "kp3d_fk": 10.0, "presence": 0.5}


@pytest.fixture(scope="module")
def robot():
    return RobotModel("panda")


@pytest.fixture(scope="module")
def views():
    cfg = SampleConfig(64, mode_probabilities=(0.6, 0.2, 0.2))
    dataset = RenderedViews("panda", cfg, load_generator_config("randomized"), seed=5, length=8)
    return [dataset[i] for i in range(8)]


def test_soft_argmax_of_a_peaked_volume_gives_the_peak():
    prob = torch.zeros(1, 2, 8, 16, 16)
    prob[0, 0, 5, 3, 11] = 1.0
    prob[0, 1] = 1.0 / prob[0, 1].numel()
    out = soft_argmax_3d(prob, crop_size=64, depth_range_m=1.6)
    assert torch.allclose(out["uv"][0, 0], torch.tensor([(11 + 0.5) * 4 - 0.5, (3 + 0.5) * 4 - 0.5]))
    assert torch.isclose(out["dz"][0, 0], torch.tensor((5.5 / 8 - 0.5) * 1.6))
    assert torch.isclose(out["confidence"][0, 0], torch.tensor(1.0))
    assert torch.allclose(out["uv"][0, 1], torch.tensor([31.5, 31.5]))  # a flat volume: the centre
    assert out["confidence"][0, 1] < 0.05


def test_reference_depth_and_depth_head():
    K = torch.tensor([[[400.0, 0, 96], [0, 900.0, 96], [0, 0, 1]]])
    d_c = reference_depth(K, 192, 1.0)
    assert torch.isclose(d_c, torch.tensor([600.0 / 192]))   # sqrt(fx fy A_real / A_box)
    head = DepthHead(16, lambda0=0.7)
    assert torch.isclose(head(torch.randn(1, 16), d_c), 0.7 * d_c)  # zero-initialized: lambda starts at lambda_0


def test_network_shapes_and_units(robot, views):
    torch.manual_seed(0)  # the initial residuals are small but random: independent of which tests ran before
    net = HolisticNet(load_model_config(SMALL), robot).eval()
    batch = torch.stack([v["image"] for v in views[:2]]), torch.stack([v["K_crop"] for v in views[:2]])
    with torch.no_grad():
        out = add_kinematics(robot, net(*batch))
    N, J, M = robot.n_keypoints, robot.n_joints, robot.n_fit_keypoints
    shapes = {"depth": (2,), "uv": (2, N, 2), "dz": (2, N), "keypoint_confidence": (2, N), "keypoints_reg": (2, N, 3),
              "t": (2, 3), "joints": (2, J), "rot6d": (2, 6), "R": (2, 3, 3), "presence_logit": (2,),
              "keypoints_fk": (2, N, 3), "T_cam_base": (2, 4, 4), "heatmap_logits": (2, M, 16, 16),
              "fit_uv": (2, M, 2), "fit_confidence": (2, M)}
    assert {k: tuple(v.shape) for k, v in out.items() if k in shapes} == shapes
    assert (out["depth"] > 0).all() and torch.allclose(out["t"], out["keypoints_reg"][:, robot.root_index])
    assert torch.allclose(out["keypoints_reg"][:, :, 2] - out["depth"][:, None], out["dz"], atol=1e-5)  # metres
    # regression starts near the neutral pose (the last layer's small random init: within 0.1 rad, not +-pi)
    assert torch.allclose(out["joints"][0], robot.neutral, atol=0.1)
    assert ((out["uv"] >= -0.5) & (out["uv"] <= 63.5)).all()           # crop pixels
    beyond = 1.5 * 64 / 16                                            # a peak on the border may decode past it
    assert ((out["fit_uv"] >= -0.5 - beyond) & (out["fit_uv"] <= 63.5 + beyond)).all()
    assert ((out["fit_confidence"] >= 0) & (out["fit_confidence"] <= 1)).all()


def test_fk_of_the_true_state_reproduces_the_true_keypoints(robot, views):
    crops = [v for v in views if int(v["mode"]) != 2]
    truth = {"joints": torch.stack([v["joints"] for v in crops]), "R": torch.stack([v["R_root"] for v in crops]),
             "t": torch.stack([v["t_root"] for v in crops])}
    out = add_kinematics(robot, truth)
    assert torch.allclose(out["keypoints_fk"], torch.stack([v["keypoints_3d"] for v in crops]), atol=1e-4)
    base = out["T_cam_base"][:, :3, 3]
    assert torch.allclose(base, out["keypoints_fk"][:, 0], atol=1e-4)  # panda_link0 is the base


def test_rendered_views_are_consistent(views):
    from holo_pose_ros.geometry.camera import project

    for v in views:
        uv = project(v["keypoints_3d"].double().numpy(), v["K_crop"].double().numpy())
        assert np.allclose(uv, v["uv"].numpy(), atol=1e-3)
        assert v["image"].shape == (3, 64, 64) and 0 <= float(v["image"].min()) and float(v["image"].max()) <= 1
        assert float(v["presence"]) == float(int(v["mode"]) != 2)


def test_a_short_training_run_lowers_the_loss(robot, views):
    torch.manual_seed(0)
    net = HolisticNet(load_model_config(SMALL), robot).train()
    batch = {k: torch.stack([v[k] for v in views]) for k in views[0]}
    optimizer = torch.optim.AdamW(net.parameters(), lr=2e-3)
    losses = []
    for _ in range(25):
        out = add_kinematics(robot, net(batch["image"], batch["K_crop"]))
        loss = total_loss(supervised_losses(out, batch, net.joint_mid, net.joint_half, 64), WEIGHTS)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert np.isfinite(losses).all()
    assert np.mean(losses[-5:]) < 0.7 * np.mean(losses[:3]), losses


def test_weights_round_trip_and_estimator(tmp_path, robot, views):
    net = HolisticNet(load_model_config(SMALL), robot).eval()
    card = save_model(net, "panda", tmp_path / "small", {"training": {"note": "test"}})
    loaded, loaded_robot, meta = load_model(card)
    assert meta["training"]["note"] == "test" and loaded_robot.name == "panda"
    x, K = views[0]["image"][None], views[0]["K_crop"][None]
    with torch.no_grad():
        a, b = net(x, K), loaded(x, K)
    assert all(torch.allclose(a[k], b[k]) for k in a)
    estimator = Estimator(loaded, loaded_robot, min_confidence=0.0)
    image = np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    K_img = np.array([[150.0, 0, 80], [0, 150.0, 60], [0, 0, 1]])
    est = estimator.estimate(image, K_img)
    assert est.found and est.joints.shape == (robot.n_joints,) and est.keypoints_2d.shape == (robot.n_keypoints, 2)
    assert np.allclose(est.T_cam_base[3], [0, 0, 0, 1]) and {"localize", "estimate", "total"} <= set(est.timings_ms)
    known = estimator.estimate(image, K_img, known_joints=robot.neutral.numpy() + 0.1)
    assert np.allclose(known.joints, robot.neutral.numpy() + 0.1)
    for bad_image, bad_K in [(image[..., 0], K_img), (image.astype(np.float32), K_img), (image, np.zeros((3, 3))),
                             (image, K_img * np.nan)]:
        with pytest.raises(ValueError):
            estimator.estimate(bad_image, bad_K)


def test_the_papers_full_configuration_builds_and_runs(robot):
    cfg = load_model_config("full")
    net = HolisticNet(cfg, robot).eval()
    assert net.depth_backbone is not None  # DepthNet has its own backbone, as in the paper
    S = cfg.input_size
    K = torch.tensor([[[400.0, 0, S / 2], [0, 400.0, S / 2], [0, 0, 1]]])
    with torch.no_grad():
        out = net(torch.rand(1, 3, S, S), K)
    assert out["uv"].shape == (1, robot.n_keypoints, 2) and out["depth"].shape == (1,)
    assert sum(p.numel() for p in net.parameters()) > 30e6


def test_a_model_config_with_a_base_changes_only_the_fields_it_lists():
    lite, lite224 = load_model_config("lite").to_dict(), load_model_config("lite224").to_dict()
    assert {k for k in lite if lite[k] != lite224[k]} == {"name", "input_size", "heatmap_size"}
    assert (lite224["input_size"], lite224["heatmap_size"]) == (224, 56)
    assert load_model_config(lite224) == load_model_config("lite224")  # a card's full dict loads as it was saved
    with pytest.raises(ValueError, match="unknown model config"):
        load_model_config({"base": "no-such-model"})


PYRAMID_SMALL = {**SMALL, "name": "test-small-pyramid", "head": "pyramid", "head_channels": 16, "segmentation": True,
                 "skip_connections": True}


def test_rendered_views_carry_the_robot_foreground_mask(robot, views):
    """The segmentation target is the robot's own pixels: most in-view keypoints of the robot (joint origins,
    inside its links) lie on or within a pixel of it (a distractor may hide a few), and negatives have none."""
    on_mask = []
    for v in views:
        mask = v["mask"].numpy()
        assert mask.shape == (64, 64) and mask.dtype == bool
        if int(v["mode"]) == 2:
            assert not mask.any()
            continue
        grown = np.zeros_like(mask)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                grown |= np.roll(np.roll(mask, dy, 0), dx, 1)
        uv = np.rint(v["uv"].numpy()).astype(int)
        inside = v["visible"].numpy() & (uv >= 0).all(1) & (uv < 64).all(1)
        on_mask += list(grown[uv[inside, 1], uv[inside, 0]])
    assert len(on_mask) > 10 and np.mean(on_mask) > 0.8, on_mask


def test_the_pyramid_head_gives_every_output_at_its_stride_and_learns_the_mask(robot, views):
    """pyramid224's head (FPN-lite): the same outputs as the deconvolution head, the fit heatmaps and the mask at
    stride 4, the 3D volume at stride 8; a few steps of the mask and coordinate losses lower them."""
    torch.manual_seed(0)
    net = HolisticNet(load_model_config({**PYRAMID_SMALL, "heatmap_size": 16}), robot)
    batch = {k: torch.stack([v[k] for v in views]) for k in views[0]}
    M = robot.n_fit_keypoints
    with torch.no_grad():
        out = net.eval()(batch["image"], batch["K_crop"])
    assert out["heatmap_logits"].shape == (8, M, 16, 16) and out["mask_logits"].shape == (8, 1, 16, 16)
    assert out["fit_uv"].shape == (8, M, 2) and out["uv"].shape == (8, robot.n_keypoints, 2)
    net.train()
    optimizer = torch.optim.AdamW(net.parameters(), lr=3e-3)
    weights = {"mask": 1.0, "fit_coord": 1.0, "heatmap": 1.0}
    history = []
    for _ in range(30):
        terms = supervised_losses(add_kinematics(robot, net(batch["image"], batch["K_crop"])), batch, net.joint_mid,
                                  net.joint_half, 64)
        optimizer.zero_grad()
        total_loss(terms, weights).backward()
        optimizer.step()
        history.append({k: float(terms[k].detach()) for k in weights})
    assert history[-1]["mask"] < 0.8 * history[0]["mask"], history
    assert history[-1]["fit_coord"] < history[0]["fit_coord"], history
    with pytest.raises(ValueError, match="stride 4"):
        HolisticNet(load_model_config({**PYRAMID_SMALL, "heatmap_size": 8}), robot)


def test_a_network_with_a_mask_gives_the_fit_its_silhouette(robot):
    """A segmentation network's estimator asked for the silhouette builds its fitter with the robot's surface, its
    detections carry the mask in image pixels (foreground inside the crop, none outside it), and the silhouette
    changes the fit; by default (measured to cost AUC, config/silhouette_sweep.yaml) it is off; asking a network
    without a mask for a silhouette is an error."""
    torch.manual_seed(0)
    net = HolisticNet(load_model_config({**SMALL, "segmentation": True}), robot).eval()
    torch.nn.init.zeros_(net.keypoint_head.mask_out.weight)
    torch.nn.init.constant_(net.keypoint_head.mask_out.bias, 3.0)     # every crop pixel is robot
    image = np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    K_img = np.array([[150.0, 0, 80], [0, 150.0, 60], [0, 0, 1]])
    assert not Estimator(net, robot, min_confidence=0.0, fit=True).silhouette
    with_mask = Estimator(net, robot, min_confidence=0.0, fit=True, silhouette=True)
    assert with_mask.silhouette
    detection = with_mask.detect(image, K_img)
    x0, y0, side = detection.box
    assert detection.mask.shape == (120, 160) and detection.mask.any()
    rows, cols = np.nonzero(detection.mask)
    assert cols.min() >= x0 - 1 and cols.max() <= x0 + side + 1 and rows.min() >= y0 - 1 and rows.max() <= y0 + side + 1
    fitted = with_mask.estimate_detection(detection, K_img, methods=("fitted",))["fitted"]
    plain = Estimator(net, robot, min_confidence=0.0, fit=True, silhouette=False)
    unmasked = plain.estimate_detection(detection, K_img, methods=("fitted",))["fitted"]
    assert np.isfinite(fitted.T_cam_base).all()
    assert not np.allclose(fitted.T_cam_base, unmasked.T_cam_base)
    with pytest.raises(ValueError, match="no robot mask"):
        Estimator(HolisticNet(load_model_config(SMALL), robot).eval(), robot, silhouette=True)
