"""The subsets every plan is also scored on: clips where constant velocity is more than 1 m
off at 3 s, where the route turns, where the truth stands still at 3 s."""

from __future__ import annotations

import numpy as np
import torch

from occtrain.core.plan_subsets import DEPARTING, SUBSETS, departing_rows, plan_metrics, subset_rows, update_plans
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
    assert set(metrics) == {"plan", "plan_departing", "plan_turning", "plan_stopping"}
    pred = gt.traj.clone()
    pred[:, -1] += torch.tensor([1.0, 0.0])  # 1 m off at 3 s on every row
    update_plans(metrics, "plan", pred[1:], gt, {DEPARTING: departing_rows(anchors, gt)}, rows=[1, 2])
    whole, dep = metrics["plan"].compute(), metrics["plan" + DEPARTING].compute()
    assert int(whole["samples"]) == 2 and int(dep["samples"]) == 1  # row 1 departs (3 m short at 3 s)
    assert abs(float(whole["L2_uniad"]["3s"]) - 1.0) < 1e-9 and abs(float(dep["L2_uniad"]["3s"]) - 1.0) < 1e-9
    assert float(whole["L2_uniad"]["1s"]) == 0.0


def test_the_turning_and_stopping_subsets_read_the_command_and_the_truths_last_step():
    anchors = [{"ego_speed": 2.0, "command": c} for c in ("go straight", "turn left", "go straight", "turn right")]
    gt = target((6.0, 0.0), (6.0, 0.0), (5.0, 0.0), (5.0, 0.0))
    gt.traj[3, -1] = gt.traj[3, -2]  # row 3 stands still between 2.5 and 3 s
    gt.traj[2, -2] = gt.traj[2, -1] - torch.tensor([0.1, 0.0])  # row 2 creeps at 0.2 m/s: stopped
    rows = subset_rows(anchors, gt)
    assert list(rows) == list(SUBSETS)
    assert rows["_turning"] == [1, 3] and rows["_stopping"] == [2, 3]
