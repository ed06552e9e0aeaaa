"""The road context and the route's command: what they hold on routes built by hand, and that
a frame the closed loop drives is annotated exactly as the dataset annotates it."""

from __future__ import annotations

import numpy as np
import pytest

from occtrain.data.schema import ROUTE_ARC, RoadContext
from occtrain.data.synth.catalog import KINDS, TrackSet
from occtrain.data.synth.closed_loop_world import STRIDE, DrivingWorld
from occtrain.data.synth.road_context import road_context, route_command, route_points
from occtrain.data.synth.roads import Path
from occtrain.data.synth.scene import route_labels
from occtrain.data.synth.traffic import SIM_DT, mover_tracks
from occtrain.formats.occ3d import EGO_LENGTH

#: A light whose x-road traffic has green from 0 to 10 s of a 40 s period (amber from 7 s).
LIGHT = np.array([40.0, 0.0, 0.0, 10.0, 12.0, 38.0])


def straight(stops=((50.0, LIGHT, 0),)) -> Path:
    """200 m along +x from the origin, with a stop line 50 m along."""
    return Path.from_points(np.array([[0.0, 0.0], [200.0, 0.0]]), list(stops))


def left_turn(radius: float = 10.0, before: float = 30.0) -> Path:
    """``before`` m along +x, a quarter circle to the left, then 100 m along +y."""
    phi = np.linspace(0.0, np.pi / 2, 200)
    arc = np.stack([before + radius * np.sin(phi), radius * (1 - np.cos(phi))], axis=1)
    end = np.array([[before + radius, radius + 100.0]])
    return Path.from_points(np.concatenate([[[0.0, 0.0]], arc, end]), [])


def agents(*rows: tuple[str, float, float, float, float]) -> TrackSet:
    """One-frame tracks of (kind, x, y, yaw, speed), each the largest of its kind."""
    return TrackSet(
        cls=np.array([KINDS[k].cls for k, *_ in rows], dtype=np.int64),
        size=np.array([KINDS[k].size_hi for k, *_ in rows]).reshape(-1, 3),
        xy=np.array([[[x, y]] for _, x, y, _, _ in rows]).reshape(-1, 1, 2),
        yaw=np.array([[yaw] for *_, yaw, _ in rows]).reshape(-1, 1),
        speed=np.array([[v] for *_, v in rows]).reshape(-1, 1),
        parked=np.zeros(len(rows), bool),
        rider=np.full(len(rows), -1, dtype=np.int64),
    )


def rounded(expected):
    """What the annotation holds of ``expected``: numbers to 1e-4."""
    return pytest.approx(expected, abs=1e-4)


def context(route: Path, s: float, tracks: TrackSet, t: float = 5.0, pose=None, yaw: float = 0.0) -> RoadContext:
    pose = route_points(route, np.array([s]))[0] if pose is None else np.asarray(pose, dtype=np.float64)
    return road_context(route, s, pose, yaw, t, tracks, 0)


def test_on_a_straight_road_each_field_is_the_nearest_that_qualifies():
    car = KINDS["car"].size_hi
    tracks = agents(
        ("car", 5.0, 0.0, 0.0, 9.0),  # behind the ego
        ("car", 20.0, 0.3, np.pi, 6.0),  # oncoming
        ("car", 25.0, 3.5, 0.0, 9.0),  # the next lane
        ("car", 34.0, 0.4, 0.3, 5.0),  # the lead: ahead, overlapping sideways, same way
        ("truck", 50.0, 0.0, 0.0, 8.0),  # further ahead
        ("pedestrian", 22.0, 4.0, 0.0, 1.2),  # outside the corridor
        ("pedestrian", 41.0, -2.5, np.pi / 2, 1.4),  # in it
        ("pedestrian", 60.0, 0.0, 0.0, 1.0),  # beyond its 40 m
    )
    road = context(straight(), 10.0, tracks)
    np.testing.assert_allclose(road["route"], np.stack([ROUTE_ARC, np.zeros(len(ROUTE_ARC))], 1), atol=1e-9)
    assert road["curvature"] == 0.0
    assert road["lead"] == rounded({"gap": 24.0 - (EGO_LENGTH + car[0]) / 2, "speed": 5.0 * np.cos(0.3)})
    assert road["pedestrian"] == rounded({"distance": 31.0, "offset": -2.5, "speed": 1.4})
    # The stop line from the front bumper; at 5 s the light has 5 s of green left.
    assert road["stop_line"] == rounded({"distance": 40.0 - EGO_LENGTH / 2, "light": "green", "green_left": 5.0})


def test_the_light_is_amber_in_greens_last_seconds_and_red_after_it():
    route, nobody = straight(), agents()
    assert context(route, 10.0, nobody, t=8.0)["stop_line"] == rounded(
        {"distance": 40.0 - EGO_LENGTH / 2, "light": "amber", "green_left": 2.0}
    )
    assert context(route, 10.0, nobody, t=11.0)["stop_line"]["light"] == "red"
    assert context(route, 10.0, nobody, t=11.0)["stop_line"]["green_left"] == -1.0


