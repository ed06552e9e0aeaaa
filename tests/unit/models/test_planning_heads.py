"""Planning heads that write along the route: the route's geometry, the prior along it, and a
head that learns where on it the expert goes."""

from __future__ import annotations

import numpy as np
import torch

from occtrain.formats.occ3d import FRAME_DT, FUTURE_STEPS
from occtrain.models.planning_heads import (
    ALONG_ROUTE,
    LATERAL_DECAY_S,
    ROUTE_ARC,
    PlanningHead,
    lateral_offset,
    prior_plan,
    route_plan,
    route_prior,
)

ARC = np.asarray(ROUTE_ARC)


def quarter_turn(radius: float = 10.0, offset: float = 0.0) -> np.ndarray:
    """A route 10 m straight ahead then a left quarter circle, ``offset`` m to the ego's left."""
    pts = []
    for s in ARC:
        if s <= 10.0:
            pts.append([s, offset])
        else:
            a = min((s - 10.0) / radius, np.pi / 2)
            extra = max(s - 10.0 - radius * np.pi / 2, 0.0)
            pts.append([10.0 + radius * np.sin(a), offset + radius * (1 - np.cos(a)) + extra])
    return np.array(pts)


def test_a_plan_along_the_route_lies_on_its_centreline_and_to_its_side():
    route = torch.tensor(quarter_turn(), dtype=torch.float32)[None]
    progress = torch.tensor([[0.0, 5.0, 10.0, 10.0 + 10 * np.pi / 4, 10.0 + 10 * np.pi / 2, 70.0]], dtype=torch.float32)
    on = route_plan(route, progress, torch.zeros(1, 6))[0].numpy()
    np.testing.assert_allclose(on[:3], [[0, 0], [5, 0], [10, 0]], atol=1e-5)
    # A chord of the circle between points 2.5 m apart lies a little inside it.
    assert abs(np.hypot(on[3, 0] - 10.0, on[3, 1] - 10.0) - 10.0) < 0.1
    np.testing.assert_allclose(on[5], quarter_turn()[-1] + [0.0, 10.0], atol=1e-4)  # on along its last segment
    left = route_plan(route, progress[:, :2], torch.full((1, 2), 1.5))[0].numpy()
    np.testing.assert_allclose(left, [[0, 1.5], [5, 1.5]], atol=1e-5)


def test_the_route_prior_is_constant_acceleration_along_it_and_its_offset_fades():
    anchor = {
        "ego_speed": 8.0,
        "ego_past": [[-4.0, 0.0]] * 3 + [[-3.8, 0.0]],  # the last move 3.8 m in 0.5 s: 7.6 m/s, accelerating
        "ego_past_mask": [1, 1, 1, 1],
        "road": {"route": quarter_turn(offset=-2.0).tolist()},
    }
    prior = route_prior([anchor])
    t = np.arange(1, FUTURE_STEPS + 1) * FRAME_DT
    accel = (8.0 - 7.6) / (FRAME_DT / 2)
    np.testing.assert_allclose(prior.progress[0].numpy(), 8.0 * t + 0.5 * accel * t**2, rtol=1e-5)
    assert lateral_offset(quarter_turn(offset=-2.0)) == 2.0  # the ego is 2 m left of its route
    np.testing.assert_allclose(prior.lateral[0].numpy(), 2.0 * np.exp(-t / LATERAL_DECAY_S), rtol=1e-5)
    plan = prior_plan([anchor], ALONG_ROUTE)
    assert plan is not None and plan.shape == (1, FUTURE_STEPS, 2) and float(plan[0, -1, 1]) > 0.5  # turning left
    straight = prior_plan([{k: v for k, v in anchor.items() if k != "road"}], ALONG_ROUTE)
    assert straight is not None and abs(float(straight[0, -1, 1])) < 1e-6  # no route: straight on


def test_a_head_along_the_route_learns_where_on_it_the_expert_brakes():
    """Frames whose expert stops short on the route ahead (its progress half the prior's)
    when a flag says so: the head learns the flag's progress, the turn comes from the route."""
    torch.manual_seed(0)
    route = torch.tensor(quarter_turn(), dtype=torch.float32)[None].expand(64, -1, -1)
    progress = torch.linspace(2.0, 14.0, FUTURE_STEPS)[None].expand(64, -1)
    flag = (torch.arange(64) % 2).float()[:, None]
    truth = route_plan(route, progress * (1 - 0.5 * flag), torch.zeros(64, FUTURE_STEPS))
    head = PlanningHead(1, 32, 2, FUTURE_STEPS, along_route=True)
    from occtrain.models.planning_heads import RoutePrior

    prior = RoutePrior(route, progress, torch.zeros(64, FUTURE_STEPS))
    opt = torch.optim.Adam(head.parameters(), lr=1e-2)
    first = None
    for _ in range(300):
        loss = (head(flag, route=prior) - truth).abs().sum(-1).mean()
        first = float(loss) if first is None else first
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss) < 0.05 * first and float(loss) < 0.3
