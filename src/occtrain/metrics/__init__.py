"""torchmetrics Metrics that reproduce the papers' reference evaluation code, DDP-synchronised.

Every result names its convention: occupancy ``occ3d`` / ``occworld``, planning
``stp3`` / ``uniad`` keys, caption keys as pycocoevalcap spells them.
"""

from __future__ import annotations

from typing import Any

import torch

from occtrain.metrics.captions import CAPTION_KEYS, CaptionMetric, coco_caption_scores
from occtrain.metrics.codebook import CodebookUsage
from occtrain.metrics.meta_action import MetaActionAccuracy
from occtrain.metrics.occupancy import CONVENTIONS, ForecastMetric, OccupancyMetric, confusion_matrix, horizon_label
from occtrain.metrics.pixels import DepthAbsRelMetric, PixelSegmentationMetric
from occtrain.metrics.planning import PlanningMetric
from occtrain.metrics.qa import QAMetric

__all__ = [
    "CAPTION_KEYS",
    "CONVENTIONS",
    "CaptionMetric",
    "CodebookUsage",
    "DepthAbsRelMetric",
    "ForecastMetric",
    "MetaActionAccuracy",
    "OccupancyMetric",
    "PixelSegmentationMetric",
    "PlanningMetric",
    "QAMetric",
    "coco_caption_scores",
    "confusion_matrix",
    "flatten_metrics",
    "horizon_label",
]



def flatten_metrics(prefix: str, result: dict[str, Any]) -> dict[str, float]:
    """``("val/plan", {"L2_stp3": {"1s": .5}})`` -> ``{"val/plan_L2_stp3_1s": .5}``.

    Non-numeric values (the convention labels) are left out: the names carry them.
    """
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
