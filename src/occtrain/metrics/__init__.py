"""torchmetrics Metrics that reproduce the papers' reference evaluation code, DDP-synchronised.

Every result names its convention: occupancy ``occ3d`` / ``occworld``, planning
``stp3`` / ``uniad`` keys, caption keys as pycocoevalcap spells them.
"""

from occtrain.metrics.captions import CAPTION_KEYS, CaptionMetric, coco_caption_scores
from occtrain.metrics.occupancy import CONVENTIONS, ForecastMetric, OccupancyMetric, confusion_matrix, horizon_label
from occtrain.metrics.planning import PlanningMetric
from occtrain.metrics.qa import QAMetric

__all__ = [
    "CAPTION_KEYS",
    "CONVENTIONS",
    "CaptionMetric",
    "ForecastMetric",
    "OccupancyMetric",
    "PlanningMetric",
    "QAMetric",
    "coco_caption_scores",
    "confusion_matrix",
    "horizon_label",
]
