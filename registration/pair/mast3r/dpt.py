"""The DPT head (Ranftl et al. 2021) as MASt3R/DUSt3R use it: four hooked token maps -> reassembled at 1/4, 1/8,
1/16, 1/32 of the image -> projected to `feature_dim` -> fused coarse-to-fine by residual refinement blocks ->
regression head at full resolution. Names match the official checkpoints (`act_postprocess.{i}`,
`scratch.layer{i}_rn` (also reachable as `scratch.layer_rn.{i-1}`), `scratch.refinenet{i}.resConfUnit{1,2}`,
`scratch.refinenet{i}.out_conv`, `head.{0,2,4}`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class ResidualConvUnit(nn.Module):
    def __init__(self, features: int):
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, 1, 1, bias=True)
        self.conv2 = nn.Conv2d(features, features, 3, 1, 1, bias=True)

    def forward(self, x):
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FusionBlock(nn.Module):
    """out_conv(upsample2x(rcu2(x + rcu1(skip))))."""

    def __init__(self, features: int):
        super().__init__()
        self.out_conv = nn.Conv2d(features, features, 1, 1, 0, bias=True)
        self.resConfUnit1 = ResidualConvUnit(features)
        self.resConfUnit2 = ResidualConvUnit(features)

    def forward(self, x, skip=None):
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)
        return self.out_conv(x)


class Upsample(nn.Module):
    """Parameter-free x2 bilinear upsampling (a slot in `head`, so the conv indices stay 0, 2, 4)."""

    def forward(self, x):
        return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)


class DPTAdapter(nn.Module):
    def __init__(self, dim_tokens: list[int], hooks: list[int], num_channels: int, patch_size: int,
                 layer_dims=(96, 192, 384, 768), feature_dim: int = 256, last_dim: int = 128):
        super().__init__()
        self.hooks = list(hooks)
        self.patch_size = patch_size
        ld = list(layer_dims)
        self.act_postprocess = nn.ModuleList([
            nn.Sequential(nn.Conv2d(dim_tokens[0], ld[0], 1), nn.ConvTranspose2d(ld[0], ld[0], 4, stride=4)),
            nn.Sequential(nn.Conv2d(dim_tokens[1], ld[1], 1), nn.ConvTranspose2d(ld[1], ld[1], 2, stride=2)),
            nn.Sequential(nn.Conv2d(dim_tokens[2], ld[2], 1)),
            nn.Sequential(nn.Conv2d(dim_tokens[3], ld[3], 1), nn.Conv2d(ld[3], ld[3], 3, stride=2, padding=1)),
        ])
        scratch = nn.Module()
        rn = [nn.Conv2d(ld[i], feature_dim, 3, 1, 1, bias=False) for i in range(4)]
        for i, conv in enumerate(rn):
            setattr(scratch, f"layer{i + 1}_rn", conv)
        scratch.layer_rn = nn.ModuleList(rn)  # the same modules again, as the checkpoint stores them twice
        for i in range(4):
            setattr(scratch, f"refinenet{i + 1}", FusionBlock(feature_dim))
        self.scratch = scratch
        self.head = nn.Sequential(
            nn.Conv2d(feature_dim, feature_dim // 2, 3, 1, 1), Upsample(),
            nn.Conv2d(feature_dim // 2, last_dim, 3, 1, 1), nn.ReLU(True),
            nn.Conv2d(last_dim, num_channels, 1, 1, 0))

    def forward(self, tokens: list[torch.Tensor], hw: tuple[int, int]) -> torch.Tensor:
        """tokens: per-layer [B, N, C_i]; hw: image (H, W) -> [B, num_channels, H, W]."""
        h, w = hw[0] // self.patch_size, hw[1] // self.patch_size
        maps = []
        for i, hook in enumerate(self.hooks):
            t = tokens[hook]
            x = t.transpose(1, 2).reshape(t.shape[0], t.shape[2], h, w)
            maps.append(self.scratch.layer_rn[i](self.act_postprocess[i](x)))
        s = self.scratch
        p4 = s.refinenet4(maps[3])[:, :, : maps[2].shape[2], : maps[2].shape[3]]  # odd grids: crop to the 1/16 map
        p3 = s.refinenet3(p4, maps[2])
        p2 = s.refinenet2(p3, maps[1])
        p1 = s.refinenet1(p2, maps[0])
        return self.head(p1)
