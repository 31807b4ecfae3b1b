"""train/frozen_prefix.py: the frozen stem and first blocks of a Lite0 backbone run by ONNX Runtime give the same
maps as PyTorch, only in training mode, never in a copy; and a CPU training run uses it."""

import copy

import pytest
import torch

from holo_pose_ros.model.backbones import EfficientNetLite
from holo_pose_ros.train.frozen_prefix import OnnxFrozenPrefix

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py


@pytest.fixture(scope="module")
def backbone():
    torch.manual_seed(0)
    return EfficientNetLite(0, pretrained=True)


@pytest.mark.parametrize("blocks", [2, 5])
def test_the_onnx_prefix_computes_the_torch_pyramid(backbone, tmp_path, blocks):
    x = torch.randn(3, 3, 96, 96)
    backbone.eval()
    with torch.no_grad():
        features, skips = backbone.pyramid(x)
    backbone.frozen_prefix = OnnxFrozenPrefix(backbone, blocks, 96, tmp_path / "prefix.onnx", threads=1)
    try:
        with torch.no_grad():
            assert torch.equal(backbone.pyramid(x)[0], features)   # eval mode: the prefix is not used
            backbone.train()
            backbone.net.eval()   # the backbone in training mode (it gates the prefix), every layer fixed
            trained, trained_skips = backbone.pyramid(x)
            assert torch.allclose(backbone(x), trained, atol=1e-6)
        assert torch.allclose(trained, features, atol=1e-3)
        for a, b in zip(trained_skips, skips):
            assert a.shape == b.shape and torch.allclose(a, b, atol=1e-3)
        assert copy.deepcopy(backbone).frozen_prefix is None
    finally:
        backbone.frozen_prefix = None
        backbone.eval()


def test_a_prefix_longer_than_the_trunk_is_refused(backbone, tmp_path):
    with pytest.raises(ValueError, match="frozen blocks"):
        OnnxFrozenPrefix(backbone, 99, 96, tmp_path / "p.onnx")
