"""Shared task parts: the bases a plan is written against (``plan_prior``)."""

from __future__ import annotations

import numpy as np
import pytest

from occtrain.core.shared_tasks import PLAN_PRIORS, ego_plan, plan_base
from occtrain.data.clips import Clip


def _clip(speed: float, last_move: float) -> Clip:
    """A clip whose anchor drives at ``speed`` now, having moved ``last_move`` m in the last 0.5 s."""
    anchor = {
        "token": "t",
        "ego_speed": speed,
        "ego_past": [[-2 * last_move, 0.0], [-last_move, 0.0]],
        "ego_past_mask": [1, 1],
    }
    return Clip({"anchor": anchor, "tokens": ["t"], "ego_poses": [[0.0, 0.0, 0.0]], "history": 0, "future": 0}, [], "")


def test_constant_acceleration_writes_the_plan_as_offsets_from_the_pasts_acceleration():
    # 6 m/s now after a last move of 2.5 m (5 m/s on average, 0.25 s ago): +4 m/s^2.
    clip = _clip(6.0, 2.5)
    t = np.arange(1, 7) * 0.5
    np.testing.assert_allclose(plan_base(clip, "constant_acceleration")[:, 0], 6.0 * t + 2.0 * t**2)
    np.testing.assert_allclose(plan_base(clip, "constant_velocity")[:, 0], 6.0 * t)
    assert plan_base(clip, "none") is None and "constant_acceleration" in PLAN_PRIORS
    # Braking stops at standstill: 2 m/s now after 1.5 m (3 m/s): -4 m/s^2, stopped after 0.5 s at 0.5 m.
    np.testing.assert_allclose(plan_base(_clip(2.0, 1.5), "constant_acceleration")[:, 0], [0.5] * 6)
    truth = plan_base(clip, "constant_acceleration") + [[0.1, 0.0]] * 6
    written = ego_plan(truth, clip, "constant_acceleration")
    assert written.base is not None
    np.testing.assert_allclose(np.asarray(written.xy) - np.asarray(written.base), [[0.1, 0.0]] * 6, atol=1e-9)
    assert written.supervise is True and pytest.approx(written.xy[0][0]) == truth[0, 0]
