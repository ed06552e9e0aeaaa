"""Occ-LLM's scene tokens (Sec. III-B): latent patches, and pre-fusion of the ego action.

A scene's latent grid (C, h, w) is cut into p x p patches, each one LLM token (p = 10 gives
25 tokens per 50 x 50 frame). The paper does not say how the LLM emits a patch; here each
patch token's hidden state goes through one linear head to every cell's code in each
codebook (a cross-entropy per cell and codebook). Pre-fusion (Table V): the ego action
through an MLP to an SE-style per-channel gate on the latents before they are patchified.
"""

from __future__ import annotations

import torch
from torch import nn

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


class PatchEmbedding(nn.Module):
    """Latent patches (B, N, p * p * C) -> LLM input embeddings (B, N, hidden)."""

    def __init__(self, channels: int, patch: int, hidden: int):
        super().__init__()
        self.proj = nn.Sequential(nn.LayerNorm(patch * patch * channels), nn.Linear(patch * patch * channels, hidden))

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        return self.proj(patches)


class PatchHead(nn.Module):
    """A patch token's hidden state (B, N, hidden) -> per-cell code logits of each codebook:
    a list, one (B, N, p * p, K_i) tensor per codebook."""

    def __init__(self, hidden: int, patch: int, codebook_sizes: list[int]):
        super().__init__()
        self.cells = patch * patch
        self.sizes = list(codebook_sizes)
        self.proj = nn.Linear(hidden, self.cells * sum(self.sizes))

    def forward(self, hidden: torch.Tensor) -> list[torch.Tensor]:
        b, n, _ = hidden.shape
        out = self.proj(hidden).view(b, n, self.cells, sum(self.sizes))
        return list(out.split(self.sizes, dim=-1))


class PreFusion(nn.Module):
    """The ego action (B, A) -> a per-channel gate in (0, 2) applied to latents (B, C, h, w).

    SE-style: an MLP to C gate logits, 2 * sigmoid so a zero-initialised last layer starts at
    the identity (gate 1) and training moves away from it only as far as the action helps.
    """

    def __init__(self, action_dim: int, channels: int, hidden: int = 64):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(action_dim, hidden), nn.GELU(), nn.Linear(hidden, channels))
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, latents: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        gate = 2.0 * torch.sigmoid(self.mlp(action))  # (B, C)
        return latents * gate[:, :, None, None]