def test_the_stop_line_holds_until_the_bumper_is_half_a_metre_past_it_and_only_within_60_m():
    route = straight(((50.0, LIGHT, 0), (150.0, LIGHT, 0)))
    at = 50.0 - EGO_LENGTH / 2  # the bumper on the line
    assert context(route, at + 0.4, agents())["stop_line"]["distance"] == pytest.approx(-0.4)
    assert context(route, at + 0.6, agents())["stop_line"] is None  # the next one is 99.4 m on
    assert context(route, at + 41.0, agents())["stop_line"]["distance"] == pytest.approx(59.0)


def test_along_a_turn_distances_follow_the_route_not_the_egos_axis():
    route = left_turn()
    quarter = np.pi / 2 * 10.0
    beyond = 30.0 + quarter + 8.0  # arc length of a point 8 m up the crossing road
    tracks = agents(
        ("car", 40.0, 18.0, np.pi / 2, 7.0),  # beyond the turn, heading up the new road
        ("car", 45.0, 0.0, 0.0, 7.0),  # straight ahead of the ego, off the route
    )
    road = context(route, 10.0, tracks)
    car = KINDS["car"].size_hi
    assert road["lead"] == pytest.approx({"gap": beyond - 10.0 - (EGO_LENGTH + car[0]) / 2, "speed": 7.0}, abs=0.05)
    assert road["curvature"] == pytest.approx(0.1, rel=0.05)
    # The route's points are the turn's, seen from the ego.
    assert road["route"][8] == pytest.approx([20.0, 0.0], abs=1e-6)
    assert road["route"][-1][1] > 20.0
    # A turn more than 60 m of route ahead is not in the curvature.
    assert context(left_turn(before=100.0), 10.0, agents())["curvature"] == 0.0


def test_the_route_command_looks_3_s_ahead_at_the_current_speed_and_at_least_2_m_s():
    route = left_turn(before=30.0)
    assert route_command(route, 0.0, np.zeros(2), 0.0, 5.0) == "go straight"  # 15 m: before the turn
    assert route_command(route, 0.0, np.zeros(2), 0.0, 13.0) == "turn left"  # 39 m: in it
    tight = left_turn(radius=3.0)
    for s, command in ((28.0, "turn left"), (20.0, "go straight")):  # standing, it looks 6 m on
        pose = np.array([s, 0.0])
        assert route_command(tight, s, pose, 0.0, 0.0) == route_command(tight, s, pose, 0.0, 2.0) == command
    mirrored = Path(route.xy * [1.0, -1.0], -route.heading, -route.curvature, [])
    assert route_command(mirrored, 0.0, np.zeros(2), 0.0, 13.0) == "turn right"


def test_an_ego_off_its_route_sees_the_route_where_it_lies():
    road = context(straight(), 10.0, agents(), pose=[10.0, 1.5], yaw=0.1)
    local = np.asarray(road["route"])
    assert local[0] == pytest.approx([-1.5 * np.sin(0.1), -1.5 * np.cos(0.1)], abs=1e-4)
    assert np.all(np.diff(local[:, 1]) < 0)  # the road runs off to the right of the ego's axis


def close(a, b, where: str = "") -> None:
    """``a == b`` with numbers to 2e-4 (both rounded to 1e-4)."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            close(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b)):
            close(x, y, f"{where}[{k}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert a == pytest.approx(b, abs=2e-4), where
    else:
        assert a == b, where


@pytest.mark.parametrize(("seed", "seconds"), [(45, 4.0), (1, 8.0)])  # a turn, a lead, red; pedestrians
def test_a_frame_the_expert_drives_in_the_loop_is_annotated_as_the_dataset_annotates_it(seed, seconds):
    """The closed loop's road and command (the driven ego's projection on its route, its
    pose, the agents now) equal what the synthesis computes for the same frame (the
    expert's logged arc length and pose, its logged traffic, the same pedestrians and
    objects: ``scene.route_labels``)."""
    world = DrivingWorld(seed, seconds)
    rest = slice(len(world.expert.movers) - 1, None)  # the agents after the movers: pedestrians, objects
    driven, others = [], []
    while True:
        if world.at_frame:
            driven.append(world.frame_annotation("episode"))
            now = world.agents().tracks()
            others.append((now.xy[rest], now.yaw[rest], now.speed[rest]))
        if world.done:
            break
        world.advance(None)
    n = len(driven)
    movers = mover_tracks(world.expert, STRIDE)  # the logged traffic, as a scene's tracks hold it
    logged = TrackSet(
        cls=now.cls,
        size=now.size,
        xy=np.concatenate([movers.xy[:, :n], np.concatenate([o[0] for o in others], axis=1)]),
        yaw=np.concatenate([movers.yaw[:, :n], np.concatenate([o[1] for o in others], axis=1)]),
        speed=np.concatenate([movers.speed[:, :n], np.concatenate([o[2] for o in others], axis=1)]),
        parked=now.parked,
        rider=now.rider,
    )
    labels = route_labels(world.expert, logged, n, STRIDE)
    for i, (frame, (command, road)) in enumerate(zip(driven, labels)):
        assert frame["command"] == command, i
        close(frame["road"], road, f"frame {i}")
    roads = [f["road"] for f in driven]
    assert any(r["lead"] for r in roads) and any(r["stop_line"] for r in roads)
    assert any(f["command"] != "go straight" for f in driven) or any(r["pedestrian"] for r in roads)
    assert world.time == pytest.approx((n - 1) * STRIDE * SIM_DT)
