"""2D convolutional encoder/decoder of the OccWorld layout (ResNet blocks, attention at the latent).

Levels are joined by arbitrary integer strides rather than fixed factors of two, so one
layout serves the paper's 200 -> 50 latent and a CPU recipe's 200 -> 10.
"""

from __future__ import annotations

from typing import TypedDict

import torch
import torch.nn.functional as F
from torch import nn


def group_norm(channels: int) -> nn.GroupNorm:
    """GroupNorm with 32 groups, or 4 channels per group for narrow layers."""
    groups = 32 if channels > 32 else max(1, channels // 4)
    return nn.GroupNorm(groups, channels, eps=1e-6)


class ResnetBlock(nn.Module):
    """Pre-activation residual block: (GroupNorm, SiLU, conv3x3) twice, 1x1 shortcut if widths differ."""

    def __init__(self, in_ch: int, out_ch: int):
        super().__init__()
        self.body = nn.Sequential(
            group_norm(in_ch), nn.SiLU(), nn.Conv2d(in_ch, out_ch, 3, padding=1),
            group_norm(out_ch), nn.SiLU(), nn.Conv2d(out_ch, out_ch, 3, padding=1),
        )  # fmt: skip
        self.shortcut = nn.Conv2d(in_ch, out_ch, 1) if in_ch != out_ch else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.shortcut(x) + self.body(x)


class AttnBlock(nn.Module):
    """Single-head self-attention over all positions of a feature map, residual."""

    def __init__(self, ch: int):
        super().__init__()
        self.norm = group_norm(ch)
        self.qkv = nn.Conv2d(ch, 3 * ch, 1)
        self.proj = nn.Conv2d(ch, ch, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        q, k, v = self.qkv(self.norm(x)).flatten(2).transpose(1, 2).chunk(3, dim=-1)  # (B, hw, C) each
        out = F.scaled_dot_product_attention(q, k, v)
        return x + self.proj(out.transpose(1, 2).reshape(b, c, h, w))


def strided_conv(in_ch: int, out_ch: int, stride: int) -> nn.Conv2d:
    """Conv with an odd kernel >= stride and 'same'-style padding: exactly divides the side by ``stride``."""
    kernel = 2 * (stride // 2) + 1
    return nn.Conv2d(in_ch, out_ch, kernel, stride=stride, padding=kernel // 2)


class Upsample(nn.Module):
    """Nearest-neighbour upsampling by ``stride`` followed by a 3x3 conv."""

    def __init__(self, ch: int, stride: int):
        super().__init__()
        self.stride = stride
        self.conv = nn.Conv2d(ch, ch, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.interpolate(x, scale_factor=self.stride, mode="nearest"))


def _level_stack(in_ch: int, out_ch: int, blocks: int, attention: bool) -> tuple[nn.ModuleList, int]:
    layers = nn.ModuleList()
    for _ in range(blocks):
        layers.append(ResnetBlock(in_ch, out_ch))
        in_ch = out_ch
        if attention:
            layers.append(AttnBlock(out_ch))
    return layers, out_ch


def _middle(ch: int, attention: bool) -> nn.Sequential:
    return nn.Sequential(ResnetBlock(ch, ch), AttnBlock(ch) if attention else nn.Identity(), ResnetBlock(ch, ch))


class ConvLayout(TypedDict):
    """A :class:`ConvEncoder`'s shape besides its in and out channels (its mirror
    :class:`ConvDecoder` takes the same)."""

    ch: int
    channel_mult: list[int]
    strides: list[int]
    num_res_blocks: int
    latent_attention: bool


class ConvEncoder(nn.Module):
    """(B, in_ch, H, W) -> (B, out_ch, H / prod(strides), W / prod(strides))."""

    def __init__(self, in_ch: int, ch: int, channel_mult: list[int], strides: list[int], num_res_blocks: int,
                 latent_attention: bool, out_ch: int):  # fmt: skip
        super().__init__()
        self.conv_in = nn.Conv2d(in_ch, ch, 3, padding=1)
        self.levels = nn.ModuleList()
        block_in = ch
        last = len(channel_mult) - 1
        for i, mult in enumerate(channel_mult):
            stack, block_in = _level_stack(block_in, ch * mult, num_res_blocks, latent_attention and i == last)
            if i < last:
                stack.append(strided_conv(block_in, block_in, strides[i]))
            self.levels.append(stack)
        self.mid = _middle(block_in, latent_attention)
        self.out = nn.Sequential(group_norm(block_in), nn.SiLU(), nn.Conv2d(block_in, out_ch, 3, padding=1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv_in(x)
        for stack in self.levels:
            for layer in stack.children():
                h = layer(h)
        return self.out(self.mid(h))


class ConvDecoder(nn.Module):
    """Mirror of :class:`ConvEncoder`: (B, in_ch, h, w) -> (B, out_ch, h * prod(strides), w * prod(strides))."""

    def __init__(self, in_ch: int, ch: int, channel_mult: list[int], strides: list[int], num_res_blocks: int,
                 latent_attention: bool, out_ch: int):  # fmt: skip
        super().__init__()
        last = len(channel_mult) - 1
        block_in = ch * channel_mult[last]
        self.conv_in = nn.Conv2d(in_ch, block_in, 3, padding=1)
        self.mid = _middle(block_in, latent_attention)
        self.levels = nn.ModuleList()
        for i in reversed(range(len(channel_mult))):
            stack, block_in = _level_stack(
                block_in, ch * channel_mult[i], num_res_blocks, latent_attention and i == last
            )
            if i > 0:
                stack.append(Upsample(block_in, strides[i - 1]))
            self.levels.append(stack)
        self.out = nn.Sequential(group_norm(block_in), nn.SiLU(), nn.Conv2d(block_in, out_ch, 3, padding=1))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        h = self.mid(self.conv_in(z))
        for stack in self.levels:
            for layer in stack.children():
                h = layer(h)
        return self.out(h)
