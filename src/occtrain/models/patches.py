"""Patches of a 2D grid as tokens: the one place their layout lives.

A (C, h, w) grid is cut into p x p patches in row-major order; a patch's values are its cells
in row-major order with the channels innermost. Occ-LLM's scene tokens and the vision
stage's dense head (which unpatchifies per-patch predictions back to pixels) share it.
"""

from __future__ import annotations

import torch

from occtrain.errors import ConfigError


def check_patch(hw: tuple[int, int], patch: int) -> None:
    """A one-line error unless ``patch`` divides both sides of the latent grid."""
    if patch < 1 or hw[0] % patch or hw[1] % patch:
        raise ConfigError(f"patch size {patch} must divide the latent grid {hw[0]} x {hw[1]} (e.g. 10 for 50 x 50)")


def patchify(latents: torch.Tensor, patch: int) -> torch.Tensor:
    """(B, C, h, w) -> (B, N, p * p * C) with N = (h / p) * (w / p) patches in row-major order;
    each patch's cells in row-major order, channels innermost."""
    b, c, h, w = latents.shape
    check_patch((h, w), patch)
    x = latents.reshape(b, c, h // patch, patch, w // patch, patch)
    return x.permute(0, 2, 4, 3, 5, 1).reshape(b, (h // patch) * (w // patch), patch * patch * c)


def unpatchify(tokens: torch.Tensor, patch: int, hw: tuple[int, int]) -> torch.Tensor:
    """Inverse of :func:`patchify`: (B, N, p * p * C) -> (B, C, h, w)."""
    h, w = hw
    check_patch(hw, patch)
    b, n, d = tokens.shape
    c = d // (patch * patch)
    x = tokens.reshape(b, h // patch, w // patch, patch, patch, c)
    return x.permute(0, 5, 1, 3, 2, 4).reshape(b, c, h, w)
