"""No input a model reads holds anything from after its frame: each annotated input is a
function of the frames up to the anchor, in the synthesized world and in the closed loop."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from occtrain.data.synth import generate_scene
from occtrain.data.synth.annotate import EgoMotion, frame_annotation, past_accels
from occtrain.data.synth.catalog import TrackSet
from occtrain.data.synth.closed_loop_world import STRIDE, DrivingWorld
from occtrain.data.synth.traffic import SIM_DT
from occtrain.data.synth.vehicle import PlanTracker, bicycle_step
from occtrain.engine.closed_loop.baselines import constant_acceleration
from occtrain.engine.closed_loop.episodes import drive_episode
from occtrain.formats.occ3d import FRAME_DT, FUTURE_STEPS
from occtrain.kinematics import past_acceleration

#: What the prompts, the planning heads and the encoders read about a frame.
INPUTS = ("ego_pose", "ego_speed", "ego_accel", "ego_yaw_rate", "ego_past", "ego_past_mask", "boxes")
#: What a model is asked to predict: made of the future by definition.
TARGETS = ("ego_future", "ego_future_mask", "meta_action", "agent_futures")
#: ``command`` is neither: the route's intent, which navigation knows ahead (nuScenes and the
#: papers derive it from the logged future; the synthetic world, dataset and closed loop
#: alike, reads it off the route: ``road_context.route_command``). ``road`` is an input of
#: the frame now (the route as a map holds it, the agents and the light as they are).

FRAMES, ANCHOR = 12, 5


def _motion(speed: np.ndarray) -> EgoMotion:
    """A straight drive along +x at ``speed`` (per frame), its positions integrated."""
    x = np.concatenate([[0.0], np.cumsum((speed[1:] + speed[:-1]) / 2 * FRAME_DT)])
    xy = np.stack([x, np.zeros_like(x)], axis=1)
    return EgoMotion(xy, np.zeros_like(x), speed, past_accels(xy, speed), np.zeros_like(x))


def _tracks(frames: int) -> TrackSet:
    """One parked car ahead, the same at every frame."""
    return TrackSet(
        cls=np.array([4]),
        size=np.array([[4.5, 1.9, 1.6]]),
        xy=np.tile([[[20.0, 3.0]]], (1, frames, 1)),
        yaw=np.zeros((1, frames)),
        speed=np.zeros((1, frames)),
        parked=np.array([True]),
        rider=np.array([False]),
    )


def test_every_input_is_the_same_whatever_the_future_holds():
    steady = np.full(FRAMES + FUTURE_STEPS, 8.0)
    braking = steady.copy()
    braking[ANCHOR + 1 :] = np.linspace(6.0, 0.0, len(braking) - ANCHOR - 1)  # the next frames brake hard
    n = FRAMES + FUTURE_STEPS
    a, b = (
        frame_annotation("s", 0, ANCHOR, FRAMES, _motion(v), _tracks(n), command="go straight", road=None)
        for v in (steady, braking)
    )
    for key in INPUTS:
        assert a[key] == b[key], key
    assert any(a[key] != b[key] for key in TARGETS)  # the test sees a future that changed


def test_the_acceleration_at_a_frame_is_the_speed_now_against_the_last_moves():
    speed = np.array([4.0, 5.0, 6.0, 6.0])  # +2 m/s^2 for a second, then steady
    accel = _motion(speed).accel
    # The last move's mean speed (4.5 m/s over the first half second) is 0.25 s old: (5 - 4.5) / 0.25.
    assert accel[0] == 0.0 and accel[1] == pytest.approx(2.0) and accel[2] == pytest.approx(2.0)
    assert accel[3] == pytest.approx((6.0 - 6.0) / 0.25)
    assert past_acceleration(5.0, None) == 0.0


def test_a_synthesized_scenes_ego_accel_is_its_past_not_its_next_command():
    scene = generate_scene(name="s", seed=7, num_frames=FRAMES)
    frames = scene.frames
    for i, frame in enumerate(frames[1:], start=1):
        move = float(
            np.hypot(*np.subtract(frame["ego_pose"]["translation"][:2], frames[i - 1]["ego_pose"]["translation"][:2]))
        )
        assert frame["ego_accel"] == pytest.approx(past_acceleration(frame["ego_speed"], move), abs=2e-3), i
    assert frames[0]["ego_accel"] == 0.0


def test_the_closed_loop_annotates_a_driven_frame_as_the_dataset_does():
    """In the closed loop ``ego_accel`` is computed by the same rule from the driven frames,
    not the bicycle's acceleration over its last 0.1 s step."""
    world = DrivingWorld(101, 3.0)
    seen = []

    def planner(w: DrivingWorld) -> np.ndarray:
        seen.append(w.frame_annotation("episode"))
        return constant_acceleration(w)

    drive_episode(world, planner)
    assert len(seen) >= 4
    for before, now in zip(seen, seen[1:]):
        move = float(np.hypot(*np.subtract(now["ego_pose"]["translation"][:2], before["ego_pose"]["translation"][:2])))
        assert now["ego_accel"] == pytest.approx(past_acceleration(now["ego_speed"], move), abs=2e-3)


def test_no_input_of_a_driven_frame_is_the_last_plans_command_relabelled():
    """What the controller commanded to follow the previous plan (each state's ``accel``, the
    bicycle's acceleration over its last 0.1 s) reaches no input: set to nonsense, every
    input a model reads of the frame is unchanged. The planner then acts on where the ego
    went and how fast, as in the dataset, not on what it told the ego to do."""
    world = DrivingWorld(101, 3.0)
    while world.time < 1.55 or not world.at_frame:
        world.advance(None)
    for _ in range(2):  # a plan that brakes: what the planner commanded is far from 0
        tracker = PlanTracker(np.stack([np.arange(1, 7) * 1.0, np.zeros(6)], 1), world.ego, FRAME_DT)
        for _ in range(STRIDE):
            accel, steer = tracker.controls(world.ego, 0.0)
            world.advance(bicycle_step(world.ego, accel, steer, SIM_DT))
    before = world.frame_annotation("episode")
    assert max(abs(s.accel) for s in world.log.states[-2 * STRIDE :]) > 0.5  # it did command something
    world.log.states = [replace(s, accel=99.0) for s in world.log.states]
    world.ego = replace(world.ego, accel=-99.0)
    after = world.frame_annotation("episode")
    for key in (*INPUTS, "road", "command"):
        assert before[key] == after[key], key
