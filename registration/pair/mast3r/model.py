"""MASt3R (Leroy et al., ECCV 2024) in plain torch: a shared ViT encoder, two ViT decoders that cross-attend to
each other, and per view a head that regresses a pointmap with confidence (DPT) and dense local descriptors (MLP on
the concatenated encoder and decoder tokens).

The parameter layout is the official one (`patch_embed.proj`, `enc_blocks.{i}`, `enc_norm`, `decoder_embed`,
`dec_blocks.{i}`, `dec_blocks2.{i}`, `dec_norm`, `mask_token`, `downstream_head{1,2}.dpt.*`,
`downstream_head{1,2}.head_local_features.fc{1,2}`), so `MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth`
loads with `load_state_dict(strict=True)`. Inference is split as FLOCC-SLAM's Fig. 1 needs:
`encode(img)` once per keyframe on its robot, `decode(enc1, enc2)` for a pair on one robot.

Outputs per view (both pointmaps in view 1's camera frame, metres up to the model's scale):
    pts3d [B, H, W, 3], conf [B, H, W] (>= 1), desc [B, H, W, D] (unit norm), desc_conf [B, H, W].
"""

from __future__ import annotations

import ast
import math
import re
from dataclasses import dataclass, field

import torch
from torch import nn

from .blocks import Block, DecoderBlock, Mlp, PatchEmbed, RoPE2D, grid_positions, layer_norm
from .dpt import DPTAdapter


@dataclass(frozen=True)
class Mast3rConfig:
    """Architecture hyper-parameters. Defaults: the released ViT-Large encoder / ViT-Base decoder, 512 px model."""

    patch_size: int = 16
    enc_embed_dim: int = 1024
    enc_depth: int = 24
    enc_num_heads: int = 16
    dec_embed_dim: int = 768
    dec_depth: int = 12
    dec_num_heads: int = 12
    mlp_ratio: float = 4.0
    rope_freq: float = 100.0
    local_feat_dim: int = 24
    two_confs: bool = True
    depth_mode: tuple = ("exp", -math.inf, math.inf)
    conf_mode: tuple = ("exp", 1.0, math.inf)
    desc_conf_mode: tuple = ("exp", 0.0, math.inf)
    feature_dim: int = 256  # DPT fusion width
    layer_dims: tuple = (96, 192, 384, 768)
    img_size: int = 512  # longer side the model was trained at

    @classmethod
    def from_model_string(cls, s: str) -> "Mast3rConfig":
        """Parse the `AsymmetricMASt3R(...)` constructor string stored in official checkpoints (ckpt['args'].model).

        Only literal keyword arguments are read (never evaluated as code).
        """
        inner = s[s.index("(") + 1 : s.rindex(")")] if "(" in s else s
        inner = re.sub(r"(?<![\w.])-?inf\b", lambda m: "-1e999" if m.group(0).startswith("-") else "1e999", inner)
        call = ast.parse(f"f({inner})", mode="eval").body
        kw = {k.arg: ast.literal_eval(k.value) for k in call.keywords}
        out = {}
        names = {f for f in cls.__dataclass_fields__}
        for k, v in kw.items():
            if k == "pos_embed" and str(v).startswith("RoPE"):
                out["rope_freq"] = float(str(v)[4:])
            elif k == "output_mode" and str(v).startswith("pts3d+desc"):
                out["local_feat_dim"] = int(str(v)[10:])
            elif k == "img_size":
                out["img_size"] = int(max(v) if isinstance(v, (tuple, list)) else v)
            elif k in names:
                out[k] = tuple(v) if isinstance(v, list) else v
        return cls(**out)


def _reg_points(xyz: torch.Tensor, mode) -> torch.Tensor:
    kind = mode[0]
    if kind == "linear":
        return xyz
    d = xyz.norm(dim=-1, keepdim=True)
    u = xyz / d.clamp(min=1e-8)
    return u * (d.square() if kind == "square" else torch.expm1(d))


def _reg_conf(x: torch.Tensor, mode) -> torch.Tensor:
    kind, lo, hi = mode
    if kind == "sigmoid":
        return (hi - lo) * torch.sigmoid(x) + lo
    return lo + x.exp().clamp(max=hi - lo)


