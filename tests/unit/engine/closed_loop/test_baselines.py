"""The baselines start as a stage does: the expert drives the frames a stage's prompts read."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from occtrain.data.closed_loop_recording import DrivingWorld
from occtrain.engine.closed_loop.baselines import BASELINES, WarmRule, baseline_planner, constant_velocity
from occtrain.engine.closed_loop.episodes import drive_episode
from occtrain.metrics.closed_loop_scores import score_episode


@pytest.fixture(scope="module")
def route() -> DrivingWorld:
    return DrivingWorld(11, 5.0)


def _trace(world: DrivingWorld, planner) -> list:
    drive_episode(world, planner)
    return [(round(float(s.xy[0]), 6), round(float(s.xy[1]), 6), round(s.speed, 6)) for s in world.log.states]


def test_a_rule_waits_out_the_history_the_expert_drives(route):
    rule = baseline_planner("constant_velocity", history=3)
    assert isinstance(rule, WarmRule) and baseline_planner("expert", 3) is None
    drive_episode(copy.deepcopy(route), rule)
    assert (rule.counts.expert, rule.counts.planned) == (3, 7)  # 10 planning frames before 5 s ends
    with pytest.raises(ValueError, match="is not a baseline; the baselines are expert, constant_velocity"):
        baseline_planner("cruise", 3)
    assert BASELINES[0] == "expert"


def test_warm_constant_acceleration_is_not_constant_velocity(route):
    """From frame 0 there is no past: constant acceleration equalled constant velocity, route by route."""
    cold = [
        _trace(copy.deepcopy(route), baseline_planner(name, 0))
        for name in ("constant_velocity", "constant_acceleration")
    ]
    warm = [
        _trace(copy.deepcopy(route), baseline_planner(name, 2))
        for name in ("constant_velocity", "constant_acceleration")
    ]
    assert cold[0] == cold[1] and warm[0] != warm[1]


def test_a_driver_that_never_plans_scores_as_every_rule_that_never_did(route):
    """An episode no longer than the history: the stage planned none of its frames, nor did
    any rule; they drove the same expert start, so none outscores another."""
    never = lambda world: None  # noqa: E731 - a stage waiting for its history, all episode long
    scores = [
        score_episode(drive_episode(copy.deepcopy(route), planner)).driving_score
        for planner in (never, baseline_planner("constant_velocity", 11), WarmRule(constant_velocity, 11))
    ]
    assert np.ptp(scores) == 0.0
