"""Open-loop planning L2 and collision rate, in the ST-P3 (VAD) and the UniAD conventions.

Both read the same per-waypoint quantities over a 3 s future at 2 Hz (6 waypoints,
ego frame, metres) and differ in how they aggregate them:

* ``stp3`` (ST-P3 ``stp3/metrics.py`` ``PlanningMetric``, as VAD evaluates it): a sample
  counts only when all 6 ground-truth waypoints are valid (VAD's ``fut_valid_flag``);
  other samples are left out entirely. The value at t is the mean over the waypoints up
  to t (1 s: waypoints 1-2, 2 s: 1-4, 3 s: 1-6), averaged over the counted samples.
* ``uniad`` (UniAD ``planning_metrics.py``): every sample counts; an invalid waypoint
  contributes an L2 of 0 (its squared error is multiplied by the mask) yet still sits in
  the denominator, which is the number of samples. The value at t is that of waypoint t
  alone (1 s: waypoint 2, 2 s: 4, 3 s: 6).

``avg`` is the mean of the 1 s, 2 s and 3 s values, as the papers print it.

Collision, in both references: the ego box (``EGO_LENGTH`` x ``EGO_WIDTH``, centred 0.5 m
ahead of the waypoint, never rotated: it keeps the current heading) is rasterised on a
200 x 200 BEV grid of 0.5 m cells spanning +-50 m, snapped to whole cells at each waypoint
(cells past the border are clamped onto it), and collides when one of its cells is
occupied by a ground-truth agent box at that step. Steps where the ground-truth
trajectory itself collides are not counted (they add 0, but stay in the denominator).
Here the agent occupancy is not rasterised into a grid: a cell is occupied when its
centre lies inside an agent's oriented box, which is what rasterising the box onto that
grid marks, so the result equals the grid test up to centres exactly on a box edge. The
references rasterise their agents from their own annotation pipelines, so only the
ego-side rules are theirs verbatim. Collision rates are percent, as the papers print them;
L2 is metres.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torchmetrics import Metric

from occtrain.formats.occ3d import EGO_LENGTH, EGO_WIDTH, FRAME_DT, FUTURE_STEPS

#: The reference's BEV collision grid: 0.5 m cells, +-50 m, cell centres from -49.75 m.
BEV_CELL = 0.5
BEV_CELLS = 200
BEV_FIRST_CENTRE = -50.0 + BEV_CELL / 2
#: The reference places the ego box centre this far ahead of the waypoint.
EGO_BOX_FORWARD_OFFSET = 0.5
#: Waypoint index of each reported horizon (1 s, 2 s, 3 s at 2 Hz).
HORIZONS: dict[str, int] = {f"{s}s": round(s / FRAME_DT) - 1 for s in (1, 2, 3)}


def ego_footprint_cells() -> Tensor:
    """(K, 2) integer BEV cells (forward, lateral) whose centres lie inside the ego box at the origin."""
    centres = BEV_FIRST_CENTRE + BEV_CELL * torch.arange(BEV_CELLS, dtype=torch.float64)
    fwd = torch.nonzero((centres - EGO_BOX_FORWARD_OFFSET).abs() < EGO_LENGTH / 2).flatten()
    lat = torch.nonzero(centres.abs() < EGO_WIDTH / 2).flatten()
    return torch.cartesian_prod(fwd, lat)


_FOOTPRINT = ego_footprint_cells()


def ego_cell_centres(traj: Tensor) -> Tensor:
    """Metric centres (..., K, 2) of the ego box's cells at each waypoint of ``traj`` (..., 2).

    The footprint moves by the waypoint in cells and is truncated to whole cells, then
    clamped to the grid, as the reference does before indexing its occupancy grid.
    """
    shifted = _FOOTPRINT.to(traj.device, torch.float64) + (traj.double() / BEV_CELL).unsqueeze(-2)
    cells = torch.trunc(shifted).clamp(0, BEV_CELLS - 1)
    return BEV_FIRST_CENTRE + BEV_CELL * cells


def pad_agents(agents: Sequence[Sequence[Any]], batch: int, steps: int) -> tuple[Tensor, Tensor]:
    """Per-sample per-step agent boxes -> ``boxes [B, T, N, 5]`` (zero-padded) and ``present [B, T, N]``."""
    if len(agents) != batch:
        raise ValueError(f"agents has {len(agents)} samples, expected {batch}")
    arrays = []
    for b, per_step in enumerate(agents):
        if len(per_step) != steps:
            raise ValueError(f"agents[{b}] has {len(per_step)} steps, expected {steps}")
        for boxes in per_step:
            arr = np.asarray(boxes.cpu() if isinstance(boxes, Tensor) else boxes, dtype=np.float64)
            if arr.size and (arr.ndim != 2 or arr.shape[1] != 5):
                raise ValueError(
                    f"agents[{b}] holds boxes of shape {arr.shape}, expected [N, 5] (x, y, length, width, yaw)"
                )
            arrays.append(arr.reshape(-1, 5))
    most = max((a.shape[0] for a in arrays), default=0)
    out = np.zeros((batch * steps, max(most, 1), 5))
    present = np.zeros((batch * steps, max(most, 1)), dtype=bool)
    for i, a in enumerate(arrays):
        out[i, : len(a)] = a
        present[i, : len(a)] = True
    shape = (batch, steps, out.shape[1])
    return torch.from_numpy(out).reshape(*shape, 5), torch.from_numpy(present).reshape(shape)


def box_collisions(traj: Tensor, boxes: Tensor, present: Tensor) -> Tensor:
    """``[B, T]`` True where the ego box at waypoint ``traj [B, T, 2]`` overlaps an agent box.

    ``boxes [B, T, N, 5]`` hold (x, y, length, width, yaw) per agent; ``present`` masks padding.
    """
    points = ego_cell_centres(traj)  # B, T, K, 2
    boxes = boxes.to(points.device, torch.float64)
    rel = points.unsqueeze(-2) - boxes[..., None, :, :2]  # B, T, K, N, 2
    cos, sin = torch.cos(boxes[..., 4]).unsqueeze(-2), torch.sin(boxes[..., 4]).unsqueeze(-2)
    along = rel[..., 0] * cos + rel[..., 1] * sin
    across = -rel[..., 0] * sin + rel[..., 1] * cos
    inside = (along.abs() <= boxes[..., None, :, 2] / 2) & (across.abs() <= boxes[..., None, :, 3] / 2)
    return (inside & present.to(points.device).unsqueeze(-2)).flatten(-2).any(-1)


class PlanningMetric(Metric):
    """L2 (m) and collision rate (%) at 1 s / 2 s / 3 s and their mean, ST-P3 and UniAD conventions.

    ``update(pred [B, 6, 2], gt [B, 6, 2], mask [B, 6], agents=None)``: ``agents`` is a
    list (one per sample) of per-step lists of ``[N, 5]`` arrays (x, y, length, width,
    yaw in the current ego frame); without it no collision is counted for those samples.
    ``compute()`` returns ``L2_stp3``, ``L2_uniad``, and, when some sample had agents,
    ``collision_stp3`` and ``collision_uniad`` (each ``{"1s", "2s", "3s", "avg"}``), plus
    ``samples`` (all) and ``samples_stp3`` (those with a fully valid future). The
    conventions are spelled out in the module docstring.
    """

    is_differentiable = False
    higher_is_better = False
    full_state_update = False
    #: Per-step sums (FUTURE_STEPS,) and sample counts.
    l2_stp3: Tensor
    l2_uniad: Tensor
    col_stp3: Tensor
    col_uniad: Tensor
    samples: Tensor
    samples_stp3: Tensor
    col_samples: Tensor
    col_samples_stp3: Tensor

    def __init__(self, **kwargs: Any):
        super().__init__(**kwargs)
        steps = torch.zeros(FUTURE_STEPS, dtype=torch.float64)
        for name in ("l2_stp3", "l2_uniad", "col_stp3", "col_uniad"):
            self.add_state(name, steps.clone(), dist_reduce_fx="sum")
        for name in ("samples", "samples_stp3", "col_samples", "col_samples_stp3"):
            self.add_state(name, torch.zeros((), dtype=torch.long), dist_reduce_fx="sum")

    def update(self, pred: Tensor, gt: Tensor, mask: Tensor, agents: Sequence[Sequence[Any]] | None = None) -> None:
        expected = (gt.shape[0], FUTURE_STEPS, 2)
        if tuple(gt.shape) != expected or tuple(pred.shape) != expected:
            raise ValueError(f"pred {tuple(pred.shape)} and gt {tuple(gt.shape)} must both be [B, {FUTURE_STEPS}, 2]")
        if tuple(mask.shape) != expected[:2]:
            raise ValueError(f"mask has shape {tuple(mask.shape)}, expected {expected[:2]}")
        pred, gt, valid = pred.double(), gt.double(), mask.bool()
        full = valid.all(dim=1)
        l2 = (pred - gt).norm(dim=-1)  # B, T
        self.l2_stp3 += l2[full].sum(0)
        self.l2_uniad += (l2 * valid).sum(0)
        self.samples += pred.shape[0]
        self.samples_stp3 += full.sum()
        if agents is None:
            return
        boxes, present = pad_agents(agents, pred.shape[0], FUTURE_STEPS)
        counted = box_collisions(pred, boxes, present) & ~box_collisions(gt, boxes, present)
        counted = counted.to(self.col_uniad.device, torch.float64)
        self.col_uniad += counted.sum(0)
        self.col_stp3 += counted[full.to(counted.device)].sum(0)
        self.col_samples += pred.shape[0]
        self.col_samples_stp3 += full.sum()

    @staticmethod
    def _at_horizons(per_step_sum: Tensor, count: Tensor, cumulative: bool, scale: float = 1.0) -> dict[str, Tensor]:
        per_step = per_step_sum / count.double()  # 0/0 -> NaN when nothing was counted
        out = {
            label: scale * (per_step[: i + 1].mean() if cumulative else per_step[i]) for label, i in HORIZONS.items()
        }
        out["avg"] = torch.stack(list(out.values())).mean()
        return out

    def compute(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "L2_stp3": self._at_horizons(self.l2_stp3, self.samples_stp3, cumulative=True),
            "L2_uniad": self._at_horizons(self.l2_uniad, self.samples, cumulative=False),
        }
        if int(self.col_samples) > 0:
            out["collision_stp3"] = self._at_horizons(
                self.col_stp3, self.col_samples_stp3, cumulative=True, scale=100.0
            )
            out["collision_uniad"] = self._at_horizons(self.col_uniad, self.col_samples, cumulative=False, scale=100.0)
        out["samples"] = self.samples.clone()
        out["samples_stp3"] = self.samples_stp3.clone()
        return out
