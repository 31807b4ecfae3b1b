"""The unseen generator look (config/generate/unseen.yaml), a stand-in for a new camera: no training config names
it, it renders valid DREAM frames that differ from the training looks in their pixels but not their geometry, each
of its post-processing steps does what it says, the shading modes change the shading, and configs without the new
keys draw exactly what they drew before. Real renders (Mesa EGL), no mocks."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import (
    DISTRACTOR_LABEL, _post_process, generate, jpeg_roundtrip, load_generator_config, motion_blur, resample,
    shot_noise, tone_curve, vignette,
)
from holo_pose_ros.data.render import Light, Material, Primitive, Renderer, Shading
from holo_pose_ros.geometry.camera import look_at
from holo_pose_ros.resources import config_dir

SEED, N_FRAMES = 7, 3


def string_values(node) -> list[str]:
    """Every string anywhere in a parsed YAML document (mapping keys and values, list items), depth first."""
    if isinstance(node, str):
        return [node]
    if isinstance(node, dict):
        return [s for key, value in node.items() for s in string_values(key) + string_values(value)]
    if isinstance(node, list):
        return [s for item in node for s in string_values(item)]
    return []


def names_unseen(text: str) -> bool:
    """Whether a config string refers to the unseen look: its name, or a path whose file is unseen.yaml."""
    return "unseen" in text.lower() or Path(text).name == "unseen.yaml"


def test_no_training_config_names_the_unseen_look():
    configs = sorted((config_dir() / "train").glob("*.yaml")) + [config_dir() / "lifter.yaml"]
    assert len(configs) >= 4 and (config_dir() / "generate" / "unseen.yaml").is_file()
    assert names_unseen("unseen") and names_unseen("/x/config/generate/unseen.yaml")
    for path in configs:
        named = [s for s in string_values(yaml.safe_load(path.read_text())) if names_unseen(s)]
        assert not named, f"{path.name} names the unseen look: {named}"


@pytest.fixture(scope="module")
def looks(tmp_path_factory) -> dict[str, DreamReader]:
    """The same seed's frames under the three looks (Panda, one worker)."""
    readers = {}
    for look in ("unseen", "photo", "randomized"):
        out = tmp_path_factory.mktemp(look)
        generate("panda", N_FRAMES, out, seed=SEED, workers=1, config=look, progress=False)
        readers[look] = DreamReader(out, "panda")
    return readers


def test_unseen_frames_are_valid_dream_frames(looks):
    reader = looks["unseen"]
    assert len(reader) == N_FRAMES and not reader.problems
    for frame in reader:
        image, mask = reader.load_image(frame), reader.load_mask(frame)
        assert image.shape == (480, 640, 3) and image.std() > 10
        assert mask.shape == (480, 640) and ((mask > 0) & (mask < DISTRACTOR_LABEL)).sum() > 500


def test_unseen_look_changes_pixels_not_geometry(looks):
    """Same seed: the joints of photo (drawn first), and randomized's camera (the geometry sections are its own);
    the robot pixels agree wherever no distractor covers them, and the images differ clearly in statistics."""
    unseen, photo, randomized = (list(looks[k]) for k in ("unseen", "photo", "randomized"))
    cfg, randomized_cfg = load_generator_config("unseen"), load_generator_config("randomized")
    assert cfg["intrinsics"] == randomized_cfg["intrinsics"] and cfg["camera"] == randomized_cfg["camera"]
    for u, p, r in zip(unseen, photo, randomized):
        np.testing.assert_array_equal(u.joints, p.joints)
        np.testing.assert_array_equal(u.joints, r.joints)
        np.testing.assert_allclose(u.K, r.K)
        np.testing.assert_allclose(u.T_cam_base, r.T_cam_base, atol=1e-9)
        np.testing.assert_allclose(u.keypoints_2d, r.keypoints_2d, atol=1e-6)
        mask_u, mask_r = looks["unseen"].load_mask(u), looks["randomized"].load_mask(r)
        clear = (mask_u != DISTRACTOR_LABEL) & (mask_r != DISTRACTOR_LABEL)
        assert (mask_u[clear] == mask_r[clear]).mean() > 0.999
    images = {k: [looks[k].load_image(f).astype(np.float32) for f in looks[k]] for k in ("unseen", "photo")}
    assert np.mean([np.abs(u - p).mean() for u, p in zip(*images.values())]) > 20  # grey levels
    # its heavy JPEG leaves 8x8 blocks that photo's (the folder's own quality-95 write) does not
    unseen_blocks, photo_blocks = ([blockiness(image) for image in images[k]] for k in ("unseen", "photo"))
    assert min(unseen_blocks) > 1.6 and max(photo_blocks) < 1.4, (unseen_blocks, photo_blocks)


