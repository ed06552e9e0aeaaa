"""Closed-loop driving scores on hand-built episodes (numbers worked out in the comments)."""

from __future__ import annotations

import numpy as np
import pytest

from occtrain.metrics.closed_loop_scores import (
    MAX_ABS_LON_JERK,
    MIN_LON_ACCEL,
    EpisodeTrace,
    Infraction,
    aggregate,
    score_episode,
)

DT = 0.1


def cruise(seconds: float = 10.0, speed: float = 10.0, **changes) -> EpisodeTrace:
    """An uneventful episode: constant speed on a straight route, as far as the expert."""
    n = int(round(seconds / DT)) + 1
    base = dict(
        dt=DT,
        speed=np.full(n, speed),
        lon_accel=np.zeros(n),
        lat_accel=np.zeros(n),
        yaw_rate=np.zeros(n),
        ttc=np.full(n, np.inf),
        progress=speed * seconds,
        expert_progress=speed * seconds,
    )
    base.update(changes)
    return EpisodeTrace(**base)


def test_a_clean_drive_scores_full_marks():
    s = score_episode(cruise())
    assert (s.route_completion, s.driving_score, s.pdm_score) == (100.0, 100.0, 100.0)
    assert s.collisions == s.red_lights == s.off_road == 0


def test_a_rear_end_collision_the_ego_caused():
    # The ego ran into a car ahead at 6 s, then stopped: 60 of the expert's 100 m.
    trace = cruise(progress=60.0, infractions=[Infraction("collision_vehicle", 6.0, other="car")])
    s = score_episode(trace)
    assert s.route_completion == pytest.approx(60.0)
    assert s.driving_score == pytest.approx(60.0 * 0.60)  # CARLA: vehicle collision x0.60
    assert s.no_at_fault_collision == 0.0 and s.pdm_score == 0.0  # NAVSIM: NC = 0 zeroes the score
    assert s.collisions_vehicle == 1


def test_being_rear_ended_is_not_the_egos_fault():
    trace = cruise(infractions=[Infraction("collision_vehicle", 3.0, at_fault=False, other="car")])
    s = score_episode(trace)
    assert s.driving_score == 100.0 and s.pdm_score == 100.0 and s.collisions == 0


def test_a_red_light_and_a_static_hit():
    trace = cruise(infractions=[Infraction("red_light", 2.0), Infraction("collision_static", 5.0, other="barrier")])
    s = score_episode(trace)
    assert s.infraction_penalty == pytest.approx(0.70 * 0.65)
    assert s.driving_score == pytest.approx(100.0 * 0.455)
    # NC = 0.5 for a static object only; TTC, EP and comfort all 1: PDMS = 0.5 * 12 / 12.
    assert s.pdm_score == pytest.approx(50.0)


def test_a_lane_departure_costs_completion_and_the_pdm_score():
    # 20 of the 100 m driven off the road: completion 80 %, DAC = 0.
    trace = cruise(off_route=20.0, infractions=[Infraction("off_road", 4.0)])
    s = score_episode(trace)
    assert s.route_completion == pytest.approx(80.0)
    assert s.driving_score == pytest.approx(80.0)
    assert s.drivable_area_compliance == 0.0 and s.pdm_score == 0.0


def test_standing_still_completes_nothing_but_is_safe():
    trace = cruise(speed=0.0, progress=0.0, expert_progress=100.0, ttc=np.full(101, 0.1))
    s = score_episode(trace)
    assert s.route_completion == 0.0 and s.driving_score == 0.0
    # TTC is not judged while still; EP = 0: PDMS = (5 * 1 + 5 * 0 + 2 * 1) / 12.
    assert s.ttc_within_bound == 1.0
    assert s.pdm_score == pytest.approx(100.0 * 7 / 12)


def test_time_to_collision_and_comfort_bounds():
    ttc = np.full(101, np.inf)
    ttc[50] = 0.9  # below nuPlan's 0.95 s while moving
    assert score_episode(cruise(ttc=ttc)).pdm_score == pytest.approx(100.0 * 7 / 12)
    harsh = np.zeros(101)
    harsh[50:] = -5.0  # braking beyond -4.05 m/s^2, from nothing within a step
    s = score_episode(cruise(lon_accel=harsh))
    assert s.comfort == 0.0 and s.pdm_score == pytest.approx(100.0 * 10 / 12)
    assert s.max_abs_lon_accel > -MIN_LON_ACCEL
    assert s.max_abs_jerk > MAX_ABS_LON_JERK  # smoothed over 1.5 s, still beyond the bound


def test_comfort_is_judged_on_smoothed_signals():
    # One step of 3 m/s^2 (a controller's blip) passes; a second of it does not.
    blip = np.zeros(101)
    blip[50] = 3.0
    assert score_episode(cruise(lon_accel=blip)).comfort == 1.0
    held = np.zeros(101)
    held[50:60] = 3.0
    assert score_episode(cruise(lon_accel=held)).comfort == 0.0


def test_the_expert_standing_still_gives_full_progress():
    trace = cruise(speed=0.0, progress=0.0, expert_progress=2.0)
    assert score_episode(trace).ego_progress == 1.0


def test_aggregate_means_over_episodes():
    agg = aggregate([score_episode(cruise()), score_episode(cruise(progress=50.0))])
    assert agg["route_completion"] == pytest.approx(75.0)
    assert agg["episodes"] == 2.0 and agg["episodes_without_at_fault_collision"] == 2.0
