"""Closed-loop driving in the synthetic world: the expert, the baselines, and what the checks catch."""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pytest

from occtrain.data.schema import LATERAL_DECAY_S
from occtrain.data.synth.citymap import SIDEWALK
from occtrain.data.synth.closed_loop_world import STRIDE, DrivingWorld
from occtrain.data.synth.roads import PATH_DS, green_left
from occtrain.data.synth.vehicle import EgoState
from occtrain.engine.closed_loop.baselines import stand_still
from occtrain.engine.closed_loop.episodes import drive_episode
from occtrain.formats.occ3d import EGO_LENGTH, FREE
from occtrain.metrics.closed_loop_scores import TTC_BOUND, Infraction, score_episode

SEED = 101  # the ego starts from rest; the light at its first stop line is red for the first 5.5 s


@pytest.fixture(scope="module")
def built() -> DrivingWorld:
    return DrivingWorld(SEED, 6.0)


@pytest.fixture
def world(built) -> DrivingWorld:
    """A fresh copy of the 6 s world (building one paints a city: copying is cheaper)."""
    return copy.deepcopy(built)


def kinds(world: DrivingWorld) -> list[str]:
    return [i.kind for i in world.log.infractions]


def test_the_expert_drives_its_route_cleanly_and_the_same_every_time(world):
    traces = [drive_episode(w, None) for w in (world, DrivingWorld(SEED, 6.0))]
    np.testing.assert_array_equal(traces[0].speed, traces[1].speed)
    scores = score_episode(traces[0])
    assert scores.route_completion == pytest.approx(100.0, abs=0.5)
    assert scores.driving_score >= 95.0 and scores.collisions == 0 and scores.off_road == 0
    assert traces[0].progress > 10.0


def test_standing_still_makes_no_progress(world):
    scores = score_episode(drive_episode(world, stand_still))
    assert world.ego.speed == 0.0
    assert scores.route_completion < 15.0  # only the braking distance
    assert scores.collisions == 0


def test_running_into_a_vehicle_is_an_at_fault_collision(world):
    agents = world.agents()
    k = agents.kind.index("collision_vehicle")
    world.advance(EgoState(agents.xy[k].copy(), float(agents.yaw[k]), 5.0))
    hits = [i for i in world.log.infractions if i.kind == "collision_vehicle"]
    assert hits and hits[0].at_fault and hits[0].other == agents.ident[k]
    # Contact that goes on is one collision, not one per step.
    world.advance(replace(world.ego))
    assert sum(i.kind == "collision_vehicle" for i in world.log.infractions) == 1


def test_a_vehicle_closing_in_ahead_sets_the_time_to_collision(world):
    agents = world.agents()
    k = agents.kind.index("collision_vehicle")
    heading = np.array([np.cos(agents.yaw[k]), np.sin(agents.yaw[k])])
    behind = agents.xy[k] - heading * (agents.size[k, 0] / 2 + EGO_LENGTH / 2 + 2.0)  # a 2 m gap
    world.advance(EgoState(behind, float(agents.yaw[k]), float(agents.speed[k]) + 8.0))
    assert world.log.ttc[-1] < TTC_BOUND


def test_turning_round_in_the_lane_is_driving_the_wrong_way(world):
    world.advance(replace(world.ego, yaw=world.ego.yaw + np.pi))
    assert "wrong_way" in kinds(world)


def test_stepping_onto_the_sidewalk_leaves_the_drivable_area(world):
    ego = world.ego
    side = np.array([np.sin(ego.yaw), -np.cos(ego.yaw)])  # to the ego's right
    for d in np.arange(1.0, 25.0, 0.5):
        spot = ego.xy + side * d
        ix, iy = world.static.cells(spot)
        if world.static.ground[ix, iy] == SIDEWALK and world.static.cls[ix, iy] == FREE:
            break
    else:
        pytest.fail("no sidewalk within 25 m to the ego's right")
    world.advance(replace(ego, xy=spot))
    assert "off_road" in kinds(world)


def test_crossing_the_stop_line_on_red_is_running_a_red_light(world):
    stop_s, light, axis = world.route.stops[0]
    assert float(green_left(light, axis, world.time + 0.1)) < 0  # as SEED was chosen
    world.advance(replace(world.ego, xy=world.route.xy[int((stop_s - EGO_LENGTH) / PATH_DS)], speed=5.0))
    assert "red_light" not in kinds(world)
    world.advance(replace(world.ego, xy=world.route.xy[int(stop_s / PATH_DS)]))
    assert "red_light" in kinds(world)


