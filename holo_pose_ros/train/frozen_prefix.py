"""The frozen first blocks of an EfficientNet-Lite backbone, run by ONNX Runtime while training on the CPU. They
take no gradient and their BatchNorm statistics are fixed, so ORT's fused inference kernels compute the same maps
(to ~1e-4) about five times faster than eager PyTorch: Lite0's stem and first 5 blocks at batch 24 and 192 px take
37 ms instead of 199, about 17 % of a training step (issue 10's throughput table)."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import torch
from torch import nn

from holo_pose_ros.model.backbones import EfficientNetLite


class _Prefix(nn.Module):
    """The stem and blocks [0, blocks) of a Lite trunk, returning the outputs of the blocks in `keep` (the graph
    that is exported)."""

    def __init__(self, backbone: EfficientNetLite, blocks: int, keep: list[int]):
        super().__init__()
        self.trunk, self.blocks, self.keep = backbone.net, blocks, keep

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        net, outs = self.trunk, []
        x = net._swish(net._bn0(net._conv_stem(x)))
        for i, block in enumerate(net._blocks[:self.blocks]):
            x = block(x)                                   # eval mode: no drop connect
            if i in self.keep:
                outs.append(x)
        return tuple(outs)


class OnnxFrozenPrefix:
    """Callable (B, 3, S, S) normalized images -> {block index: output map} for the last frozen block and the
    skip-stride ends before it, as torch tensors (channels_last). Exported from the backbone's current weights:
    build it after they are loaded, and only over modules that stay frozen."""

    def __init__(self, backbone: EfficientNetLite, blocks: int, input_size: int, path: str | Path,
                 threads: int | None = None):
        from holo_pose_ros.model.onnx_runtime import export_module, session

        if not 0 < blocks <= len(backbone.net._blocks):
            raise ValueError(f"frozen blocks must be 1..{len(backbone.net._blocks)}, got {blocks}")
        self.blocks = blocks
        self.keep = sorted({i for i in backbone.skip_ends() if i < blocks} | {blocks - 1})
        module = _Prefix(copy.deepcopy(backbone), blocks, self.keep).eval()  # a copy: the live trunk keeps its mode
        example = (torch.rand(2, 3, input_size, input_size),)
        self.path = export_module(module, example, path, ("x",), [f"block{i}" for i in self.keep])
        self.session = session(self.path, threads)

    def __call__(self, x: torch.Tensor) -> dict[int, torch.Tensor]:
        outs = self.session.run(None, {"x": np.ascontiguousarray(x.detach().cpu().numpy(), dtype=np.float32)})
        return {i: torch.from_numpy(o).to(x.device).contiguous(memory_format=torch.channels_last)
                for i, o in zip(self.keep, outs)}

    def __deepcopy__(self, memo: dict) -> None:
        """A copied network (e.g. for an ONNX export, always in eval mode) gets no prefix: sessions do not copy."""
        return None
