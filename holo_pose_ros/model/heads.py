"""The network heads of the paper (§3): DepthNet's scale, KeypointNet's 3D heatmaps with soft-argmax, and the
iterative residual regressors of JointNet and RotationNet. Batched tensors; crop pixels, metres, radians."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from holo_pose_ros.model.heatmaps import decode_heatmaps


class DepthHead(nn.Module):
    """Root depth d = lambda * d_c. lambda = lambda_0 * exp(s): lambda_0 is the training set's median d / d_c
    (a buffer saved with the weights) and s comes from a zero-initialized linear layer, clamped to +-log(8), so
    training starts at the right scale and lambda stays positive and bounded (the official code leaves lambda
    unbounded and starts it at 0)."""

    def __init__(self, channels: int, lambda0: float = 1.0, max_log_scale: float = math.log(8.0)):
        super().__init__()
        self.fc = nn.Linear(channels, 1)
        nn.init.zeros_(self.fc.weight)
        nn.init.zeros_(self.fc.bias)
        self.register_buffer("log_lambda0", torch.tensor(math.log(lambda0)))
        self.max_log_scale = max_log_scale

    def forward(self, pooled: torch.Tensor, d_c: torch.Tensor) -> torch.Tensor:
        """(B, C) pooled features, (B,) d_c in metres -> (B,) root depth in metres."""
        s = self.fc(pooled).squeeze(-1).clamp(-self.max_log_scale, self.max_log_scale)
        return torch.exp(self.log_lambda0 + s) * d_c


def reference_depth(K_crop: torch.Tensor, crop_size: int, reference_side_m: float) -> torch.Tensor:
    """d_c = sqrt(fx fy A_real / A_box) in metres, with the box the whole S x S crop (the localizer's box):
    A_real = side^2 (m^2), A_box = S^2 (crop pixels^2), fx, fy of the crop's K (B, 3, 3)."""
    return torch.sqrt(K_crop[:, 0, 0] * K_crop[:, 1, 1]) * reference_side_m / crop_size


class KeypointHead(nn.Module):
    """KeypointNet: deconvolutions to an N x D x H x W volume per image, softmax over each keypoint's volume,
    and soft-argmax -> (u, v) in crop pixels and root-relative depth dz in metres. With `n_fit` > 0, a second
    1x1 convolution of the same deconvolved features gives 2D heatmaps (H x W logits) of the robot's fit
    keypoints, decoded to sub-pixel positions and confidences (model/heatmaps.py); with `segmentation`, a third
    gives the robot-foreground mask's logits (mask_logits, B x 1 x H x W). With `skip_channels` (the
backbone's maps at strides 16, 8, 4), each deconvolution's output gains a 1x1 projection of the map of its
resolution (skip connections, a small FPN: finer evidence than the 6 x 6 stride-32 map). The projections start
at zero, so a network warm-started without them computes the same function at first."""

    def __init__(self, channels: int, n_keypoints: int, crop_size: int, size: int = 64, depth_bins: int = 64,
                 deconv_channels: int = 256, depth_range_m: float = 1.3, n_fit: int = 0,
                 skip_channels: tuple[int, ...] = (), segmentation: bool = False):
        super().__init__()
        layers, cin, res = [], channels, crop_size // 32
        while res < size:
            layers += [nn.ConvTranspose2d(cin, deconv_channels, 4, 2, 1, bias=False), nn.BatchNorm2d(deconv_channels), nn.ReLU(inplace=True)]
            cin, res = deconv_channels, res * 2
        if res != size:
            raise ValueError(f"heatmap size {size} must be crop_size/32 * 2^k (crop {crop_size})")
        self.deconv = nn.Sequential(*layers)
        self.skips = nn.ModuleList(nn.Conv2d(c, deconv_channels, 1) for c in skip_channels[:len(layers) // 3])
        for conv in self.skips:
            nn.init.zeros_(conv.weight)
            nn.init.zeros_(conv.bias)
        self.out = nn.Conv2d(cin, n_keypoints * depth_bins, 1)
        self.fit_out = nn.Conv2d(cin, n_fit, 1) if n_fit else None
        self.mask_out = nn.Conv2d(cin, 1, 1) if segmentation else None
        self.n, self.d, self.size, self.crop_size, self.depth_range = n_keypoints, depth_bins, size, crop_size, depth_range_m

    def forward(self, features: torch.Tensor, skips: list[torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        """(B, C, S/32, S/32) (and the skip maps, finest last) -> uv (B, N, 2) crop px, dz (B, N) m, confidence
        (B, N) in [0, 1]; with fit heatmaps also heatmap_logits (B, M, H, W) and, in eval mode, fit_uv (B, M, 2)
        crop px and fit_confidence (B, M)."""
        deconvolved = self.heatmap_features(features, skips)
        logits = self.out(deconvolved)
        B = logits.shape[0]
        prob = torch.softmax(logits.reshape(B, self.n, -1).float(), dim=-1).reshape(B, self.n, self.d, self.size, self.size)
        out = soft_argmax_3d(prob, self.crop_size, self.depth_range)
        if self.fit_out is not None:
            heatmaps = self.fit_out(deconvolved)
            out["heatmap_logits"] = heatmaps
            if not self.training:  # the loss reads the logits; decoding costs ~4 % of a CPU training step
                out["fit_uv"], out["fit_confidence"] = decode_heatmaps(heatmaps, self.crop_size)
        if self.mask_out is not None:
            out["mask_logits"] = self.mask_out(deconvolved)
        return out

    def heatmap_features(self, features: torch.Tensor, skips: list[torch.Tensor] | None = None) -> torch.Tensor:
        """The deconvolved map (B, C, S/4, S/4) that every output reads; any crop size S that is a multiple of 32
        (the localizer's lower-resolution pass reads only this and the fit heatmaps)."""
        deconvolved = features
        for k in range(len(self.deconv) // 3):
            deconvolved = self.deconv[3 * k + 2](self.deconv[3 * k + 1](self.deconv[3 * k](deconvolved)))
            if k < len(self.skips):
                deconvolved = deconvolved + self.skips[k](skips[k])
        return deconvolved


def _separable(channels: int) -> nn.Sequential:
    """A depthwise 3x3 then pointwise 1x1 convolution, each with BatchNorm and ReLU: a 3x3 receptive step at
    about 1/9 of a dense 3x3's cost."""
    return nn.Sequential(
        nn.Conv2d(channels, channels, 3, padding=1, groups=channels, bias=False), nn.BatchNorm2d(channels), nn.ReLU(inplace=True),
        nn.Conv2d(channels, channels, 1, bias=False), nn.BatchNorm2d(channels), nn.ReLU(inplace=True))


class PyramidHead(nn.Module):
    """KeypointNet sized for the CPU (an FPN-lite): 1x1 lateral projections of the backbone's maps at strides 32,
    16, 8 and 4 to `width` channels, merged top-down by bilinear upsampling and sums, each level refined by
    depthwise-separable convolutions. The paper's 3D volume is read at stride 8 (the feed-forward head's starts
    and root pixel need no finer), the fit keypoints' 2D heatmaps and the robot-foreground mask at stride 4.
    Same outputs as KeypointHead, plus `mask_logits` (B, 1, H, W) with `segmentation`."""

    def __init__(self, channels: int, skip_channels: tuple[int, int, int], n_keypoints: int, crop_size: int,
                 size: int = 56, depth_bins: int = 32, width: int = 96, depth_range_m: float = 1.3, n_fit: int = 0,
                 segmentation: bool = True, blocks: tuple[int, int, int] = (1, 2, 2)):
        super().__init__()
        if size * 4 != crop_size:
            raise ValueError(f"the pyramid head's heatmaps are at stride 4: size {size} must be crop_size / 4 ({crop_size})")
        self.lateral = nn.ModuleList(nn.Sequential(nn.Conv2d(c, width, 1, bias=False), nn.BatchNorm2d(width))
                                     for c in (channels, *skip_channels))
        self.refine = nn.ModuleList(nn.Sequential(*(_separable(width) for _ in range(n))) for n in blocks)
        self.out = nn.Conv2d(width, n_keypoints * depth_bins, 1)
        self.fit_out = nn.Conv2d(width, n_fit, 1) if n_fit else None
        self.mask_out = nn.Conv2d(width, 1, 1) if segmentation else None
        self.n, self.d, self.size, self.crop_size, self.depth_range = n_keypoints, depth_bins, size, crop_size, depth_range_m

    def forward(self, features: torch.Tensor, skips: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        """(B, C, S/32, S/32) and the skip maps at strides 16, 8, 4 -> uv (B, N, 2) crop px, dz (B, N) m,
        confidence (B, N); heatmap_logits (B, M, H, W) and in eval mode fit_uv (B, M, 2) crop px and fit_confidence
        (B, M); mask_logits (B, 1, H, W) (robot foreground, before the sigmoid)."""
        stride8, stride4 = self._levels(features, skips)[1:]
        logits = self.out(stride8)
        B, H8 = logits.shape[0], logits.shape[-1]
        prob = torch.softmax(logits.reshape(B, self.n, -1).float(), dim=-1).reshape(B, self.n, self.d, H8, H8)
        out = soft_argmax_3d(prob, self.crop_size, self.depth_range)
        if self.fit_out is not None:
            heatmaps = self.fit_out(stride4)
            out["heatmap_logits"] = heatmaps
            if not self.training:
                out["fit_uv"], out["fit_confidence"] = decode_heatmaps(heatmaps, self.crop_size)
        if self.mask_out is not None:
            out["mask_logits"] = self.mask_out(stride4)
        return out

    def _levels(self, features: torch.Tensor, skips: list[torch.Tensor]) -> list[torch.Tensor]:
        """The merged, refined maps at strides 16, 8 and 4."""
        x = self.lateral[0](features)
        levels = []
        for lateral, refine, skip in zip(self.lateral[1:], self.refine, skips):
            x = refine(F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False) + lateral(skip))
            levels.append(x)
        return levels

    def heatmap_features(self, features: torch.Tensor, skips: list[torch.Tensor]) -> torch.Tensor:
        """The stride-4 map (B, width, S/4, S/4) that the fit heatmaps and the mask read; any crop size S that is
        a multiple of 32."""
        return self._levels(features, skips)[2]


def soft_argmax_3d(prob: torch.Tensor, crop_size: int, depth_range_m: float) -> dict[str, torch.Tensor]:
    """Expectations of a normalized (B, N, D, H, W) volume: u, v in crop pixels (cell centres map to pixel centres
    of the S x S crop), dz in metres over [-range/2, range/2], and a confidence: the 2D mass within one cell of
    the expected position (a peaked heatmap gives 1, a flat one ~9/(H W))."""
    B, N, D, H, W = prob.shape
    p_xy = prob.sum(2)                                   # (B, N, H, W)
    px, py, pz = p_xy.sum(2), p_xy.sum(3), prob.sum((3, 4))
    ix = torch.arange(W, dtype=prob.dtype, device=prob.device)
    iy = torch.arange(H, dtype=prob.dtype, device=prob.device)
    iz = torch.arange(D, dtype=prob.dtype, device=prob.device)
    x, y, z = (px * ix).sum(-1), (py * iy).sum(-1), (pz * iz).sum(-1)
    u = (x + 0.5) * crop_size / W - 0.5
    v = (y + 0.5) * crop_size / H - 0.5
    dz = ((z + 0.5) / D - 0.5) * depth_range_m
    near = ((ix.view(1, 1, 1, W) - x[..., None, None]).abs() <= 1.0) & ((iy.view(1, 1, H, 1) - y[..., None, None]).abs() <= 1.0)
    confidence = (p_xy * near).sum((-1, -2))
    return {"uv": torch.stack([u, v], -1), "dz": dz, "confidence": confidence}


class IterativeRegressor(nn.Module):
    """HMR-style iterative residual regression: state <- state + MLP([features, state]), `iterations` times,
    from a fixed initial state (the neutral pose / identity rotation). Unlike the official code, the MLP has
    non-linearities."""

    def __init__(self, channels: int, initial: torch.Tensor, iterations: int = 4, hidden: int = 1024, dropout: float = 0.2):
        super().__init__()
        dim = initial.numel()
        self.register_buffer("initial", initial.float().reshape(1, dim))
        self.mlp = nn.Sequential(
            nn.Linear(channels + dim, hidden), nn.ReLU(inplace=True), nn.Dropout(dropout),
            nn.Linear(hidden, hidden), nn.ReLU(inplace=True), nn.Dropout(dropout), nn.Linear(hidden, dim))
        nn.init.xavier_uniform_(self.mlp[-1].weight, gain=0.01)
        nn.init.zeros_(self.mlp[-1].bias)
        self.iterations = iterations

    def forward(self, pooled: torch.Tensor) -> torch.Tensor:
        state = self.initial.expand(pooled.shape[0], -1)
        for _ in range(self.iterations):
            state = state + self.mlp(torch.cat([pooled, state], dim=1))
        return state
