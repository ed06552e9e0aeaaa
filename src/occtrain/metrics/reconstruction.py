"""A scene tokenizer's reconstruction over a split: what its stage validates and
``occtrain eval`` reports, in one place."""

from __future__ import annotations

from typing import TypeVar

import torch
from torchmetrics import MeanMetric, Metric

from occtrain.formats.occ3d import FREE, MOVABLE_CLASSES
from occtrain.metrics.codebook import CodebookUsage
from occtrain.metrics.occupancy import OccupancyMetric

M = TypeVar("M", bound=torch.nn.Module)


def _member(modules: torch.nn.ModuleDict, name: str, kind: type[M]) -> M:
    """``modules[name]``, which a ModuleDict types as any Module, as the ``kind`` it holds."""
    module = modules[name]
    assert isinstance(module, kind)
    return module


class ReconstructionMetrics(torch.nn.Module):
    """IoU/mIoU in the ``occworld`` convention (with the movable classes' mIoU, where motion
    separation should show) and the ``occ3d`` one, an empty scene as the trivial baseline,
    and each codebook's usage and perplexity. ``codebooks``: name -> size, in the order of
    the tokenizer's code grids. With ``oracles``, also the reconstructions that bound what the
    encoder can reach (``baseline_<name>_occworld``: ``budget_oracle``, what a point-set
    encoder's points reach placed on occupied voxels with their true classes;
    ``lifted_pixels``, what a perfect reader of its cameras' pixels lifts into the grid). With
    ``prior`` (X, Y, Z), the per-voxel prior of the train split (``data.voxel_prior``) as
    the baseline that reads no input (``baseline_prior_occworld``). ``occupied_share`` and
    ``true_occupied_share``: the percent of voxels predicted and truly occupied (a loss that
    trades free for occupied voxels shows here first)."""

    prior: torch.Tensor | None

    def __init__(self, codebooks: dict[str, int], oracles: tuple[str, ...] = (), prior: torch.Tensor | None = None):
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
                **{
                    f"baseline_{name}_occworld": OccupancyMetric(convention="occworld", subsets=movable)
                    for name in oracles
                },
            }
        )
        self.oracles = tuple(oracles)
        self.register_buffer("prior", None if prior is None else prior.long(), persistent=False)
        self.occupied = torch.nn.ModuleDict({"occupied_share": MeanMetric(), "true_occupied_share": MeanMetric()})
        self.usage = torch.nn.ModuleDict({name: CodebookUsage(size) for name, size in codebooks.items()})

    def update(
        self,
        pred: torch.Tensor,
        target: torch.Tensor,
        mask: torch.Tensor,
        codes: torch.Tensor | None = None,
        oracles: dict[str, torch.Tensor] | None = None,
    ) -> None:
        """Label volumes (B, X, Y, Z), ``mask_camera``, and the codes: (B, h, w) for one
        codebook, (B, codebooks, h, w) for several, None for a continuous encoder; each
        oracle's reconstruction (B, X, Y, Z) that the metrics report."""
        self._score("occworld").update(pred, target)
        self._score("occ3d").update(pred, target, mask)
        self._score("baseline_free_occworld").update(torch.full_like(target, FREE), target)
        if self.prior is not None:
            self._score("baseline_prior_occworld").update(self.prior.to(target.device).expand_as(target), target)
        voxels = target[0].numel()
        for name, volume in (("occupied_share", pred), ("true_occupied_share", target)):
            share = 100.0 * (volume != FREE).flatten(1).sum(1).float() / voxels
            _member(self.occupied, name, MeanMetric).update(share, weight=torch.ones_like(share))
        missing = [name for name in self.oracles if name not in (oracles or {})]
        if missing:
            raise ValueError(f"these reconstruction metrics report the oracles {', '.join(missing)}: pass their labels")
        for name in self.oracles:
            self._score(f"baseline_{name}_occworld").update((oracles or {})[name], target)
        if codes is None:
            return
        grids = codes if codes.dim() == 4 else codes[:, None]
        for i, name in enumerate(self.usage):
            _member(self.usage, name, CodebookUsage).update(grids[:, i])

    def compute(self) -> dict[str, float]:
        """``occworld_mIoU``, ``occworld_movable_mIoU``, ``occ3d_IoU``, ..., ``<codebook>_usage``,
        ``<codebook>_perplexity``."""
        out: dict[str, float] = {}
        for name in self.scores:
            scores = self._score(name).compute()
            out |= {f"{name}_{k}": float(v) for k, v in scores.items() if k.endswith("IoU")}
        for name in self.usage:
            out |= {f"{name}_{k}": v for k, v in _member(self.usage, name, CodebookUsage).compute().items()}
        return out | {name: float(_member(self.occupied, name, MeanMetric).compute()) for name in self.occupied}

    def _score(self, name: str) -> OccupancyMetric:
        return _member(self.scores, name, OccupancyMetric)

    def reset(self) -> None:
        for metric in self.modules():
            if isinstance(metric, Metric):
                metric.reset()
