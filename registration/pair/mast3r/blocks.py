"""Transformer pieces of MASt3R (CroCo v2 lineage): 2D rotary position embedding, ViT blocks, decoder blocks with
cross-attention, and the patch embedding. Parameter names match the official checkpoints (`norm1`, `attn.qkv`,
`attn.proj`, `cross_attn.projq/projk/projv/proj`, `norm_y`, `mlp.fc1/fc2`, `patch_embed.proj`).

Token positions are integer (y, x) patch coordinates; RoPE rotates the first half of each head's channels by y
and the second half by x.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class RoPE2D(nn.Module):
    """Rotary embedding over two axes with frequency base `freq` (MASt3R uses 100: 'RoPE100'). No parameters."""

    def __init__(self, freq: float = 100.0):
        super().__init__()
        self.base = float(freq)

    def _rotate(self, x: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        # x: [B, heads, N, D] with D even; pos: [B, N] integer coordinates along one axis
        d = x.shape[-1]
        inv_freq = 1.0 / (self.base ** (torch.arange(0, d, 2, device=x.device, dtype=torch.float32) / d))
        ang = pos.to(torch.float32)[..., None] * inv_freq  # [B, N, D/2]
        ang = torch.cat([ang, ang], dim=-1)[:, None].to(x.dtype)  # [B, 1, N, D]
        x1, x2 = x[..., : d // 2], x[..., d // 2 :]
        return x * ang.cos() + torch.cat([-x2, x1], dim=-1) * ang.sin()

    def forward(self, tokens: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        """tokens [B, heads, N, Dh], pos [B, N, 2] (y, x) -> rotated tokens, same shape."""
        ty, tx = tokens.chunk(2, dim=-1)
        return torch.cat([self._rotate(ty, pos[..., 0]), self._rotate(tx, pos[..., 1])], dim=-1)


class Mlp(nn.Module):
    def __init__(self, dim_in: int, hidden: int, dim_out: int | None = None):
        super().__init__()
        self.fc1 = nn.Linear(dim_in, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim_out or dim_in)

    def forward(self, x):
        return self.fc2(self.act(self.fc1(x)))


def _attend(q, k, v, rope, qpos, kpos):
    if rope is not None:
        q, k = rope(q, qpos), rope(k, kpos)
    return F.scaled_dot_product_attention(q, k, v)  # softmax(q k^T / sqrt(d)) v


class Attention(nn.Module):
    def __init__(self, dim: int, heads: int, rope: RoPE2D | None):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, dim * 3, bias=True)
        self.proj = nn.Linear(dim, dim)
        self.rope = rope

    def forward(self, x, pos):  # x [B, N, C]
        b, n, c = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        out = _attend(q, k, v, self.rope, pos, pos)
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class CrossAttention(nn.Module):
    def __init__(self, dim: int, heads: int, rope: RoPE2D | None):
        super().__init__()
        self.heads = heads
        self.projq = nn.Linear(dim, dim, bias=True)
        self.projk = nn.Linear(dim, dim, bias=True)
        self.projv = nn.Linear(dim, dim, bias=True)
        self.proj = nn.Linear(dim, dim)
        self.rope = rope

    def forward(self, x, y, xpos, ypos):  # queries from x [B, N, C], keys/values from y [B, M, C]
        b, n, c = x.shape
        m = y.shape[1]
        h = self.heads
        q = self.projq(x).reshape(b, n, h, c // h).transpose(1, 2)
        k = self.projk(y).reshape(b, m, h, c // h).transpose(1, 2)
        v = self.projv(y).reshape(b, m, h, c // h).transpose(1, 2)
        out = _attend(q, k, v, self.rope, xpos, ypos)
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


def layer_norm(dim: int) -> nn.LayerNorm:
    return nn.LayerNorm(dim, eps=1e-6)


class Block(nn.Module):
    """Pre-norm ViT block: x + attn(norm1 x), then x + mlp(norm2 x)."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float, rope: RoPE2D | None):
        super().__init__()
        self.norm1 = layer_norm(dim)
        self.attn = Attention(dim, heads, rope)
        self.norm2 = layer_norm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x, pos):
        x = x + self.attn(self.norm1(x), pos)
        return x + self.mlp(self.norm2(x))


class DecoderBlock(nn.Module):
    """Self-attention on one view, cross-attention to the other view's tokens (normalised by norm_y), MLP."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float, rope: RoPE2D | None):
        super().__init__()
        self.norm1 = layer_norm(dim)
        self.attn = Attention(dim, heads, rope)
        self.cross_attn = CrossAttention(dim, heads, rope)
        self.norm2 = layer_norm(dim)
        self.norm3 = layer_norm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))
        self.norm_y = layer_norm(dim)

    def forward(self, x, y, xpos, ypos):
        x = x + self.attn(self.norm1(x), xpos)
        y_ = self.norm_y(y)
        x = x + self.cross_attn(self.norm2(x), y_, xpos, ypos)
        return x + self.mlp(self.norm3(x))


class PatchEmbed(nn.Module):
    """Non-overlapping p x p patches -> tokens [B, N, C] and their (y, x) grid positions [B, N, 2]."""

    def __init__(self, patch_size: int, dim: int):
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(3, dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, img):  # [B, 3, H, W], H and W multiples of patch_size
        x = self.proj(img)
        b, _, h, w = x.shape
        return x.flatten(2).transpose(1, 2), grid_positions(b, h, w, img.device)


def grid_positions(b: int, h: int, w: int, device) -> torch.Tensor:
    """[B, h*w, 2] int64 (y, x) in row-major token order."""
    y, x = torch.meshgrid(torch.arange(h, device=device), torch.arange(w, device=device), indexing="ij")
    return torch.stack([y.reshape(-1), x.reshape(-1)], -1)[None].expand(b, -1, -1).clone()
