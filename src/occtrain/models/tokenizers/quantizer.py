"""Vector quantizer: nearest-code lookup, straight-through gradients, EMA codebook, dead-code restart.

DDP: assignment counts and EMA sums are all-reduced, so every rank sees the same usage and
picks the same dead codes; the restart vectors are drawn on rank 0 and broadcast, so the
codebooks stay identical on all ranks. Nothing collective happens outside training mode,
nor when EMA and restart are both off.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import nn


@dataclass
class QuantizerOutput:
    """What one quantization returns: straight-through vectors, codes, loss and usage statistics."""

    z_q: torch.Tensor  # (B, D, h, w), gradients flow to the encoder output
    codes: torch.Tensor  # (B, h, w) long
    loss: torch.Tensor  # codebook + commitment (or commitment alone under EMA)
    stats: dict[str, torch.Tensor]


def _distributed() -> bool:
    return dist.is_available() and dist.is_initialized()


class VectorQuantizer(nn.Module):
    """K code vectors of dimension D with nearest-neighbour assignment (Euclidean).

    Without EMA the codebook is a parameter trained by ||sg(z) - e||^2; with EMA
    (``ema_decay > 0``) it is a buffer moved towards the mean of its assigned vectors.
    A code whose running count of assignments per batch (decay ``usage_decay``, starting
    at 1) drops below ``restart_threshold`` is moved onto a random encoder output of the
    current batch and its count reset to 1.
    """

    #: (K, D): a parameter, or with EMA a buffer like ``ema_count`` (K,) and ``ema_sum`` (K, D).
    embed: torch.Tensor
    ema_count: torch.Tensor
    ema_sum: torch.Tensor
    #: (K,) running assignments per batch.
    usage: torch.Tensor

    def __init__(
        self,
        num_codes: int,
        code_dim: int,
        beta: float = 1.0,
        ema_decay: float = 0.0,
        restart_threshold: float = 0.0,
        usage_decay: float = 0.99,
    ):
        super().__init__()
        self.num_codes = num_codes
        self.code_dim = code_dim
        self.beta = beta
        self.ema_decay = ema_decay
        self.restart_threshold = restart_threshold
        self.usage_decay = usage_decay
        init = torch.empty(num_codes, code_dim).uniform_(-1.0 / num_codes, 1.0 / num_codes)
        if ema_decay > 0:
            self.register_buffer("embed", init)
            # A count of one per code keeps unused codes where they are instead of dividing by ~0.
            self.register_buffer("ema_count", torch.ones(num_codes))
            self.register_buffer("ema_sum", init.clone())
        else:
            self.embed = nn.Parameter(init)
        self.register_buffer("usage", torch.ones(num_codes))

    @property
    def codebook(self) -> torch.Tensor:
        """The current code vectors (K, D)."""
        return self.embed

    def nearest(self, z: torch.Tensor) -> torch.Tensor:
        """Codes (B, h, w) of the nearest entries to z (B, D, h, w); no side effects."""
        flat = z.detach().movedim(1, -1).reshape(-1, self.code_dim)
        return self._assign(flat).view(z.shape[0], *z.shape[2:])

    def lookup(self, codes: torch.Tensor) -> torch.Tensor:
        """Code vectors (B, D, h, w) of codes (B, h, w)."""
        return F.embedding(codes, self.embed).movedim(-1, 1)

    def _assign(self, flat: torch.Tensor) -> torch.Tensor:
        # float32 even under autocast: bf16 distances would tie or swap near codes
        with torch.autocast(flat.device.type, enabled=False):
            flat, embed = flat.float(), self.embed.detach().float()
            dist2 = flat.pow(2).sum(1, keepdim=True) - 2.0 * flat @ embed.t() + embed.pow(2).sum(1)
        return dist2.argmin(1)

    def forward(self, z: torch.Tensor) -> QuantizerOutput:
        """Quantize z (B, D, h, w); in training mode also update EMA statistics and restart dead codes."""
        # In float32 whatever the encoder's autocast dtype: the codebook, its EMA sums and the
        # commitment loss are float32 state, and bf16 would round the code distances.
        flat = z.movedim(1, -1).reshape(-1, self.code_dim).float()
        if self.training and self.restart_threshold > 0:
            self._restart_dead(flat.detach())
        codes = self._assign(flat.detach())
        quantized = F.embedding(codes, self.embed)
        commitment = F.mse_loss(flat, quantized.detach())
        if self.ema_decay > 0:
            loss = self.beta * commitment
        else:
            loss = F.mse_loss(quantized, flat.detach()) + self.beta * commitment
        counts = torch.bincount(codes, minlength=self.num_codes).to(flat.dtype)
        stats = self._stats(counts)
        if self.training and (self.ema_decay > 0 or self.restart_threshold > 0):
            self._update(flat.detach(), codes, counts)
        z_q = flat + (quantized - flat).detach()
        b, _, h, w = z.shape
        return QuantizerOutput(
            z_q=z_q.view(b, h, w, self.code_dim).permute(0, 3, 1, 2),
            codes=codes.view(b, h, w),
            loss=loss,
            stats=stats,
        )

    def _stats(self, counts: torch.Tensor) -> dict[str, torch.Tensor]:
        probs = counts / counts.sum().clamp_min(1.0)
        entropy = -(probs * probs.clamp_min(1e-12).log()).sum()
        return {
            "codebook_usage": (counts > 0).float().mean(),
            "perplexity": entropy.exp(),
        }

    @torch.no_grad()
    def _update(self, flat: torch.Tensor, codes: torch.Tensor, counts: torch.Tensor) -> None:
        counts = counts.clone()
        sums = torch.zeros_like(self.embed).index_add_(0, codes, flat) if self.ema_decay > 0 else None
        if _distributed():
            dist.all_reduce(counts)
            if sums is not None:
                dist.all_reduce(sums)
        self.usage.mul_(self.usage_decay).add_(counts, alpha=1.0 - self.usage_decay)
        if sums is not None:
            self.ema_count.mul_(self.ema_decay).add_(counts, alpha=1.0 - self.ema_decay)
            self.ema_sum.mul_(self.ema_decay).add_(sums, alpha=1.0 - self.ema_decay)
            self.embed.copy_(self.ema_sum / self.ema_count.clamp_min(1e-6).unsqueeze(1))

    @torch.no_grad()
    def _restart_dead(self, flat: torch.Tensor) -> None:
        dead = (self.usage < self.restart_threshold).nonzero().squeeze(1)
        if dead.numel() == 0:
            return
        picks = torch.randint(0, flat.shape[0], (dead.numel(),), device=flat.device)
        fresh = flat[picks].contiguous()
        if _distributed():
            dist.broadcast(fresh, src=0)
        self.embed.data[dead] = fresh
        self.usage[dead] = 1.0
        if self.ema_decay > 0:
            self.ema_count[dead] = 1.0
            self.ema_sum[dead] = fresh