def blockiness(image: np.ndarray) -> float:
    """Mean absolute step between columns across JPEG's 8-pixel block boundaries over the mean step within blocks
    (about 1 for an image without block artefacts)."""
    steps = np.abs(np.diff(image.mean(-1), axis=1))
    return float(steps[:, 7::8].mean() / np.delete(steps, np.s_[7::8], axis=1).mean())


# --- each post-processing step on a small synthetic image ------------------------------------------------------

def test_vignette_darkens_corners_not_centre():
    image = np.full((61, 81, 3), 200.0, np.float32)
    out = vignette(image, 0.4)
    assert out[30, 40, 0] == pytest.approx(200.0, abs=0.5)
    for corner in [(0, 0), (0, -1), (-1, 0), (-1, -1)]:
        assert out[corner][0] == pytest.approx(200.0 * 0.6, abs=0.5)
    assert (np.diff(out[30, 40:, 0]) <= 0).all()  # falls off monotonically away from the centre


def test_heavy_jpeg_makes_8x8_blocks():
    """A smooth ramp at quality 10: the steps between 8-pixel blocks are much larger than within them."""
    y, x = np.mgrid[0:64, 0:96].astype(np.float32)
    image = np.clip(np.stack([x * 2.0 + y, 60 + y * 1.5, 200 - x], -1), 0, 255).astype(np.uint8)
    out = jpeg_roundtrip(image, 10)
    assert out.shape == image.shape and out.dtype == np.uint8
    out = out.astype(np.float32)
    assert np.abs(out - image).mean() > 1.0
    assert blockiness(out) > 2.0 > 1.2 > blockiness(image)


def test_downscale_upscale_removes_high_frequencies():
    rng = np.random.default_rng(0)
    fine = rng.uniform(0, 255, (64, 64, 3)).astype(np.float32)  # white noise: energy at every frequency
    for interpolation in (1, 2):  # cv2.INTER_LINEAR, cv2.INTER_CUBIC
        out = resample(fine, 2.0, interpolation)
        assert out.shape == fine.shape
        spectrum_in = np.abs(np.fft.fftshift(np.fft.fft2(fine[..., 0] - fine[..., 0].mean())))
        spectrum_out = np.abs(np.fft.fftshift(np.fft.fft2(out[..., 0] - out[..., 0].mean())))
        r = np.hypot(*np.mgrid[-32:32, -32:32])
        high = r > 20  # above about 0.6 of the Nyquist frequency, which a factor-2 sensor cannot hold
        assert spectrum_out[high].mean() < 0.15 * spectrum_in[high].mean()
        assert abs(out.mean() - fine.mean()) < 2.0  # the image's brightness stays


def test_tone_curve_maps_mid_grey():
    grey = np.full((2, 2, 3), 127.5, np.float32)
    assert tone_curve(grey, 2.0, 0.0)[0, 0, 0] == pytest.approx(63.75, abs=0.01)
    assert tone_curve(grey, 0.5, 0.0)[0, 0, 0] == pytest.approx(255 * 0.5 ** 0.5, abs=0.01)
    assert tone_curve(grey, 1.0, 0.8)[0, 0, 0] == pytest.approx(127.5, abs=0.01)  # S curve keeps mid-grey
    ramp = np.linspace(0, 255, 256, dtype=np.float32)[None, :, None]
    s = tone_curve(ramp, 1.0, 1.0)[0, :, 0]
    assert s[64] < 64 and s[192] > 192 and (np.diff(s) >= 0).all()  # darker shadows, brighter highlights
    assert s[0] == pytest.approx(0.0) and s[-1] == pytest.approx(255.0)


