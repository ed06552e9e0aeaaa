"""Semantic occupancy IoU/mIoU in the Occ3D and the OccWorld conventions, and per-horizon forecasting.

Both conventions are read off one 18x18 confusion matrix (rows: ground truth, columns:
prediction) summed over the dataset, so a single state reduces across DDP processes by
summation. They differ in which voxels count and in what a class with no ground truth
contributes:

* ``occ3d`` (CVPR 2023 Occ3D challenge, ``Metric_mIoU``): only voxels where ``mask_camera``
  is true count (unless ``use_mask=False``); per-class IoU = TP / (TP + FP + FN), which is
  0/0 = NaN for a class absent from both prediction and ground truth; mIoU is the NaN-mean
  over classes 0-16 (a class predicted but absent from the ground truth scores 0).
  The challenge code prints nothing for geometry; IoU here is occupied (class != 17) vs
  free over the same voxels, NaN when neither side has an occupied voxel.
* ``occworld`` (OccWorld ``utils/metric_util.py``, ``MeanIoU``): every voxel counts (its
  ignore label is never met); a class with no ground-truth voxel scores IoU 1 (100 %),
  even when it was predicted; mIoU is the plain mean over classes 0-16. IoU is the same
  rule on the binary occupied-vs-free labels.

Values are percent, unrounded (the reference scripts print them rounded to 2 decimals).
``per_class`` names classes by their label (``occtrain.formats.occ3d.CLASS_NAMES``); the challenge
script prints classes 1-10 under names in another order (car, truck, ... for labels 1-10).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric

from occtrain.formats.occ3d import CLASS_NAMES, FREE, NUM_CLASSES
from occtrain.metrics.conventions import CONVENTIONS, OCC3D, OCCWORLD, horizon_label  # noqa: F401 (theirs)

#: The two occupancy conventions (see the module docstring), by name.


def confusion_matrix(pred: Tensor, target: Tensor, mask: Tensor | None = None) -> Tensor:
    """18x18 int64 counts of (ground truth, prediction) label pairs over the voxels in ``mask``."""
    if pred.shape != target.shape:
        raise ValueError(f"prediction shape {tuple(pred.shape)} differs from target shape {tuple(target.shape)}")
    pred, target = pred.long(), target.long()
    if mask is not None:
        if mask.shape != target.shape:
            raise ValueError(f"mask shape {tuple(mask.shape)} differs from target shape {tuple(target.shape)}")
        keep = mask.bool()
        pred, target = pred[keep], target[keep]
    for name, labels in (("prediction", pred), ("target", target)):
        if labels.numel() and (int(labels.min()) < 0 or int(labels.max()) >= NUM_CLASSES):
            raise ValueError(f"{name} holds labels outside 0..{NUM_CLASSES - 1}")
    flat = (target * NUM_CLASSES + pred).reshape(-1)
    return torch.bincount(flat, minlength=NUM_CLASSES * NUM_CLASSES).reshape(NUM_CLASSES, NUM_CLASSES)


def _binary_counts(confmat: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(TP, FP, FN) of the occupied-vs-free split of a confusion matrix."""
    occ = slice(0, FREE)
    tp = confmat[occ, occ].sum()
    fp = confmat[FREE, occ].sum()  # free in the ground truth, predicted occupied
    fn = confmat[occ, FREE].sum()
    return tp, fp, fn


def scores_from_confmat(confmat: Tensor, convention: str) -> dict[str, Any]:
    """mIoU, IoU and per-class IoU (percent, float64) of a summed confusion matrix."""
    cm = confmat.double()
    tp = cm.diagonal()[:FREE]
    gt = cm.sum(1)[:FREE]
    pred = cm.sum(0)[:FREE]
    union = gt + pred - tp
    btp, bfp, bfn = (x.double() for x in _binary_counts(confmat))
    if convention == "occ3d":
        per_class = tp / union  # 0/0 -> NaN: absent from both sides, skipped by the NaN-mean
        miou = per_class.nanmean()
        iou = btp / (btp + bfp + bfn)
    elif convention == "occworld":
        per_class = torch.where(gt > 0, tp / union, torch.ones_like(tp))
        miou = per_class.mean()
        iou = btp / (btp + bfp + bfn) if btp + bfn > 0 else torch.ones((), dtype=torch.float64)
    else:
        raise ValueError(f"unknown convention '{convention}'; expected one of {', '.join(CONVENTIONS)}")
    return {
        "mIoU": 100.0 * miou,
        "IoU": 100.0 * iou,
        "per_class": {name: 100.0 * per_class[i] for i, name in enumerate(CLASS_NAMES[:FREE])},
    }


def subset_miou(confmat: Tensor, classes: tuple[str, ...]) -> Tensor:
    """Mean IoU (percent) over ``classes`` that occur in the ground truth: e.g. the movable
    classes, where a motion-separated tokenizer should gain. NaN when none occurs."""
    cm = confmat.double()
    idx = torch.tensor([CLASS_NAMES.index(c) for c in classes], device=cm.device)
    tp, gt, pred = cm.diagonal()[idx], cm.sum(1)[idx], cm.sum(0)[idx]
    present = gt > 0
    return (
        100.0 * (tp[present] / (gt + pred - tp)[present]).mean() if bool(present.any()) else torch.tensor(float("nan"))
    )


