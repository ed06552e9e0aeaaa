"""The kinematic bicycle and the plan tracker: the driven ego goes where its plan says."""

from __future__ import annotations

import numpy as np
import pytest

from occtrain.data.geometry import global_to_ego
from occtrain.data.synth.vehicle import MIN_ACCEL, EgoState, PlanTracker, bicycle_step, follow

DT, PLAN_DT = 0.1, 0.5


def drive(plan_of, state: EgoState, seconds: float) -> EgoState:
    """Replan every PLAN_DT with ``plan_of(state)``, as closed-loop driving does."""
    for _ in range(int(round(seconds / PLAN_DT))):
        tracker = PlanTracker(plan_of(state), state, PLAN_DT)
        state = follow(state, tracker, 0.0, DT, int(round(PLAN_DT / DT)))[-1]
    return state


def test_a_straight_plan_at_the_current_speed_keeps_speed_and_heading():
    start = EgoState(np.zeros(2), 0.3, 10.0)
    straight = np.stack([np.arange(1, 7) * 5.0, np.zeros(6)], axis=1)  # 10 m/s straight ahead
    end = drive(lambda s: straight, start, 5.0)
    assert end.speed == pytest.approx(10.0, abs=0.05)
    assert end.yaw == pytest.approx(0.3, abs=1e-3)
    assert np.linalg.norm(end.xy - 50.0 * np.array([np.cos(0.3), np.sin(0.3)])) < 0.5


def test_a_circle_plan_is_followed_within_half_a_metre():
    radius, speed = 20.0, 6.0
    start = EgoState(np.array([0.0, -radius]), 0.0, speed)  # on a circle round the origin, counter-clockwise

    def arc(state: EgoState) -> np.ndarray:
        theta = np.arctan2(state.xy[1], state.xy[0]) + np.arange(1, 7) * speed * PLAN_DT / radius
        return global_to_ego(radius * np.stack([np.cos(theta), np.sin(theta)], axis=1), state.xy, state.yaw)

    end = drive(arc, start, 8.0)  # 48 m: well over a third of the circle
    assert abs(np.linalg.norm(end.xy) - radius) < 0.5
    assert np.arctan2(end.xy[1], end.xy[0]) > -np.pi / 2 + 2.0


def test_a_standstill_plan_brakes_to_a_stop_and_never_reverses():
    start = EgoState(np.zeros(2), 0.0, 8.0)
    end = drive(lambda s: np.zeros((6, 2)), start, 3.0)
    assert end.speed == 0.0
    # 8 m/s at 6 m/s^2: 5.3 m to stop.
    assert end.xy[0] == pytest.approx(8.0**2 / (2 * -MIN_ACCEL), abs=0.5)


def test_steering_is_rate_and_angle_limited():
    state = bicycle_step(EgoState(np.zeros(2), 0.0, 5.0), 0.0, 1.5, DT)
    assert state.steer == pytest.approx(0.1)  # 1 rad/s for 0.1 s
