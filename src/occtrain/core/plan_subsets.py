"""Plans scored on the whole split and on the clips where driving on at constant velocity
is wrong: the subset that shows whether a planner reads the scene.

On a split where the ego mostly cruises, constant velocity is a strong open-loop plan
(the AD-MLP study's point), and a planner that copies it looks good. The "departing"
subset keeps the clips whose true position at 3 s lies more than ``DEPARTING_M`` from
constant velocity's (a stop at a red light, a turn, a start from standstill): there a
plan must differ from constant velocity to score well. Every planner's metric ``name``
has its twin ``name_departing`` on that subset.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch

from occtrain.data.clips import PlanTarget
from occtrain.metrics import PlanningMetric
from occtrain.models.planning_heads import constant_velocity

#: Metres between the true position at 3 s and constant velocity's for a clip to depart.
DEPARTING_M = 1.0
#: The suffix of a plan metric's twin on the departing subset.
DEPARTING = "_departing"


def departing_rows(anchors: list[dict], target: PlanTarget, threshold: float = DEPARTING_M) -> list[int]:
    """The rows of ``anchors`` whose 3 s truth is known and departs from constant velocity."""
    cv = constant_velocity(anchors, target.traj.device)
    gap = (target.traj[:, -1] - cv[:, -1]).norm(dim=-1)
    return [i for i in range(len(anchors)) if bool(target.mask[i, -1]) and float(gap[i]) > threshold]


def plan_metrics(names: Iterable[str]) -> dict[str, PlanningMetric]:
    """A planning metric per name, and its twin on the departing subset."""
    return {n: PlanningMetric() for name in names for n in (name, name + DEPARTING)}


def update_plans(
    metrics: dict | torch.nn.ModuleDict,
    name: str,
    pred: torch.Tensor,
    target: PlanTarget,
    departing: list[int],
    rows: list[int] | None = None,
) -> None:
    """Score plans ``pred`` (one per row of ``rows``, default every row of ``target``) under
    ``name``, and those of ``departing`` rows also under its twin."""
    rows = list(range(target.traj.shape[0])) if rows is None else rows
    if not rows:
        return
    sub = target.rows(rows)
    _planning(metrics, name).update(pred, sub.traj, sub.mask, sub.agents)
    departs = set(departing)
    keep = [k for k, r in enumerate(rows) if r in departs]
    if keep:
        sub = sub.rows(keep)
        _planning(metrics, name + DEPARTING).update(pred[keep], sub.traj, sub.mask, sub.agents)


def _planning(metrics: dict | torch.nn.ModuleDict, name: str) -> PlanningMetric:
    metric = metrics[name]
    if not isinstance(metric, PlanningMetric):
        raise TypeError(f"metric '{name}' is a {type(metric).__name__}, not a PlanningMetric")
    return metric