class Mast3rHead(nn.Module):
    """DPT pointmap+confidence regression and an MLP local-feature head on [encoder | decoder] tokens."""

    def __init__(self, cfg: Mast3rConfig):
        super().__init__()
        self.cfg = cfg
        l2 = cfg.dec_depth
        self.dpt = DPTAdapter([cfg.enc_embed_dim] + [cfg.dec_embed_dim] * 3, [0, l2 * 2 // 4, l2 * 3 // 4, l2],
                              num_channels=4, patch_size=cfg.patch_size, layer_dims=cfg.layer_dims,
                              feature_dim=cfg.feature_dim, last_dim=cfg.feature_dim // 2)
        idim = cfg.enc_embed_dim + cfg.dec_embed_dim
        self.head_local_features = Mlp(idim, int(4 * idim), (cfg.local_feat_dim + int(cfg.two_confs)) * cfg.patch_size**2)

    def forward(self, tokens: list[torch.Tensor], hw: tuple[int, int]) -> dict[str, torch.Tensor]:
        cfg, p = self.cfg, self.cfg.patch_size
        geo = self.dpt(tokens, hw)  # [B, 4, H, W]
        cat = torch.cat([tokens[0], tokens[-1]], dim=-1)  # [B, N, enc + dec]
        b = cat.shape[0]
        feats = self.head_local_features(cat).transpose(1, 2).reshape(b, -1, hw[0] // p, hw[1] // p)
        feats = nn.functional.pixel_shuffle(feats, p)  # [B, D (+1), H, W]
        fmap = torch.cat([geo, feats], dim=1).permute(0, 2, 3, 1)  # [B, H, W, 4 + D (+1)]
        d = cfg.local_feat_dim
        desc = fmap[..., 4 : 4 + d]
        out = {"pts3d": _reg_points(fmap[..., :3], cfg.depth_mode), "conf": _reg_conf(fmap[..., 3], cfg.conf_mode),
               "desc": desc / desc.norm(dim=-1, keepdim=True)}
        out["desc_conf"] = _reg_conf(fmap[..., 4 + d], cfg.desc_conf_mode) if cfg.two_confs else out["conf"].clone()
        return out


@dataclass
class EncodedImage:
    """Encoder output for one image: tokens [B, N, enc_dim], positions [B, N, 2], image (H, W) in network pixels."""

    tokens: torch.Tensor
    pos: torch.Tensor
    hw: tuple[int, int]
    meta: dict = field(default_factory=dict)


class Mast3rNet(nn.Module):
    def __init__(self, cfg: Mast3rConfig | None = None):
        super().__init__()
        cfg = cfg or Mast3rConfig()
        self.cfg = cfg
        rope = RoPE2D(cfg.rope_freq)
        self.patch_embed = PatchEmbed(cfg.patch_size, cfg.enc_embed_dim)
        self.enc_blocks = nn.ModuleList(
            [Block(cfg.enc_embed_dim, cfg.enc_num_heads, cfg.mlp_ratio, rope) for _ in range(cfg.enc_depth)])
        self.enc_norm = layer_norm(cfg.enc_embed_dim)
        # CroCo's pre-training mask token: unused at inference but part of every released checkpoint.
        self.mask_token = nn.Parameter(torch.zeros(1, 1, cfg.dec_embed_dim))
        self.decoder_embed = nn.Linear(cfg.enc_embed_dim, cfg.dec_embed_dim)
        self.dec_blocks = nn.ModuleList(
            [DecoderBlock(cfg.dec_embed_dim, cfg.dec_num_heads, cfg.mlp_ratio, rope) for _ in range(cfg.dec_depth)])
        self.dec_blocks2 = nn.ModuleList(
            [DecoderBlock(cfg.dec_embed_dim, cfg.dec_num_heads, cfg.mlp_ratio, rope) for _ in range(cfg.dec_depth)])
        self.dec_norm = layer_norm(cfg.dec_embed_dim)
        self.downstream_head1 = Mast3rHead(cfg)
        self.downstream_head2 = Mast3rHead(cfg)

    def encode(self, img: torch.Tensor) -> EncodedImage:
        """img [B, 3, H, W] in [-1, 1], H and W multiples of the patch size -> EncodedImage."""
        x, pos = self.patch_embed(img)
        for blk in self.enc_blocks:
            x = blk(x, pos)
        return EncodedImage(self.enc_norm(x), pos, (int(img.shape[2]), int(img.shape[3])))

    def decode(self, e1: EncodedImage, e2: EncodedImage) -> tuple[dict, dict]:
        """Decode a pair -> (view1 outputs, view2 outputs), both pointmaps in view 1's frame.

        View 2's pointmap is returned as 'pts3d_in_other_view' (the official name)."""
        f1, f2 = self.decoder_embed(e1.tokens), self.decoder_embed(e2.tokens)
        seq1, seq2 = [e1.tokens], [e2.tokens]
        for blk1, blk2 in zip(self.dec_blocks, self.dec_blocks2):
            # both views advance from the previous layer's pair, not one after the other
            f1, f2 = blk1(f1, f2, e1.pos, e2.pos), blk2(f2, f1, e2.pos, e1.pos)
            seq1.append(f1)
            seq2.append(f2)
        seq1[-1], seq2[-1] = self.dec_norm(seq1[-1]), self.dec_norm(seq2[-1])
        out1 = self.downstream_head1(seq1, e1.hw)
        out2 = self.downstream_head2(seq2, e2.hw)
        out2["pts3d_in_other_view"] = out2.pop("pts3d")
        return out1, out2

    def forward(self, img1: torch.Tensor, img2: torch.Tensor) -> tuple[dict, dict]:
        """Both images at once (one batched encoder pass when their shapes agree), then decode."""
        if img1.shape == img2.shape:
            e = self.encode(torch.cat([img1, img2]))
            b = img1.shape[0]
            e1 = EncodedImage(e.tokens[:b], e.pos[:b], e.hw)
            e2 = EncodedImage(e.tokens[b:], e.pos[b:], e.hw)
        else:
            e1, e2 = self.encode(img1), self.encode(img2)
        return self.decode(e1, e2)


__all__ = ["Mast3rConfig", "Mast3rNet", "EncodedImage", "grid_positions"]
