"""How a scene tokenizer uses its codebook over a whole split (DDP-summed code counts)."""

from __future__ import annotations

import torch
from torchmetrics import Metric


class CodebookUsage(Metric):
    """Code counts of one codebook: ``usage`` is the percentage of its codes used at least
    once, ``perplexity`` the exponential of the entropy of the code distribution (the
    number of equally used codes it is worth). Counted over every update, unlike the
    per-batch figures a quantizer logs in training."""

    full_state_update = False
    counts: torch.Tensor

    def __init__(self, num_codes: int, **kwargs):
        super().__init__(**kwargs)
        self.num_codes = int(num_codes)
        self.add_state("counts", default=torch.zeros(self.num_codes, dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, codes: torch.Tensor) -> None:
        self.counts += torch.bincount(codes.reshape(-1).long(), minlength=self.num_codes).to(self.counts)

    def compute(self) -> dict[str, float]:
        total = self.counts.sum().clamp_min(1.0)
        probs = self.counts / total
        entropy = -(probs * probs.clamp_min(1e-30).log()).sum()
        return {"usage": float(100.0 * (self.counts > 0).double().mean()), "perplexity": float(entropy.exp())}
