"""BatchNorm statistics of the user's images (AdaBN): a new look shifts the means and variances of every layer's
features; re-estimating them on the deployed inputs (the localizer's letterboxed frames and the crop passes) takes
no labels and no gradients, and moves no learned weight."""

from __future__ import annotations

from collections.abc import Iterable

import torch


def batchnorm_layers(net: torch.nn.Module) -> list[torch.nn.modules.batchnorm._BatchNorm]:
    """Every BatchNorm layer of `net`, in module order."""
    return [m for m in net.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]


@torch.no_grad()
def reestimate_batchnorm(net: torch.nn.Module, batches: Iterable[tuple[torch.Tensor, torch.Tensor]],
                         keep: float = 0.0) -> int:
    """Replace every BatchNorm layer's running mean and variance by their average over `batches` of network
    inputs ((B, 3, S, S) in [0, 1], (B, 3, 3) crop intrinsics), blended as keep * old + (1 - keep) * new (keep in
    [0, 1): how much of the training statistics stays). Returns the number of images seen; the network is left
    in eval mode."""
    if not 0.0 <= keep < 1.0:
        raise ValueError(f"keep must be in [0, 1), got {keep}")
    layers = batchnorm_layers(net)
    old = [(m.running_mean.clone(), m.running_var.clone(), m.momentum) for m in layers]
    net.eval()
    for m in layers:
        m.reset_running_stats()
        m.momentum = None  # a cumulative average over every batch, whatever their number
        m.train()
    seen = 0
    try:
        for images, K_crop in batches:
            net(images, K_crop)
            seen += len(images)
    finally:
        for m, (mean, var, momentum) in zip(layers, old):
            m.momentum = momentum
            m.eval()
            if seen == 0:
                m.running_mean.copy_(mean)
                m.running_var.copy_(var)
            else:
                m.running_mean.mul_(1.0 - keep).add_(keep * mean)
                m.running_var.mul_(1.0 - keep).add_(keep * var)
    net.eval()
    return seen
