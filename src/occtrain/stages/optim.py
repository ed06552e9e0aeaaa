"""The optimizer every stage uses (AdamW, warm-up then cosine or constant) and parameter freezing."""

from __future__ import annotations

import math
from typing import Any

import torch
from lightning.pytorch.utilities.types import OptimizerLRSchedulerConfig

from occtrain.config.recipe import OptimConfig
from occtrain.errors import OcctrainError


def configure_adamw(params: Any, cfg: OptimConfig, max_steps: int) -> OptimizerLRSchedulerConfig:
    """AdamW with linear warm-up and cosine decay to ``min_lr_ratio`` (or constant), per step."""
    betas = (cfg.betas[0], cfg.betas[1])  # two, checked with the recipe
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay, betas=betas, eps=cfg.eps)
    if cfg.schedule not in ("cosine", "constant"):
        raise OcctrainError(f"optim.schedule '{cfg.schedule}' is not one of cosine, constant")

    def factor(step: int) -> float:
        if cfg.warmup_steps and step < cfg.warmup_steps:
            return (step + 1) / cfg.warmup_steps
        if cfg.schedule == "constant" or max_steps <= cfg.warmup_steps:
            return 1.0
        progress = min(1.0, (step - cfg.warmup_steps) / max(1, max_steps - cfg.warmup_steps))
        return cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
    return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}


def freeze_prefixes(module: torch.nn.Module, prefixes: list[str]) -> int:
    """Freeze parameters whose names start with any prefix; returns how many tensors were frozen."""
    n = 0
    for name, p in module.named_parameters():
        if any(name.startswith(pre) for pre in prefixes):
            p.requires_grad_(False)
            n += 1
    if prefixes and n == 0:
        raise OcctrainError(f"freeze: no parameter name starts with {', '.join(prefixes)}")
    return n
