"""Dense per-pixel scores of camera images: semantic segmentation IoU and depth AbsRel.

Both keep sums over the dataset (a confusion matrix; an error sum and a pixel count), so
they reduce across DDP processes by summation and score a split exactly as one process.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric

from occtrain.formats.occ3d import CLASS_NAMES, NUM_CLASSES
from occtrain.metrics.occupancy import confusion_matrix


class PixelSegmentationMetric(Metric):
    """Per-pixel IoU of the 18 Occ3D labels (17 = free: sky, no surface) and their mean.

    ``update(pred, target)`` takes label maps of any equal shape. ``compute()`` returns
    ``mIoU`` (percent) over the classes present in the ground truth of everything seen,
    and ``per_class`` (name -> IoU %) for those classes only; a class only predicted
    counts against the classes it was confused with, not as a term of its own.
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False
    confmat: Tensor

    def __init__(self, **kwargs: Any):
        super().__init__(**kwargs)
        self.add_state("confmat", torch.zeros(NUM_CLASSES, NUM_CLASSES, dtype=torch.long), dist_reduce_fx="sum")

    def update(self, pred: Tensor, target: Tensor) -> None:
        self.confmat += confusion_matrix(pred, target)

    def compute(self) -> dict[str, Any]:
        cm = self.confmat.double()
        tp, gt, pr = cm.diagonal(), cm.sum(1), cm.sum(0)
        present = (gt > 0).nonzero().flatten().tolist()
        iou = 100.0 * tp / (gt + pr - tp).clamp(min=1)
        per_class = {CLASS_NAMES[c]: iou[c] for c in present}
        miou = iou[present].mean() if present else torch.tensor(float("nan"), dtype=torch.float64)
        return {"mIoU": miou, "per_class": per_class}


class DepthAbsRelMetric(Metric):
    """Mean absolute relative depth error ``|d - d*| / d*`` over the pixels with ground-truth depth (d* > 0)."""

    is_differentiable = False
    higher_is_better = False
    full_state_update = False
    error_sum: Tensor
    pixels: Tensor

    def __init__(self, **kwargs: Any):
        super().__init__(**kwargs)
        self.add_state("error_sum", torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("pixels", torch.zeros((), dtype=torch.long), dist_reduce_fx="sum")

    def update(self, pred: Tensor, target: Tensor) -> None:
        if pred.shape != target.shape:
            raise ValueError(f"prediction shape {tuple(pred.shape)} differs from target shape {tuple(target.shape)}")
        valid = target > 0
        d, t = pred[valid].double(), target[valid].double()
        self.error_sum += ((d - t).abs() / t).sum()
        self.pixels += valid.sum()

    def compute(self) -> Tensor:
        return self.error_sum / self.pixels if self.pixels > 0 else torch.tensor(float("nan"), dtype=torch.float64)
