"""Planning L2 and collision in the ST-P3 and UniAD conventions, on hand-computed trajectories."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from occtrain.metrics import PlanningMetric
from occtrain.metrics.planning import box_collisions, ego_footprint_cells, pad_agents

STRAIGHT = torch.tensor([[2.5 * (k + 1), 0.0] for k in range(6)])  # 5 m/s along +x


def values(d: dict) -> list[float]:
    return [d[k].item() for k in ("1s", "2s", "3s", "avg")]


def test_l2_stp3_is_cumulative_over_fully_valid_samples_uniad_is_per_step_over_all():
    # sample A: lateral errors 0, 1, 2, 3, 4, 5 m, every waypoint valid
    # sample B: 1 m error everywhere, the last waypoint invalid
    gt = torch.stack([STRAIGHT, STRAIGHT])
    pred = gt.clone()
    pred[0, :, 1] = torch.arange(6.0)
    pred[1, :, 1] = 1.0
    mask = torch.tensor([[1] * 6, [1] * 5 + [0]], dtype=torch.bool)
    m = PlanningMetric()
    m.update(pred, gt, mask)
    r = m.compute()
    # stp3: only A counts; 1 s = mean(0, 1) = 0.5, 2 s = mean(0..3) = 1.5, 3 s = mean(0..5) = 2.5, avg 1.5
    assert values(r["L2_stp3"]) == pytest.approx([0.5, 1.5, 2.5, 1.5])
    # uniad: waypoint 2: (1 + 1) / 2 = 1; waypoint 4: (3 + 1) / 2 = 2; waypoint 6: (5 + 0) / 2 = 2.5
    # (B's invalid waypoint adds 0 but B stays in the denominator); avg = 5.5 / 3
    assert values(r["L2_uniad"]) == pytest.approx([1.0, 2.0, 2.5, 5.5 / 3])
    assert r["samples"].item() == 2 and r["samples_stp3"].item() == 1
    assert "collision_stp3" not in r and "collision_uniad" not in r


def test_l2_is_euclidean_in_the_xy_plane():
    m = PlanningMetric()
    pred = STRAIGHT.clone()[None]
    pred[0, :, 0] += 3.0
    pred[0, :, 1] += 4.0
    m.update(pred, STRAIGHT[None], torch.ones(1, 6, dtype=torch.bool))
    assert values(m.compute()["L2_uniad"]) == pytest.approx([5.0, 5.0, 5.0, 5.0])


def test_no_fully_valid_sample_gives_nan_stp3():
    m = PlanningMetric()
    m.update(STRAIGHT[None], STRAIGHT[None], torch.tensor([[1, 1, 1, 1, 1, 0]], dtype=torch.bool))
    r = m.compute()
    assert all(math.isnan(v) for v in values(r["L2_stp3"]))
    assert values(r["L2_uniad"]) == [0.0, 0.0, 0.0, 0.0]


def test_ego_footprint_is_the_references_32_cells():
    # ego box 4.084 x 1.85 m centred 0.5 m ahead, on 0.5 m cells whose centres start at -49.75 m:
    # forward (-1.542 + 49.75) / 0.5 = 96.4 .. (2.542 + 49.75) / 0.5 = 104.6 -> rows 97..104;
    # lateral (-0.925 + 49.75) / 0.5 = 97.65 .. 101.35 -> cols 98..101
    cells = ego_footprint_cells()
    assert len(cells) == 32
    assert sorted(set(cells[:, 0].tolist())) == list(range(97, 105))
    assert sorted(set(cells[:, 1].tolist())) == list(range(98, 102))


def collide(traj: list[list[float]], boxes: list[list[float]]) -> list[bool]:
    """Collision per waypoint against the same boxes at every step."""
    t = torch.tensor(traj, dtype=torch.float64)[None]
    b, present = pad_agents([[np.array(boxes)] * t.shape[1]], 1, t.shape[1])
    return box_collisions(t, b, present)[0].tolist()


def test_agent_yaw_matters():
    # agent centred 3 m ahead, 4 x 0.6 m: along the ego heading it reaches back to x = 1 m and covers the
    # ego cell centres at x = 1.25 .. 2.25; turned by 90 degrees it spans x = 2.7 .. 3.3, past the last
    # ego cell centre (2.25)
    assert collide([[0.0, 0.0]], [[3.0, 0.0, 4.0, 0.6, 0.0]]) == [True]
    assert collide([[0.0, 0.0]], [[3.0, 0.0, 4.0, 0.6, math.pi / 2]]) == [False]


def test_ego_box_snaps_to_whole_cells_and_clamps_at_the_border_like_the_reference():
    # at x = 0.3 m the box front is at 0.3 + 2.542 = 2.84 m and overlaps an agent spanning x = 2.6 .. 3.0,
    # but the footprint moves by trunc(0.3 / 0.5) = 0 cells: its front cell centre stays at 2.25 m
    assert collide([[0.3, 0.0]], [[2.8, 0.0, 0.4, 2.0, 0.0]]) == [False]
    # at x = 0.5 m it moves by one cell: front cell centre 2.75 m, inside the agent
    assert collide([[0.5, 0.0]], [[2.8, 0.0, 0.4, 2.0, 0.0]]) == [True]
    # 100 m ahead is off the grid: the cells are clamped onto the last row (centre 49.75 m)
    assert collide([[100.0, 0.0]], [[49.75, 0.0, 0.2, 1.0, 0.0]]) == [True]


def collision_case() -> tuple[torch.Tensor, torch.Tensor, list]:
    """gt drives along +x; the plan drives 3 m to its left. Agents per step:

    step 1: a 2 x 1 m box at (5, 3) -- on the plan's waypoint (5, 3), clear of the gt's (5, 0);
    step 3: a 2 x 8 m box at (10, 0) -- hit by both the plan (10, 3) and the gt (10, 0): not counted;
    other steps: one box far away.
    """
    gt = STRAIGHT.clone()
    pred = gt.clone()
    pred[:, 1] = 3.0
    far = np.array([[40.0, 40.0, 4.0, 2.0, 0.0]])
    agents = [
        far,
        np.array([[5.0, 3.0, 2.0, 1.0, 0.0]]),
        far,
        np.array([[10.0, 0.0, 2.0, 8.0, 0.0]]),
        far,
        np.zeros((0, 5)),
    ]
    return pred[None], gt[None], [agents]


def test_collision_hand_case_excludes_steps_where_the_gt_collides():
    pred, gt, agents = collision_case()
    boxes, present = pad_agents(agents, 1, 6)
    assert box_collisions(pred, boxes, present)[0].tolist() == [False, True, False, True, False, False]
    assert box_collisions(gt, boxes, present)[0].tolist() == [False, False, False, True, False, False]
    m = PlanningMetric()
    m.update(pred, gt, torch.ones(1, 6, dtype=torch.bool), agents)
    r = m.compute()
    # counted per step: [0, 1, 0, 0 (gt collides too), 0, 0]
    # uniad: waypoint 2 -> 100 %, waypoint 4 -> 0 %, waypoint 6 -> 0 %, avg 33.3 %
    assert values(r["collision_uniad"]) == pytest.approx([100.0, 0.0, 0.0, 100 / 3])
    # stp3: 1 s = mean(0, 1) = 50 %, 2 s = 1/4 = 25 %, 3 s = 1/6 = 16.7 %, avg = (50 + 25 + 16.67) / 3
    assert values(r["collision_stp3"]) == pytest.approx([50.0, 25.0, 100 / 6, (50 + 25 + 100 / 6) / 3])


def test_collision_denominators_follow_each_convention():
    pred, gt, agents = collision_case()
    m = PlanningMetric()
    m.update(pred, gt, torch.ones(1, 6, dtype=torch.bool), agents)
    # a second sample, identical but with an invalid last waypoint: uniad counts it, stp3 leaves it out
    m.update(pred, gt, torch.tensor([[1, 1, 1, 1, 1, 0]], dtype=torch.bool), agents)
    # a third sample without agents adds to neither collision figure
    m.update(pred, gt, torch.ones(1, 6, dtype=torch.bool))
    r = m.compute()
    # uniad at 1 s: (1 + 1) / 2 samples with agents = 100 %; stp3 at 1 s: only the first: 50 %
    assert r["collision_uniad"]["1s"].item() == pytest.approx(100.0)
    assert r["collision_stp3"]["1s"].item() == pytest.approx(50.0)
    assert r["samples"].item() == 3


def test_planning_refuses_bad_shapes():
    m = PlanningMetric()
    with pytest.raises(ValueError, match=r"must both be \[B, 6, 2\]"):
        m.update(torch.zeros(1, 5, 2), torch.zeros(1, 5, 2), torch.ones(1, 5))
    with pytest.raises(ValueError, match="mask has shape"):
        m.update(torch.zeros(1, 6, 2), torch.zeros(1, 6, 2), torch.ones(1, 5))
    with pytest.raises(ValueError, match="expected 6"):
        m.update(torch.zeros(1, 6, 2), torch.zeros(1, 6, 2), torch.ones(1, 6), [[np.zeros((0, 5))] * 5])
    with pytest.raises(ValueError, match=r"expected \[N, 5\]"):
        m.update(torch.zeros(1, 6, 2), torch.zeros(1, 6, 2), torch.ones(1, 6), [[np.zeros((2, 4))] * 6])