def test_shot_noise_grows_with_signal():
    image = np.concatenate([np.full((200, 100, 3), 50.0), np.full((200, 100, 3), 200.0)], 1).astype(np.float32)
    out = shot_noise(image, 0.8, np.random.default_rng(1)) - image
    dark, bright = out[:, :100].var(), out[:, 100:].var()
    assert dark == pytest.approx(0.8 * 50, rel=0.1) and bright == pytest.approx(0.8 * 200, rel=0.1)
    assert abs(out.mean()) < 0.5


def test_motion_blur_smears_a_dot_along_its_direction():
    image = np.zeros((41, 41, 3), np.float32)
    image[20, 20] = 255.0
    along_x = motion_blur(image, 9.0, 0.0)[..., 0]
    rows, cols = np.nonzero(along_x > 1.0)
    assert set(rows) == {20} and cols.min() == 16 and cols.max() == 24  # 9 px long, centred, horizontal
    assert along_x.sum() == pytest.approx(255.0, rel=1e-4)  # energy kept
    diagonal = motion_blur(image, 9.0, np.pi / 4)[..., 0]
    rows, cols = np.nonzero(diagonal > 1.0)
    assert np.corrcoef(rows, cols)[0, 1] > 0.95  # down-right: y grows with x (image rows point down)


def test_post_process_runs_every_new_step_of_the_unseen_look():
    cfg = load_generator_config("unseen")["post"]
    y, x = np.mgrid[0:96, 0:128].astype(np.float32)
    image = np.stack([x * 2, y * 2, 255 - x - y], -1).astype(np.float32)
    plain = {k: cfg[k] for k in ("colour_gain", "blur_probability", "blur_sigma_px", "noise_sigma")}
    out = _post_process(image, cfg, np.random.default_rng(3))
    assert out.dtype == np.uint8 and out.shape == image.shape
    assert np.abs(out.astype(np.float32) - _post_process(image, plain, np.random.default_rng(3))).mean() > 5
    np.testing.assert_array_equal(out, _post_process(image, cfg, np.random.default_rng(3)))  # deterministic


def old_post_process_replay(image: np.ndarray, cfg: dict, rng: np.random.Generator) -> np.ndarray:
    """The draws the post-processing made before the optional steps existed, in their order: gain (3 uniform),
    blur coin, blur sigma when the coin says so, noise sigma, noise normals; and the image they give."""
    import cv2

    image = image * rng.uniform(cfg["colour_gain"][0], cfg["colour_gain"][1], 3).astype(np.float32)
    if rng.random() < cfg["blur_probability"]:
        image = cv2.GaussianBlur(image, (0, 0), rng.uniform(*cfg["blur_sigma_px"]))
    sigma = rng.uniform(*cfg["noise_sigma"])
    if sigma > 0:
        image = image + rng.normal(0.0, sigma, image.shape).astype(np.float32)
    return np.clip(image, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("look", ["randomized", "photo"])
def test_configs_without_new_keys_draw_and_render_as_before(look):
    cfg = load_generator_config(look)["post"]
    image = np.random.default_rng(0).uniform(0, 255, (48, 64, 3)).astype(np.float32)
    for seed in range(6):  # both sides of the blur coin
        rng, replay = np.random.default_rng(seed), np.random.default_rng(seed)
        out = _post_process(image, cfg, rng)
        np.testing.assert_array_equal(out, old_post_process_replay(image, cfg, replay))
        assert rng.bit_generator.state == replay.bit_generator.state  # no extra draws
        np.testing.assert_array_equal(out, _post_process(image, cfg, np.random.default_rng(seed)))


# --- shading modes --------------------------------------------------------------------------------------------

W, H = 320, 240
K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])
GREY = Material(color=(0.7, 0.7, 0.7), specular=0.0)
LIGHT = Light(direction_cam=(0.4, 0.5, 1.0), color=(0.9, 0.9, 0.9), ambient=(0.2, 0.2, 0.2))


