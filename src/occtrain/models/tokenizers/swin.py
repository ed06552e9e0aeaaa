"""A compact Swin transformer stage: windowed multi-head self-attention, alternately shifted windows.

Windows are ``window`` x ``window`` squares with a learned relative-position bias per head.
Every second block rolls the map by half a window so information crosses window borders;
tokens that the roll brought together from opposite edges are masked from each other.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class WindowAttention(nn.Module):
    """Multi-head self-attention inside each window, with relative-position bias."""

    bias_index: torch.Tensor

    def __init__(self, dim: int, heads: int, window: int):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        span = 2 * window - 1
        self.bias_table = nn.Parameter(torch.zeros(span * span, heads))
        nn.init.trunc_normal_(self.bias_table, std=0.02)
        coords = torch.stack(torch.meshgrid(torch.arange(window), torch.arange(window), indexing="ij")).flatten(1)
        rel = coords[:, :, None] - coords[:, None, :] + (window - 1)  # (2, N, N), shifted to >= 0
        self.register_buffer("bias_index", rel[0] * span + rel[1], persistent=False)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """x: (B, nW, N, C) tokens of each window; mask: additive (nW, N, N) or None."""
        b, nw, n, c = x.shape
        q, k, v = self.qkv(x).view(b, nw, n, 3, self.heads, c // self.heads).permute(3, 0, 1, 4, 2, 5).unbind(0)
        bias = self.bias_table[self.bias_index].permute(2, 0, 1)  # (heads, N, N)
        attn_mask = bias if mask is None else bias + mask[:, None]
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask)  # (B, nW, heads, N, d)
        return self.proj(out.transpose(2, 3).reshape(b, nw, n, c))


def partition(x: torch.Tensor, window: int) -> torch.Tensor:
    """(B, H, W, C) -> (B, nW, window * window, C), windows in row-major order."""
    b, h, w, c = x.shape
    x = x.view(b, h // window, window, w // window, window, c).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(b, -1, window * window, c)


def merge(windows: torch.Tensor, h: int, w: int, window: int) -> torch.Tensor:
    """Inverse of :func:`partition`."""
    b, _, _, c = windows.shape
    x = windows.view(b, h // window, w // window, window, window, c).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(b, h, w, c)


def shifted_window_mask(h: int, w: int, window: int, shift: int) -> torch.Tensor:
    """Additive (nW, N, N) mask: -inf between tokens of a window that came from different regions."""
    region = torch.zeros(h, w)
    bands = (slice(0, -window), slice(-window, -shift), slice(-shift, None))
    for i, rows in enumerate(bands):
        for j, cols in enumerate(bands):
            region[rows, cols] = 3 * i + j
    labels = partition(region[None, :, :, None], window)[0, :, :, 0]  # (nW, N)
    different = labels[:, :, None] != labels[:, None, :]
    return torch.zeros(different.shape).masked_fill(different, float("-inf"))


class SwinBlock(nn.Module):
    """Pre-norm (shifted-)window attention + MLP, both residual, on (B, H, W, C) maps."""

    #: The shifted windows' additive mask; None without a shift.
    mask: torch.Tensor | None

    def __init__(self, dim: int, heads: int, window: int, shift: int, hw: tuple[int, int], mlp_ratio: float):
        super().__init__()
        self.window, self.shift = window, shift
        self.norm1 = nn.LayerNorm(dim)
        self.attn = WindowAttention(dim, heads, window)
        self.norm2 = nn.LayerNorm(dim)
        hidden = int(dim * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))
        mask = shifted_window_mask(*hw, window, shift) if shift else None
        self.register_buffer("mask", mask, persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        _, h, w, _ = x.shape
        y = self.norm1(x)
        if self.shift:
            y = torch.roll(y, (-self.shift, -self.shift), dims=(1, 2))
        y = merge(self.attn(partition(y, self.window), self.mask), h, w, self.window)
        if self.shift:
            y = torch.roll(y, (self.shift, self.shift), dims=(1, 2))
        x = x + y
        return x + self.mlp(self.norm2(x))


class SwinStage(nn.Sequential):
    """``depth`` Swin blocks alternating regular and shifted windows; the window is clipped to the map."""

    def __init__(self, dim: int, depth: int, heads: int, window: int, hw: tuple[int, int], mlp_ratio: float):
        window = min(window, *hw)
        shift = window // 2 if window < min(hw) else 0
        super().__init__(*(SwinBlock(dim, heads, window, shift if i % 2 else 0, hw, mlp_ratio) for i in range(depth)))
