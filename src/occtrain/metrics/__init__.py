"""torchmetrics Metrics that reproduce the papers' reference evaluation code, DDP-synchronised.

Every result names its convention: occupancy ``occ3d`` / ``occworld``, planning
``stp3`` / ``uniad`` keys, caption keys as pycocoevalcap spells them.
"""

from __future__ import annotations

import importlib
from typing import Any

from occtrain.metrics.conventions import CONVENTIONS, horizon_label

#: Each metric's module. Loaded when first used: torchmetrics takes seconds to import, and
#: the commands that only name a convention (the CLI's parser, the dashboard) need none.
_MODULES = {
    "CAPTION_KEYS": "captions", "CaptionMetric": "captions", "coco_caption_scores": "captions",
    "CodebookUsage": "codebook", "MetaActionAccuracy": "meta_action",
    "ForecastMetric": "occupancy", "OccupancyMetric": "occupancy", "confusion_matrix": "occupancy",
    "DepthAbsRelMetric": "pixels", "PixelSegmentationMetric": "pixels",
    "PlanningMetric": "planning", "QAMetric": "qa",
}

__all__ = ["CONVENTIONS", "compute_and_reset", "flatten_metrics", "horizon_label", *_MODULES]


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


def compute_and_reset(prefix: str, metrics: dict[str, Any]) -> dict[str, float]:
    """Every metric of ``metrics`` that saw samples, flattened under ``prefix/name``; all are
    reset. A scalar metric's value is ``prefix/name`` itself."""
    out: dict[str, float] = {}
    for name, metric in metrics.items():
        if metric.update_count:
            value = metric.compute()
            out.update(flatten_metrics(f"{prefix}/{name}", value) if isinstance(value, dict) else {f"{prefix}/{name}": float(value)})
        metric.reset()
    return out
