"""train/style_noise.py: feature-statistics noise redraws each chosen sample's channel means and spreads and keeps
its normalized map; the backbone applies it to the maps that leave the frozen blocks, in training mode only, with
the frozen prefix of ONNX Runtime or without it; a bad configuration is refused by name."""

import pytest
import torch

from holo_pose_ros.model.backbones import EfficientNetLite
from holo_pose_ros.train.frozen_prefix import OnnxFrozenPrefix
from holo_pose_ros.train.style_noise import FeatureStatisticsNoise

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py


def _stats(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return x.mean((2, 3)), x.std((2, 3))


def test_chosen_samples_get_new_statistics_and_keep_their_normalized_maps():
    torch.manual_seed(0)
    x = torch.randn(16, 8, 12, 12) * torch.rand(16, 8, 1, 1) * 3 + torch.randn(16, 8, 1, 1) * 2
    noise = FeatureStatisticsNoise(probability=1.0, generator=torch.Generator().manual_seed(1))
    y = noise(x)
    (m0, s0), (m1, s1) = _stats(x), _stats(y)
    assert (m1 - m0).abs().mean() > 0.3 * m0.std(0).mean()          # means moved by about their batch spread
    assert not torch.allclose(s1, s0, rtol=0.05)
    normalize = lambda t: (t - t.mean((2, 3), keepdim=True)) / t.std((2, 3), keepdim=True)  # noqa: E731
    flipped = s1 < 1e-3                                            # a spread clamped at eps loses its map
    assert torch.allclose(normalize(y)[~flipped], normalize(x)[~flipped], atol=1e-3)


def test_probability_chooses_samples_and_zero_or_one_sample_is_identity():
    x = torch.randn(200, 4, 6, 6)
    y = FeatureStatisticsNoise(0.5, generator=torch.Generator().manual_seed(2))(x)
    changed = (y - x).abs().amax((1, 2, 3)) > 1e-6
    assert 60 < int(changed.sum()) < 140
    assert torch.equal(FeatureStatisticsNoise(0.0)(x), x)
    assert torch.equal(FeatureStatisticsNoise(1.0)(x[:1]), x[:1])


def test_configuration_is_checked():
    assert FeatureStatisticsNoise.from_config(None) is None
    noise = FeatureStatisticsNoise.from_config({"probability": 0.3, "scale": 0.5})
    assert (noise.probability, noise.scale) == (0.3, 0.5)
    with pytest.raises(ValueError, match="unknown keys.*'p'"):
        FeatureStatisticsNoise.from_config({"p": 0.5})
    with pytest.raises(ValueError, match="probability"):
        FeatureStatisticsNoise(1.5)


@pytest.mark.parametrize("onnx_prefix", [False, True])
def test_the_backbone_restyles_the_maps_leaving_the_frozen_blocks_in_training_only(tmp_path, onnx_prefix):
    torch.manual_seed(0)
    backbone = EfficientNetLite(0, pretrained=True)
    x = torch.randn(4, 3, 96, 96)
    backbone.eval()
    with torch.no_grad():
        clean, clean_skips = backbone.pyramid(x)
    backbone.style_noise, backbone.style_noise_after = FeatureStatisticsNoise(1.0), (4,)   # blocks 0..4: stride 8
    with torch.no_grad():
        assert torch.equal(backbone.pyramid(x)[0], clean)              # eval mode: never restyled
        if onnx_prefix:
            backbone.frozen_prefix = OnnxFrozenPrefix(backbone, 5, 96, tmp_path / "prefix.onnx", threads=1)
        backbone.train()
        backbone.net.eval()          # training mode gates the noise; every layer's statistics stay fixed
        restyled, skips = backbone.pyramid(x)
    assert not torch.allclose(restyled, clean, atol=1e-2)
    stride16, stride8, stride4 = skips
    for skip, before in ((stride8, clean_skips[1]), (stride4, clean_skips[2])):   # from the frozen blocks
        assert skip.shape == before.shape and not torch.allclose(skip, before, atol=1e-2)
    assert not torch.allclose(stride16, clean_skips[0], atol=1e-2)      # computed from the restyled map


def test_deeper_blocks_restyle_each_map_once(tmp_path):
    """With `after_blocks` past the frozen ones, each listed block restyles its output and the skips taken since the
    last restyle, so every map the decoder reads is restyled exactly once: after block 4 and the stride-16 end,
    block 4's output (the stride-8 skip) and the stride-4 skip at 4, then the stride-16 end's output; after the
    stride-16 end alone, all three there (the trunk's map first)."""
    torch.manual_seed(0)
    backbone = EfficientNetLite(0, pretrained=True)
    x = torch.randn(4, 3, 96, 96)
    backbone.eval()
    with torch.no_grad():
        clean, (c16, c8, c4) = backbone.pyramid(x)
    stride16_end = next(i for i, stride in backbone.skip_ends().items() if stride == 16)
    calls = []

    def counting(t: torch.Tensor) -> torch.Tensor:
        calls.append(tuple(t.shape))
        return FeatureStatisticsNoise(1.0)(t)

    backbone.frozen_prefix = OnnxFrozenPrefix(backbone, 5, 96, tmp_path / "prefix.onnx", threads=1)
    backbone.train()
    backbone.net.eval()
    backbone.style_noise = counting
    for after, expected in (((4, stride16_end), [c8.shape, c4.shape, c16.shape]),
                            ((stride16_end,), [c16.shape, c8.shape, c4.shape])):
        calls.clear()
        backbone.style_noise_after = after
        with torch.no_grad():
            restyled, skips = backbone.pyramid(x)
        assert calls[0] == tuple(expected[0]) and sorted(calls) == sorted(tuple(e) for e in expected), after
        assert not torch.allclose(restyled, clean, atol=1e-2)
        for skip, before in zip(skips, (c16, c8, c4)):
            assert not torch.allclose(skip, before, atol=1e-2)
