"""Feature-statistics noise for training (DSU: Li et al., "Uncertainty Modeling for Out-of-Distribution
Generalization", ICLR 2022). A new camera shifts the channel means and spreads of the early feature maps (re-estimating
BatchNorm statistics on a user's frames alone recovers +7 AUC on the unseen look: docs/adaptation.md). Training with
those statistics redrawn, per sample and channel, around their values with the spread they have across the batch
teaches the layers above to read the robot's geometry rather than the look's statistics. Generic: it draws on no
description of any look. Training mode only; inference never sees it."""

from __future__ import annotations

import torch


class FeatureStatisticsNoise:
    """Callable (B, C, H, W) -> (B, C, H, W): each sample, with `probability`, keeps its normalized map and gets new
    channel means and standard deviations, each drawn from a normal around its own with the standard deviation that
    statistic has across the batch, times `scale`. Not an nn.Module: no parameters, never in a state dict."""

    def __init__(self, probability: float = 0.5, scale: float = 1.0, eps: float = 1e-6,
                 generator: torch.Generator | None = None):
        if not 0.0 <= probability <= 1.0:
            raise ValueError(f"style noise probability must be in [0, 1], got {probability}")
        if scale < 0.0:
            raise ValueError(f"style noise scale must be >= 0, got {scale}")
        self.probability, self.scale, self.eps, self.generator = probability, scale, eps, generator

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[0] < 2 or self.probability == 0.0 or self.scale == 0.0:
            return x                                    # one sample has no batch spread to draw from
        mean = x.mean((2, 3), keepdim=True)
        std = (x.var((2, 3), keepdim=True) + self.eps).sqrt()
        spread_mean = (mean.var(0, keepdim=True) + self.eps).sqrt()
        spread_std = (std.var(0, keepdim=True) + self.eps).sqrt()
        draw = lambda t: torch.randn(t.shape, generator=self.generator, dtype=t.dtype).to(t.device)  # noqa: E731
        new_mean = mean + self.scale * draw(mean) * spread_mean
        new_std = (std + self.scale * draw(std) * spread_std).clamp_min(self.eps)
        restyled = (x - mean) / std * new_std + new_mean
        chosen = torch.rand((x.shape[0], 1, 1, 1), generator=self.generator).to(x.device) < self.probability
        return torch.where(chosen, restyled, x)

    @classmethod
    def from_config(cls, cfg: dict | None) -> FeatureStatisticsNoise | None:
        """The training YAML's `style_noise: {probability, scale}` (absent: None, no noise)."""
        if not cfg:
            return None
        unknown = set(cfg) - {"probability", "scale"}
        if unknown:
            raise ValueError(f"style_noise: unknown keys {sorted(unknown)} (known: probability, scale)")
        return cls(float(cfg.get("probability", 0.5)), float(cfg.get("scale", 1.0)))
