"""torchmetrics Metrics that reproduce the papers' reference evaluation code, DDP-synchronised.

Every result names its convention: occupancy ``occ3d`` / ``occworld``, planning
``stp3`` / ``uniad`` keys, caption keys as pycocoevalcap spells them.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import Any

from occtrain.metrics.conventions import CONVENTIONS, horizon_label

#: Each metric's module. Loaded when first used: torchmetrics takes seconds to import, and
#: the commands that only name a convention (the CLI's parser, the dashboard) need none.
_MODULES = {
    "CAPTION_KEYS": "captions",
    "CaptionMetric": "captions",
    "coco_caption_scores": "captions",
    "CodebookUsage": "codebook",
    "MetaActionAccuracy": "meta_action",
    "ForecastMetric": "occupancy",
    "OccupancyMetric": "occupancy",
    "confusion_matrix": "occupancy",
    "DepthAbsRelMetric": "pixels",
    "PixelSegmentationMetric": "pixels",
    "PlanningMetric": "planning",
    "QAMetric": "qa",
}

__all__ = ["CONVENTIONS", "compute_metrics", "flatten_metrics", "horizon_label", "updated_anywhere", *_MODULES]


def __getattr__(name: str) -> Any:
    if name in _MODULES:
        return getattr(importlib.import_module(f"occtrain.metrics.{_MODULES[name]}"), name)
    raise AttributeError(f"module 'occtrain.metrics' has no attribute {name!r}")


def flatten_metrics(prefix: str, result: dict[str, Any]) -> dict[str, float]:
    """``("val/plan", {"L2_stp3": {"1s": .5}})`` -> ``{"val/plan_L2_stp3_1s": .5}``.

    Non-numeric values (the convention labels) are left out: the names carry them.
    """
    import torch

    flat: dict[str, float] = {}
    for key, value in result.items():
        name = f"{prefix}_{key}"
        if isinstance(value, dict):
            flat.update(flatten_metrics(name, value))
        elif isinstance(value, (int, float)) or (torch.is_tensor(value) and value.numel() == 1):
            flat[name] = float(value)
    return flat


def updated_anywhere(metrics: list[Any]) -> list[bool]:
    """Which of ``metrics`` saw a sample on any process. Under DDP every ``compute`` is a
    collective, so the processes must agree on which to compute: a process that saw no
    sample of a task (fewer items than ranks, or an answer only some ranks parse) still
    joins, with empty states, or the others wait on it for ever."""
    import torch
    import torch.distributed as dist

    seen = [bool(m.update_count) for m in metrics]
    if metrics and dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
        flags = torch.tensor(seen, dtype=torch.float32, device=metrics[0].device)
        dist.all_reduce(flags, op=dist.ReduceOp.MAX)
        seen = [bool(f) for f in flags.tolist()]
    return seen


def compute_metrics(prefix: str, metrics: Mapping[str, Any], reset: bool = False) -> dict[str, float]:
    """Every metric of ``metrics`` that saw samples on any process, flattened under
    ``prefix/name`` (a scalar metric's value is ``prefix/name`` itself; no prefix: ``name``); with ``reset``,
    all are reset afterwards. Every process must call it (see :func:`updated_anywhere`)."""
    import warnings

    out: dict[str, float] = {}
    for (name, metric), seen in zip(metrics.items(), updated_anywhere(list(metrics.values()))):
        if seen:
            with warnings.catch_warnings():  # this process saw none; the others did
                warnings.filterwarnings("ignore", message=".*was called before the ``update`` method.*")
                value = metric.compute()
            key = f"{prefix}/{name}" if prefix else name
            out.update(flatten_metrics(key, value) if isinstance(value, dict) else {key: float(value)})
        if reset:
            metric.reset()
    return out
