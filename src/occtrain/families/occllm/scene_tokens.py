"""Occ-LLM's scene tokens (Sec. III-B): latent patches, and pre-fusion of the ego action.

A scene's latent grid (C, h, w) is cut into p x p patches (``occtrain.models.patches``),
each one LLM token (p = 10 gives 25 tokens per 50 x 50 frame). The paper does not say how
the LLM emits a patch; here a patch token's hidden state goes through a head to every
cell's code in each codebook (a cross-entropy per cell and codebook). Pre-fusion (Table
V): the ego action through an MLP to an SE-style per-channel gate on the latents before
they are patchified (a per-channel gate commutes with cutting into patches).
"""

from __future__ import annotations

import torch
from torch import nn


class PatchEmbedding(nn.Module):
    """Latent patches (B, N, p * p * C) -> LLM input embeddings (B, N, hidden)."""

    def __init__(self, channels: int, patch: int, hidden: int):
        super().__init__()
        self.proj = nn.Sequential(nn.LayerNorm(patch * patch * channels), nn.Linear(patch * patch * channels, hidden))

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        return self.proj(patches)


class PatchHead(nn.Module):
    """A patch token's hidden state (B, N, hidden) -> per-cell code logits of each codebook:
    a list, one (B, N, p * p, K_i) tensor per codebook.

    Factored: the hidden state becomes a ``cell_dim`` vector per cell (position-specific
    weights), and one classifier per codebook, shared by the cells, scores it. A direct
    hidden -> p*p*K layer would need 400 M weights at the paper's p = 10, K = 512 x 2.
    """

    def __init__(self, hidden: int, patch: int, codebook_sizes: list[int], cell_dim: int = 64):
        super().__init__()
        self.cells = patch * patch
        self.cell_dim = cell_dim
        self.to_cells = nn.Sequential(nn.Linear(hidden, self.cells * cell_dim), nn.GELU())
        self.norm = nn.LayerNorm(cell_dim)
        self.classify = nn.ModuleList(nn.Linear(cell_dim, k) for k in codebook_sizes)

    def forward(self, hidden: torch.Tensor) -> list[torch.Tensor]:
        cells = self.norm(self.to_cells(hidden).unflatten(-1, (self.cells, self.cell_dim)))
        return [classify(cells) for classify in self.classify]


class PreFusion(nn.Module):
    """The ego action (B, A) -> a per-channel gate in (0, 2) applied to latents (B, C, ...).

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
        return latents * gate.view(*gate.shape, *([1] * (latents.dim() - 2)))
