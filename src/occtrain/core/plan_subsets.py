"""Plans scored on the whole split and on the clips where driving on at constant velocity
is wrong: the subsets that show whether a planner reads the scene.

On a split where the ego mostly cruises, constant velocity is a strong open-loop plan
(the AD-MLP study's point), and a planner that copies it looks good. Every planner's metric
``name`` has a twin per subset (``SUBSETS``):

- ``_departing``: the clips whose true position at 3 s lies more than ``DEPARTING_M`` from
  constant velocity's (a stop at a red light, a turn, a start from standstill): there a
  plan must differ from constant velocity to score well;
- ``_turning``: the clips whose driving command turns (the route turns within 3 s);
- ``_stopping``: the clips where the truth stands still 3 s ahead (a red light, a queue).
"""

from __future__ import annotations

from collections.abc import Iterable

import torch

from occtrain.data.clips import PlanTarget
from occtrain.data.schema import STOP_SPEED
from occtrain.formats.occ3d import FRAME_DT
from occtrain.metrics import PlanningMetric
from occtrain.models.planning_heads import constant_velocity

#: Metres between the true position at 3 s and constant velocity's for a clip to depart.
DEPARTING_M = 1.0
#: The suffix of a plan metric's twin on the departing subset, and of every subset's.
DEPARTING = "_departing"
SUBSETS = (DEPARTING, "_turning", "_stopping")


def departing_rows(anchors: list[dict], target: PlanTarget, threshold: float = DEPARTING_M) -> list[int]:
    """The rows of ``anchors`` whose 3 s truth is known and departs from constant velocity."""
    cv = constant_velocity(anchors, target.traj.device)
    gap = (target.traj[:, -1] - cv[:, -1]).norm(dim=-1)
    return [i for i in range(len(anchors)) if bool(target.mask[i, -1]) and float(gap[i]) > threshold]


def subset_rows(anchors: list[dict], target: PlanTarget) -> dict[str, list[int]]:
    """Each subset's rows of ``anchors`` (see the module docstring)."""
    known = [i for i in range(len(anchors)) if bool(target.mask[i, -1])]
    last_step = (target.traj[:, -1] - target.traj[:, -2]).norm(dim=-1) / FRAME_DT
    return {
        DEPARTING: departing_rows(anchors, target),
        "_turning": [i for i in range(len(anchors)) if anchors[i].get("command", "go straight") != "go straight"],
        "_stopping": [i for i in known if float(last_step[i]) <= STOP_SPEED],
    }


def plan_metrics(names: Iterable[str]) -> dict[str, PlanningMetric]:
    """A planning metric per name, and its twin on each subset."""
    return {n: PlanningMetric() for name in names for n in (name, *(name + subset for subset in SUBSETS))}


def update_plans(
    metrics: dict | torch.nn.ModuleDict,
    name: str,
    pred: torch.Tensor,
    target: PlanTarget,
    subsets: dict[str, list[int]],
    rows: list[int] | None = None,
) -> None:
    """Score plans ``pred`` (one per row of ``rows``, default every row of ``target``) under
    ``name``, and those of each subset's rows (``subset_rows``) also under its twin."""
    rows = list(range(target.traj.shape[0])) if rows is None else rows
    if not rows:
        return
    sub = target.rows(rows)
    _planning(metrics, name).update(pred, sub.traj, sub.mask, sub.agents)
    for suffix, members in subsets.items():
        inside = set(members)
        keep = [k for k, r in enumerate(rows) if r in inside]
        if keep:
            part = sub.rows(keep)
            _planning(metrics, name + suffix).update(pred[keep], part.traj, part.mask, part.agents)


def _planning(metrics: dict | torch.nn.ModuleDict, name: str) -> PlanningMetric:
    metric = metrics[name]
    if not isinstance(metric, PlanningMetric):
        raise TypeError(f"metric '{name}' is a {type(metric).__name__}, not a PlanningMetric")
    return metric
