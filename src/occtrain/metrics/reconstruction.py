"""A scene tokenizer's reconstruction over a split: what its stage validates and
``occtrain eval`` reports, in one place."""

from __future__ import annotations

import torch
from torchmetrics import MeanMetric

from occtrain.formats.occ3d import FREE, MOVABLE_CLASSES
from occtrain.metrics.codebook import CodebookUsage
from occtrain.metrics.occupancy import OccupancyMetric


class ReconstructionMetrics(torch.nn.Module):
    """IoU/mIoU in the ``occworld`` convention (with the movable classes' mIoU, where motion
    separation should show) and the ``occ3d`` one, an empty scene as the trivial baseline,
    and each codebook's usage and perplexity. ``codebooks``: name -> size, in the order of
    the tokenizer's code grids. With ``oracle``, also the best reconstruction the encoder's
    budget allows (``baseline_budget_oracle_occworld``: what a point-set encoder's points
    reach placed on occupied voxels with their true classes), beside what it reaches. With
    ``prior`` (X, Y, Z), the per-voxel prior of the train split (``data.voxel_prior``) as
    the baseline that reads no input (``baseline_prior_occworld``). ``occupied_share`` and
    ``true_occupied_share``: the percent of voxels predicted and truly occupied (a loss that
    trades free for occupied voxels shows here first)."""

    def __init__(self, codebooks: dict[str, int], oracle: bool = False, prior: torch.Tensor | None = None):
        super().__init__()
        movable = {"movable": MOVABLE_CLASSES}
        self.scores = torch.nn.ModuleDict(
            {
                "occworld": OccupancyMetric(convention="occworld", subsets=movable),
                "occ3d": OccupancyMetric(convention="occ3d"),
                "baseline_free_occworld": OccupancyMetric(convention="occworld"),
                **(
                    {"baseline_prior_occworld": OccupancyMetric(convention="occworld", subsets=movable)}
                    if prior is not None
                    else {}
                ),
                **(
                    {"baseline_budget_oracle_occworld": OccupancyMetric(convention="occworld", subsets=movable)}
                    if oracle
                    else {}
                ),
            }
        )
        self.register_buffer("prior", None if prior is None else prior.long(), persistent=False)
        self.occupied = torch.nn.ModuleDict({"occupied_share": MeanMetric(), "true_occupied_share": MeanMetric()})
        self.usage = torch.nn.ModuleDict({name: CodebookUsage(size) for name, size in codebooks.items()})

    def update(
        self,
        pred: torch.Tensor,
        target: torch.Tensor,
        mask: torch.Tensor,
        codes: torch.Tensor | None = None,
        oracle: torch.Tensor | None = None,
    ) -> None:
        """Label volumes (B, X, Y, Z), ``mask_camera``, and the codes: (B, h, w) for one
        codebook, (B, codebooks, h, w) for several, None for a continuous encoder; the
        budget's oracle reconstruction (B, X, Y, Z) when the metrics report it."""
        self.scores["occworld"].update(pred, target)
        self.scores["occ3d"].update(pred, target, mask)
        self.scores["baseline_free_occworld"].update(torch.full_like(target, FREE), target)
        if self.prior is not None:
            self.scores["baseline_prior_occworld"].update(self.prior.to(target.device).expand_as(target), target)
        voxels = target[0].numel()
        for name, volume in (("occupied_share", pred), ("true_occupied_share", target)):
            share = 100.0 * (volume != FREE).flatten(1).sum(1).float() / voxels
            self.occupied[name].update(share, weight=torch.ones_like(share))
        if "baseline_budget_oracle_occworld" in self.scores:
            if oracle is None:
                raise ValueError("these reconstruction metrics report the budget's oracle: pass its labels")
            self.scores["baseline_budget_oracle_occworld"].update(oracle, target)
        if codes is None:
            return
        grids = codes if codes.dim() == 4 else codes[:, None]
        for i, usage in enumerate(self.usage.values()):
            usage.update(grids[:, i])

    def compute(self) -> dict[str, float]:
        """``occworld_mIoU``, ``occworld_movable_mIoU``, ``occ3d_IoU``, ..., ``<codebook>_usage``,
        ``<codebook>_perplexity``."""
        out: dict[str, float] = {}
        for name, metric in self.scores.items():
            out |= {f"{name}_{k}": float(v) for k, v in metric.compute().items() if k.endswith("IoU")}
        for name, usage in self.usage.items():
            out |= {f"{name}_{k}": v for k, v in usage.compute().items()}
        return out | {name: float(metric.compute()) for name, metric in self.occupied.items()}

    def reset(self) -> None:
        for metric in [*self.scores.values(), *self.usage.values(), *self.occupied.values()]:
            metric.reset()