class OccupancyMetric(Metric):
    """Semantic occupancy mIoU / IoU over a dataset, in the ``occ3d`` or ``occworld`` convention.

    ``update(pred, target, mask=None)`` takes label volumes ``[B, X, Y, Z]`` (class 17 = free);
    ``mask`` is ``mask_camera`` and is required by ``occ3d`` with ``use_mask=True``, refused
    by ``occworld`` (which counts every voxel). ``compute()`` returns ``convention``,
    ``mIoU``, ``IoU`` (percent, 0-dim float64 tensors), ``per_class`` (class name -> IoU %)
    and ``samples``; with ``subsets`` (name -> class names) also ``<name>_mIoU`` over the
    classes of each that occur (``subset_miou``). See the module docstring for the two
    conventions' rules.
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False
    confmat: Tensor
    samples: Tensor

    def __init__(
        self,
        convention: str = "occ3d",
        use_mask: bool = True,
        subsets: dict[str, tuple[str, ...]] | None = None,
        **kwargs: Any,
    ):
        super().__init__(**kwargs)
        self.subsets = dict(subsets or {})
        if convention not in CONVENTIONS:
            raise ValueError(f"unknown convention '{convention}'; expected one of {', '.join(CONVENTIONS)}")
        self.convention = convention
        self.use_mask = use_mask and convention == "occ3d"
        self.add_state("confmat", torch.zeros(NUM_CLASSES, NUM_CLASSES, dtype=torch.long), dist_reduce_fx="sum")
        self.add_state("samples", torch.zeros((), dtype=torch.long), dist_reduce_fx="sum")

    def update(self, pred: Tensor, target: Tensor, mask: Tensor | None = None) -> None:
        if self.convention == "occworld" and mask is not None:
            raise ValueError("the occworld convention counts every voxel; pass no mask (or use convention='occ3d')")
        if self.use_mask and mask is None:
            raise ValueError("the occ3d convention needs mask_camera; pass it, or build the metric with use_mask=False")
        self.confmat += confusion_matrix(pred, target, mask if self.use_mask else None)
        self.samples += pred.shape[0]

    def compute(self) -> dict[str, Any]:
        result = scores_from_confmat(self.confmat, self.convention)
        # Here the state is the one summed over every process (torchmetrics syncs it for compute).
        subsets = {f"{name}_mIoU": subset_miou(self.confmat, classes) for name, classes in self.subsets.items()}
        return {"convention": self.convention, **result, **subsets, "samples": self.samples.clone()}


class ForecastMetric(Metric):
    """Occupancy forecasting mIoU / IoU per future horizon, OccWorld convention.

    ``update(pred, target, valid=None)`` takes future label volumes ``[B, T, X, Y, Z]`` and,
    optionally, ``valid [B, T]`` (False for frames past a scene's end, which are not
    counted; OccWorld itself evaluates only samples with a full future). Each horizon
    (future frame index; 1, 3, 5 are 1 s, 2 s, 3 s) accumulates its own confusion matrix
    over all voxels, scored with the ``occworld`` rules of :class:`OccupancyMetric`;
    ``avg`` is the mean over the horizons, as OccWorld's evaluation prints it. With
    ``subsets`` (name -> class names), also ``<name>_mIoU`` per horizon (``subset_miou``).
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False
    #: One confusion matrix and one frame count per horizon.
    confmat: Tensor
    frames: Tensor

    def __init__(
        self, horizons: tuple[int, ...] = (1, 3, 5), subsets: dict[str, tuple[str, ...]] | None = None, **kwargs: Any
    ):
        super().__init__(**kwargs)
        self.subsets = dict(subsets or {})
        if not horizons or min(horizons) < 0:
            raise ValueError(f"horizons must be non-empty future frame indices, got {horizons}")
        self.horizons = tuple(int(h) for h in horizons)
        n = len(self.horizons)
        self.add_state("confmat", torch.zeros(n, NUM_CLASSES, NUM_CLASSES, dtype=torch.long), dist_reduce_fx="sum")
        self.add_state("frames", torch.zeros(n, dtype=torch.long), dist_reduce_fx="sum")

    def update(self, pred: Tensor, target: Tensor, valid: Tensor | None = None) -> None:
        if pred.shape != target.shape or pred.dim() < 3:
            raise ValueError(
                f"prediction {tuple(pred.shape)} and target {tuple(target.shape)} must both be [B, T, X, Y, Z]"
            )
        if pred.shape[1] <= max(self.horizons):
            raise ValueError(f"forecast has {pred.shape[1]} frames; horizon index {max(self.horizons)} needs more")
        if valid is not None and tuple(valid.shape) != tuple(pred.shape[:2]):
            raise ValueError(f"valid has shape {tuple(valid.shape)}, expected {tuple(pred.shape[:2])}")
        for i, h in enumerate(self.horizons):
            keep = None if valid is None else valid[:, h].bool()
            p, t = (pred[:, h], target[:, h]) if keep is None else (pred[keep, h], target[keep, h])
            self.confmat[i] += confusion_matrix(p, t)
            self.frames[i] += p.shape[0]

    def compute(self) -> dict[str, Any]:
        scores = [scores_from_confmat(cm, "occworld") for cm in self.confmat]
        out: dict[str, Any] = {"convention": "occworld"}
        for key in ("mIoU", "IoU"):
            values = {horizon_label(h): s[key] for h, s in zip(self.horizons, scores)}
            values["avg"] = torch.stack([s[key] for s in scores]).mean()
            out[key] = values
        for name, classes in self.subsets.items():
            values = {horizon_label(h): subset_miou(cm, classes) for h, cm in zip(self.horizons, self.confmat)}
            values["avg"] = torch.stack(list(values.values())).nanmean()
            out[f"{name}_mIoU"] = values
        out["frames"] = {horizon_label(h): n.clone() for h, n in zip(self.horizons, self.frames)}
        return out
