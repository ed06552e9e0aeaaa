"""The IDM traffic stepped one SIM_DT at a time, with the ego's pose supplied from outside."""

from __future__ import annotations

import numpy as np

from occtrain.data.synth.roads import Path
from occtrain.data.synth.traffic import JAM_GAP, SIM_DT, Mover, MoverTraffic, simulate_movers

STEPS = 300  # 30 s


def _straight_road() -> Path:
    return Path.from_points(np.array([[0.0, 0.0], [400.0, 0.0]]), stops=[])


def _car(s0: float, v0: float, v_des: float) -> Mover:
    return Mover(
        kind="car",
        size=np.array([4.5, 1.9, 1.6]),
        path=_straight_road(),
        s0=s0,
        v0=v0,
        v_des=np.full(STEPS, v_des),
        priority=0.0,
    )


def test_stepping_by_hand_is_the_generators_simulation():
    movers = [_car(40.0, 6.0, 7.0), _car(0.0, 10.0, 12.0)]
    host = np.array([-1, -1])
    whole = simulate_movers(movers, STEPS, host)
    traffic = MoverTraffic(movers, host)
    for step in range(STEPS):
        xy, yaw, _, env = traffic.pose()
        np.testing.assert_array_equal(xy, whole.xy[:, step])
        traffic.advance(step, xy, yaw, env)


def test_a_follower_stops_behind_an_ego_that_the_caller_holds_still():
    # Row 0 is the ego: its path says drive on at 12 m/s, the caller keeps it at x = 60.
    movers = [_car(60.0, 12.0, 12.0), _car(0.0, 12.0, 12.0)]
    traffic = MoverTraffic(movers, np.array([-1, -1]))
    for step in range(STEPS):
        xy, yaw, _, env = traffic.pose()
        xy[0], traffic.v[0] = [60.0, 0.0], 0.0
        traffic.advance(step, xy, yaw, env)
        gap = 60.0 - xy[1, 0] - 4.5
        assert gap > 0.5, f"the follower hit the held ego at step {step} (gap {gap:.2f} m)"
    assert traffic.v[1] < 0.05
    # IDM at rest keeps its jam distance from the leader's rear bumper.
    assert abs((60.0 - traffic.s[1] - 4.5) - JAM_GAP) < 0.5


def test_without_the_held_ego_the_follower_drives_through():
    movers = [_car(60.0, 12.0, 12.0), _car(0.0, 12.0, 12.0)]
    motion = simulate_movers(movers, STEPS, np.array([-1, -1]))
    assert motion.s[1, -1] > 60.0 + 12.0 * STEPS * SIM_DT / 2