def test_the_episode_animation_shows_the_ego_and_rings_it_where_it_went_wrong(world, tmp_path):
    from PIL import Image

    from occtrain.data.synth.closed_loop_view import ALERT_COLOUR, EGO_AT, EGO_COLOUR, PIXELS, save_gif

    views: list = []
    drive_episode(world, stand_still, views)
    assert len(views) == 12  # every 0.5 s of the 6 s
    views[3].infractions = [Infraction("red_light", views[3].time)]
    gif = save_gif(world.static, views, tmp_path / "episode.gif", 0.5)
    with Image.open(gif) as image:
        assert image.n_frames == 12
        image.seek(0)
        first = np.asarray(image.convert("RGB"))
        image.seek(3)
        ringed = np.asarray(image.convert("RGB"))
    centre = (int(PIXELS * EGO_AT), PIXELS // 2)
    assert tuple(first[centre]) == EGO_COLOUR
    alert = np.all(ringed == ALERT_COLOUR, axis=-1)
    assert alert.sum() > 50 and not np.all(first == ALERT_COLOUR, axis=-1).any()


def test_recorded_frames_read_back_as_a_dataset_and_a_clip(world, tmp_path):
    from occtrain.data.closed_loop_recording import EPISODE_SCENE, EpisodeRecorder

    recorder = EpisodeRecorder(tmp_path, world, camera_size=(18, 32))
    for _ in range(3):
        index = recorder.record()
        labels = world.render()
        for _ in range(STRIDE):
            world.advance(None)
    assert index.scenes[EPISODE_SCENE] == [f["token"] for f in recorder.frames]
    assert index.frames(EPISODE_SCENE) == recorder.frames and index.has_frame_annotations(EPISODE_SCENE)
    token = recorder.token
    np.testing.assert_array_equal(index.labels(EPISODE_SCENE, token)["semantics"], labels["semantics"])
    assert index.images(EPISODE_SCENE, token).shape == (6, 18, 32, 3)
    clip = recorder.clip(history=4)  # only two frames before it so far
    assert clip.ann["history"] == 2 and clip.anchor["token"] == token
    assert len(clip.ann["tokens"]) == len(clip.ann["ego_poses"]) == 3 + 6
    # The unknown future is driving on at the current speed: 0.5 s apart along the heading.
    future = clip.ego_positions()[3:]
    speed = clip.anchor["ego_speed"]
    np.testing.assert_allclose(future, [[speed * 0.5 * k, 0.0] for k in range(1, 7)], atol=1e-3)


def test_shadow_episodes_meet_each_plan_with_what_the_expert_did_next(world):
    from occtrain.engine.closed_loop.episodes import shadow_episode

    planners = {"expert": lambda w: w.expert_plan(), "still": stand_still, "late": lambda w: None}
    frames = shadow_episode(world, planners)
    assert len(frames) == 13 - 6  # 6 s: 13 planning frames, each scored with a whole 3 s after it
    for f in frames:
        assert f.plans["late"] is None and len(f.agents) == 6 and f.agents[0].shape[1] == 5
        np.testing.assert_allclose(f.plans["expert"], f.logged, atol=1e-9)  # the expert's plan is the log
    moved = np.linalg.norm(frames[-1].logged[-1])
    assert moved > 5.0 and np.linalg.norm(frames[-1].plans["still"][-1]) == 0.0


def test_the_expert_answers_from_wherever_the_ego_is(world):
    # At 5 s, half a second before its light turns green, on its own episode: the expert
    # from here moves off as the logged expert did (to the IDM's float noise).
    while world.time < 5.0:
        world.advance(None)
    logged, here = world.expert_plan(), world.expert_from_here()
    assert logged[-1, 0] > 2.0  # it does move off within the 3 s
    np.testing.assert_allclose(here, logged, atol=0.05)
    # Put 2 m left of its route, the expert's plan leads back onto it, to the right, and
    # asking leaves the world as it was.
    left = np.array([-np.sin(world.ego.yaw), np.cos(world.ego.yaw)])
    world.advance(replace(world.ego, xy=world.ego.xy + 2.0 * left))
    arcs, speeds, step = world.traffic.s.copy(), world.traffic.v.copy(), world.step
    plan = world.expert_from_here()
    assert plan[-1, 1] == pytest.approx(-2.0, abs=0.3) and plan[-1, 0] > 2.0
    # ... by fading its offset from the route (LATERAL_DECAY_S), not jumping onto it at once.
    assert plan[0, 1] == pytest.approx(-2.0 + 2.0 * np.exp(-0.5 / LATERAL_DECAY_S), abs=0.15)
    assert np.array_equal(world.traffic.s, arcs) and np.array_equal(world.traffic.v, speeds) and world.step == step
