"""Reconstruction losses of the tokenizers: cross-entropy and Lovasz-softmax over voxels.

Lovasz-softmax (Berman et al., 2018) is the Lovasz extension of the Jaccard loss: for each
class, sort the per-voxel errors |[y = c] - p_c| in decreasing order and weight each by the
increase of the Jaccard loss when that voxel joins the error set. On a hard one-hot
prediction it equals 1 - IoU of that class, exactly.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from occtrain.formats.occ3d import FREE, NUM_CLASSES


def lovasz_softmax(probs: torch.Tensor, labels: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Mean Lovasz-softmax loss over the classes present in ``labels``.

    probs: (B, C, *spatial) class probabilities; labels: (B, *spatial) ints in [0, C);
    valid: optional bool mask (B, *spatial) of the voxels that count. All voxels of the
    batch form one set (OccWorld's convention, not per image). Zero when nothing is valid.
    """
    flat = probs.movedim(1, -1).reshape(-1, probs.shape[1])
    return _lovasz_flat(flat, labels.reshape(-1), None if valid is None else valid.reshape(-1))


def _lovasz_flat(probs: torch.Tensor, target: torch.Tensor, keep: torch.Tensor | None) -> torch.Tensor:
    """Lovasz-softmax of (N, C) probabilities and (N,) labels over the rows in ``keep``."""
    if keep is not None:
        probs, target = probs[keep], target[keep]
    if target.numel() == 0:
        return probs.sum() * 0.0
    num_classes = probs.shape[1]
    present = torch.bincount(target, minlength=num_classes) > 0
    # Class-major layout: each class's errors are sorted as one contiguous row.
    fg = F.one_hot(target, num_classes).t()[present].to(probs.dtype)  # (C', N)
    errors = (fg - probs.t()[present]).abs()
    errors_sorted, order = errors.sort(dim=1, descending=True)
    fg_sorted = fg.gather(1, order)
    return (errors_sorted * _lovasz_grad(fg_sorted)).sum(1).mean()


def _lovasz_grad(fg_sorted: torch.Tensor) -> torch.Tensor:
    """Per-row increments of the Jaccard loss along the sorted error order (C', N)."""
    total = fg_sorted.sum(1, keepdim=True)
    intersection = total - fg_sorted.cumsum(1)
    union = total + (1.0 - fg_sorted).cumsum(1)
    jaccard = 1.0 - intersection / union
    return torch.cat([jaccard[:, :1], jaccard[:, 1:] - jaccard[:, :-1]], dim=1)


def class_balance_weights(
    semantics: torch.Tensor, power: float, num_classes: int = NUM_CLASSES, free: int = FREE
) -> torch.Tensor | None:
    """Per-voxel weights (same shape as ``semantics``) that rebalance the occupied classes
    among themselves: ``frequency(class) ** -power`` over the occupied voxels of this batch,
    scaled to a mean of 1 over them; every ``free`` voxel weighs 1. 0 weighs every voxel
    alike; 0.5 lets a class 100 times rarer count 10 times more per voxel (small moving
    objects against buildings and road). None for 0, the unweighted loss.

    Occupied and free keep their unweighted totals, so the loss does not trade free voxels
    for occupied ones: counting ``free`` among the balanced classes made an occupied voxel of
    a 93 %-free world weigh about 12 times a free one, and a decoder then called a voxel
    occupied once it was 8 % sure (12 % predicted occupied where 6.6 % were). A binary
    occupied/free loss should take no weights at all (its boundary stays at p = 0.5)."""
    if not power:
        return None
    occupied = semantics != free
    counts = torch.bincount(semantics[occupied].reshape(-1), minlength=num_classes).to(torch.float32)
    share = counts / counts.sum().clamp_min(1.0)
    per_class = torch.where(counts > 0, share.clamp_min(1e-12) ** -power, torch.zeros_like(counts))
    weights = torch.where(occupied, per_class[semantics], torch.ones((), dtype=torch.float32, device=semantics.device))
    if occupied.any():
        weights = torch.where(occupied, weights / weights[occupied].mean(), weights)
    return weights


def ce_lovasz(
    logits: torch.Tensor,
    labels: torch.Tensor,
    valid: torch.Tensor | None = None,
    lovasz_voxels: int = 0,
    weights: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(cross-entropy, Lovasz-softmax) of class logits (B, C, *spatial) over the valid voxels.

    Works on one channels-last copy of the logits (softmax over a strided class axis is
    slow on CPU). Both terms are zero, keeping the graph, when no voxel is valid, so a
    batch without any occupied voxel does not produce NaN in the semantics loss.

    ``lovasz_voxels`` > 0 evaluates Lovasz on that many voxels drawn uniformly (torch's RNG)
    instead of all of them: its sort over every voxel and class dominates a CPU step, and
    the subset's loss is a noisy estimate of the full one. 0 is the exact loss.

    ``weights`` (same shape as ``labels``) weigh each voxel's cross-entropy (a weighted
    mean); Lovasz, already an average over classes, takes none.
    """
    flat = logits.movedim(1, -1).reshape(-1, logits.shape[1])
    target = labels.reshape(-1)
    keep = None if valid is None else valid.reshape(-1)
    w = None if weights is None else weights.reshape(-1)
    if keep is not None:
        flat, target = flat[keep], target[keep]
        w = None if w is None else w[keep]
    if target.numel() == 0:
        zero = logits.sum() * 0.0
        return zero, zero
    log_probs = flat.log_softmax(1)
    if w is None:
        ce = F.nll_loss(log_probs, target)
    else:
        ce = (F.nll_loss(log_probs, target, reduction="none") * w).sum() / w.sum().clamp_min(1e-12)
    if 0 < lovasz_voxels < target.numel():
        pick = torch.randint(target.numel(), (lovasz_voxels,), device=target.device)
        log_probs, target = log_probs[pick], target[pick]
    return ce, _lovasz_flat(log_probs.exp(), target, None)
