"""Occ-LLM's scene tokens (Sec. III-B): latent patches, and pre-fusion of the ego action.

A scene's latent grid (C, h, w) is cut into p x p patches (``occtrain.models.patches``),
each one LLM token (p = 10 gives 25 tokens per 50 x 50 frame): the joint vocabulary's
patches layout, which other families read too (``core.patch_layout``: the patch embedding,
and the head through which a patch token's hidden state gives every cell's code in each
codebook; the paper does not say how the LLM emits a patch). Pre-fusion (Table V), Occ-LLM's
own: the ego action through an MLP to an SE-style per-channel gate on the latents before
they are patchified (a per-channel gate commutes with cutting into patches).
"""

from __future__ import annotations

import torch
from torch import nn


class PreFusion(nn.Module):
    """The ego action (B, A) -> a per-channel gate in (0, 2) applied to latents (B, C, ...).

    SE-style: an MLP to C gate logits, 2 * sigmoid so a zero-initialised last layer starts at
    the identity (gate 1) and training moves away from it only as far as the action helps.
    """

    def __init__(self, action_dim: int, channels: int, hidden: int = 64):
        super().__init__()
        first, last = nn.Linear(action_dim, hidden), nn.Linear(hidden, channels)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.mlp = nn.Sequential(first, nn.GELU(), last)

    def forward(self, latents: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        gate = 2.0 * torch.sigmoid(self.mlp(action))  # (B, C)
        return latents * gate.view(*gate.shape, *([1] * (latents.dim() - 2)))
