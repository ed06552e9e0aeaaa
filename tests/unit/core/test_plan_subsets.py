"""The departing subset: clips where constant velocity is more than 1 m off at 3 s."""

from __future__ import annotations

import numpy as np
import torch

from occtrain.core.plan_subsets import DEPARTING, departing_rows, plan_metrics, update_plans
from occtrain.data.clips import PlanTarget
from occtrain.formats.occ3d import FRAME_DT


def target(*finals: tuple[float, float], known: bool = True) -> PlanTarget:
    """Straight trajectories at 2 m/s except the last waypoint, set to ``finals``."""
    t = torch.arange(1, 7, dtype=torch.float32) * FRAME_DT
    traj = torch.stack([torch.stack([2.0 * t, torch.zeros(6)], -1) for _ in finals])
    for i, xy in enumerate(finals):
        traj[i, -1] = torch.tensor(xy)
    mask = torch.ones(len(finals), 6, dtype=torch.bool)
    mask[:, -1] = known
    return PlanTarget(traj, mask, [[np.zeros((0, 5))] * 6 for _ in finals])


def test_a_clip_departs_when_the_truth_at_3s_is_over_1m_from_constant_velocity():
    anchors = [{"ego_speed": 2.0}] * 4  # constant velocity: (6, 0) at 3 s
    gt = target((6.0, 0.0), (6.0, 0.9), (4.9, 0.0), (6.0, -1.5))
    assert departing_rows(anchors, gt) == [2, 3]
    assert departing_rows(anchors[:1], target((0.0, 0.0), known=False)) == []  # 3 s unknown: not judged


def test_a_plan_counts_on_the_whole_split_and_on_the_departing_rows():
    anchors = [{"ego_speed": 2.0}] * 3
    gt = target((6.0, 0.0), (3.0, 0.0), (6.0, 0.0))
    metrics = plan_metrics(["plan"])
    assert set(metrics) == {"plan", "plan" + DEPARTING}
    pred = gt.traj.clone()
    pred[:, -1] += torch.tensor([1.0, 0.0])  # 1 m off at 3 s on every row
    update_plans(metrics, "plan", pred[1:], gt, departing_rows(anchors, gt), rows=[1, 2])
    whole, dep = metrics["plan"].compute(), metrics["plan" + DEPARTING].compute()
    assert int(whole["samples"]) == 2 and int(dep["samples"]) == 1  # row 1 departs (3 m short at 3 s)
    assert abs(float(whole["L2_uniad"]["3s"]) - 1.0) < 1e-9 and abs(float(dep["L2_uniad"]["3s"]) - 1.0) < 1e-9
    assert float(whole["L2_uniad"]["1s"]) == 0.0