@pytest.fixture(scope="module")
def renderer():
    r = Renderer(W, H)
    yield r
    r.release()


@pytest.fixture(scope="module")
def link(panda_meshes):
    """One Panda link mesh (its own private mesh cache) and a pose that fills part of the image."""
    meshes = panda_meshes[1]
    name = "panda_link4" if "panda_link4" in meshes else next(iter(meshes))
    T_cam_link = np.linalg.inv(look_at(np.array([0.35, 0.25, 0.2]), meshes[name].vertices.mean(0).astype(float)))
    return name, meshes[name], T_cam_link


def render_link(renderer: Renderer, link, shading: Shading):
    """The link alone, grey, lit by LIGHT with `shading`."""
    name, mesh, T_cam_link = link
    return renderer.render({name: T_cam_link}, {name: mesh}, K, {name: GREY}, LIGHT, shading=shading)


def test_flat_and_toon_shading_differ_from_phong(renderer, link):
    phong = render_link(renderer, link, Shading("phong"))
    robot = phong.labels > 0
    assert robot.sum() > 2000
    levels = {"phong": len(np.unique(phong.rgba[..., 0][robot]))}
    for mode in ("flat", "toon"):
        out = render_link(renderer, link, Shading(mode, 3))
        np.testing.assert_array_equal(out.labels, phong.labels)  # shading changes colour, not geometry
        np.testing.assert_array_equal(out.depth, phong.depth)
        assert np.abs(out.rgba[..., :3].astype(int) - phong.rgba[..., :3])[robot].mean() > 1.0, mode
        levels[mode] = len(np.unique(out.rgba[..., 0][robot]))
    assert levels["phong"] > 20
    assert levels["toon"] <= 3


@pytest.mark.parametrize("bands", [2, 4])
def test_toon_has_as_many_levels_as_bands(renderer, link, bands):
    out = render_link(renderer, link, Shading("toon", bands))
    grey = out.rgba[..., 0][out.labels > 0]
    assert 2 <= len(np.unique(grey)) <= bands


def test_flat_shading_uses_the_facet_normal(renderer):
    """A box's faces are flat already: flat shading equals Phong there; a sphere's smooth normals become facets."""
    q, _ = np.linalg.qr(np.random.default_rng(2).normal(size=(3, 3)))
    T = np.eye(4)
    T[:3, :3] = q * np.sign(np.linalg.det(q))  # a random rotation, so that three faces show
    T[:3, 3] = 0.0, 0.0, 1.2
    box = [Primitive("box", (0.3, 0.3, 0.3), T, GREY)]
    phong, flat = (renderer.render({}, {}, K, {}, LIGHT, box, Shading(m)) for m in ("phong", "flat"))
    hit = phong.labels > 0
    assert hit.sum() > 2000
    assert np.abs(flat.rgba[..., :3].astype(int) - phong.rgba[..., :3])[hit].max() <= 2  # float rounding only
    sphere = [Primitive("sphere", (0.2, 0, 0), T, GREY)]
    phong, flat = (renderer.render({}, {}, K, {}, LIGHT, sphere, Shading(m)) for m in ("phong", "flat"))
    hit = phong.labels > 0
    assert np.abs(flat.rgba[..., :3].astype(int) - phong.rgba[..., :3])[hit].mean() > 1.0


def test_shading_rejects_unknown_modes():
    with pytest.raises(ValueError, match="unknown shading"):
        Shading("gouraud")
    with pytest.raises(ValueError, match="at least 2 bands"):
        Shading("toon", 1)
