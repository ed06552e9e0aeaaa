"""Closed-loop training's rollouts: the policy mixed with the expert as beta says, every
frame labelled with the expert's plan from where the ego is, routes apart from the data's."""

from __future__ import annotations

import copy
from types import SimpleNamespace

import numpy as np
import pytest

from occtrain.data.closed_loop_recording import DrivingWorld
from occtrain.engine.closed_loop.dagger import DaggerSettings, MixedPlanner, route_seed, scene_name
from occtrain.engine.closed_loop.episodes import drive_episode
from occtrain.errors import ConfigError


@pytest.fixture(scope="module")
def built() -> DrivingWorld:
    return DrivingWorld(101, 4.0)


class _Policy:
    """Stands in for ``StagePlanner``: waits ``history`` frames, then plans to stand still."""

    def __init__(self, history: int):
        self.recorder = SimpleNamespace(scene="round00-route00", episode="round00-route00")
        self.history, self.calls = history, 0

    def __call__(self, world):
        self.calls += 1
        return None if self.calls <= self.history else np.zeros((6, 2))


@pytest.mark.parametrize("beta", [0.0, 1.0])
def test_the_mixture_follows_the_expert_as_beta_says_and_labels_every_frame(built, beta):
    world = copy.deepcopy(built)
    mixed = MixedPlanner(_Policy(history=2), beta, np.random.default_rng(0))
    drive_episode(world, mixed)
    frames = len(mixed.labelled)
    assert frames == 8  # a plan every 0.5 s until the episode's 4 s are up
    assert mixed.expert == (frames if beta == 1.0 else 2) and mixed.expert + mixed.policy == frames
    # Each frame's future is the expert's plan from there; its token is the route's own.
    assert len({f["token"] for f in mixed.labelled}) == frames
    for frame in mixed.labelled:
        assert len(frame["ego_future"]) == 6 and all(frame["ego_future_mask"])
    if beta == 0.0:  # the policy stood still after its history: the labels say to drive on
        assert mixed.labelled[-1]["ego_future"][-1][0] > mixed.labelled[-1]["ego_future"][0][0] >= 0


def test_the_labels_are_the_expert_from_each_state(built):
    world = copy.deepcopy(built)
    labels: list[np.ndarray] = []

    class Recording(MixedPlanner):
        def __call__(self, world):
            labels.append(world.expert_from_here())
            return super().__call__(world)

    mixed = Recording(_Policy(history=0), 0.0, np.random.default_rng(0))
    drive_episode(world, mixed)
    for label, frame in zip(labels, mixed.labelled):
        np.testing.assert_allclose(
            np.asarray(frame["ego_future"]), label, atol=1e-3
        )  # the annotation rounds to 4 digits


def test_settings_are_checked_and_beta_decays():
    settings = DaggerSettings(beta=0.8, beta_decay=0.5)
    assert [settings.beta_at(r) for r in range(3)] == [0.8, 0.4, 0.2]
    for bad, key in (
        (DaggerSettings(rounds=0), "rounds"),
        (DaggerSettings(beta=1.5), "beta"),
        (DaggerSettings(seconds=50), "seconds"),
    ):
        with pytest.raises(ConfigError, match=f"model.{key}"):
            bad.validate("model")
    seeds = {route_seed(settings, r, k) for r in range(3) for k in range(4)}
    assert len(seeds) == 12 and route_seed(settings, 1, 2) == route_seed(DaggerSettings(beta=0.8), 1, 2)
    assert scene_name(1, 2) == "round01-route02"


def test_critical_frames_are_replayed_more_often_than_cruising_ones():
    """A turn, a stop line not green or a lead close ahead: where the expert does something,
    and where an aggregate of mostly cruising frames would dilute it."""
    from occtrain.data.clips import Clip
    from occtrain.engine.closed_loop.dagger import critical, replay_weights

    def frame(command="go straight", stop=None, lead=None) -> dict:
        return {"command": command, "road": {"stop_line": stop, "lead": lead}}

    frames = [
        frame(),
        frame(command="turn left"),
        frame(stop={"distance": 12.0, "light": "red", "green_left": -1.0}),
        frame(stop={"distance": 12.0, "light": "green", "green_left": 8.0}),
        frame(lead={"gap": 9.0, "speed": 3.0}),
        frame(lead={"gap": 45.0, "speed": 9.0}),
        {"command": "go straight"},  # a frame without road: only its command can say
    ]
    assert [critical(f) for f in frames] == [False, True, True, False, True, False, False]
    weights = replay_weights([Clip({"anchor": f}, [], "") for f in frames], 3.0)
    assert weights.sum() == pytest.approx(1.0) and weights[1] == pytest.approx(3 * weights[0])
    with pytest.raises(ConfigError, match="critical_weight: 0.5 must be at least 1"):
        DaggerSettings(critical_weight=0.5).validate("stages.closed_loop.model")
