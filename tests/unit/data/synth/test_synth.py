"""The synthetic world: geometry, determinism, class coverage, masks, trajectories, kinematics."""

from __future__ import annotations

import collections
import json
import re

import numpy as np
import pytest

from occtrain.data.cameras import nuscenes_rig
from occtrain.data.schema import (
    COMMANDS,
    META_ACCEL_THRESHOLD,
    META_DIRECTIONS,
    META_SPEEDS,
    ROUTE_ARC,
    STATUS_VALUES,
    STOP_SPEED,
    FrameAnnotation,
)
from occtrain.data.synth import SyntheticScene, generate_scene
from occtrain.data.synth.annotate import SIDECAR_RULES
from occtrain.data.synth.grid import GROUND_LAYER, GROUND_LAYERS, GROUND_TOP_Z
from occtrain.data.synth.raster import LIDAR, masks
from occtrain.data.synth.roads import PATH_DS
from occtrain.formats.occ3d import (
    CLASS_INDEX,
    CLASS_NAMES,
    FRAME_DT,
    FREE,
    GRID_SHAPE,
    RANGE_MIN,
    VOXEL_SIZE,
    metres_to_index,
    voxel_centers_1d,
)

FRAMES = 8
GROUND_CLASSES = [CLASS_INDEX[c] for c in ("driveable_surface", "other_flat", "sidewalk", "terrain")]
MOVABLE = set(range(11))


@pytest.fixture(scope="module")
def scene() -> SyntheticScene:
    return generate_scene(name="scene-0003", seed=1234, num_frames=FRAMES)


@pytest.fixture(scope="module")
def labels(scene) -> list[dict[str, np.ndarray]]:
    return [scene.render(i) for i in range(FRAMES)]


def to_global(frame: FrameAnnotation, xy) -> np.ndarray:
    """Ego-frame points of ``frame`` -> global, written out from the pose (independent of the code)."""
    yaw = frame["ego_pose"]["yaw"]
    t = np.array(frame["ego_pose"]["translation"][:2])
    p = np.asarray(xy, dtype=np.float64)
    return (
        np.stack(
            [np.cos(yaw) * p[..., 0] - np.sin(yaw) * p[..., 1], np.sin(yaw) * p[..., 0] + np.cos(yaw) * p[..., 1]], -1
        )
        + t
    )


def to_ego(frame: FrameAnnotation, xy) -> np.ndarray:
    yaw = frame["ego_pose"]["yaw"]
    d = np.asarray(xy, dtype=np.float64) - np.array(frame["ego_pose"]["translation"][:2])
    return np.stack(
        [np.cos(yaw) * d[..., 0] + np.sin(yaw) * d[..., 1], -np.sin(yaw) * d[..., 0] + np.cos(yaw) * d[..., 1]], -1
    )


def rotate_to_global(frame: FrameAnnotation, v) -> np.ndarray:
    yaw = frame["ego_pose"]["yaw"]
    v = np.asarray(v, dtype=np.float64)
    return np.stack(
        [np.cos(yaw) * v[..., 0] - np.sin(yaw) * v[..., 1], np.sin(yaw) * v[..., 0] + np.cos(yaw) * v[..., 1]], -1
    )


# ---------------------------------------------------------------- API, grid, records


def test_scene_api_grid_and_records(scene, labels):
    assert scene.name == "scene-0003" and len(scene.frames) == FRAMES
    for lab in labels:
        assert set(lab) == {"semantics", "mask_lidar", "mask_camera"}
        for arr in lab.values():
            assert arr.shape == GRID_SHAPE and arr.dtype == np.uint8
        assert lab["semantics"].max() <= FREE
        assert set(np.unique(lab["mask_lidar"])) == {0, 1} and set(np.unique(lab["mask_camera"])) == {0, 1}
    tokens = [f["token"] for f in scene.frames]
    assert len(set(tokens)) == FRAMES and all(re.fullmatch(r"[0-9a-f]{32}", t) for t in tokens)
    assert np.all(np.diff([f["timestamp"] for f in scene.frames]) == int(FRAME_DT * 1e6))
    for i, f in enumerate(scene.frames):
        assert set(f) == set(FrameAnnotation.__annotations__)
        assert json.loads(json.dumps(f)) == f
        assert (f["scene"], f["index"], f["caption"], f["narration"]) == ("scene-0003", i, "", "")
        assert f["ego_pose"]["translation"][2] == 0.0
        assert f["command"] in COMMANDS
        assert f["meta_action"]["speed"] in META_SPEEDS and f["meta_action"]["direction"] in META_DIRECTIONS
        assert len(f["agent_futures"]) == len(f["agent_future_mask"]) == len(f["boxes"])
        for box in f["boxes"]:
            assert box["category"] in CLASS_NAMES[:11]
            assert abs(box["center"][0]) < 40 and abs(box["center"][1]) < 40
            assert box["center"][2] == pytest.approx(GROUND_TOP_Z + box["size"][2] / 2, abs=1e-3)
            cat, attr = box["category"], box["attribute"]
            if cat in ("barrier", "traffic_cone"):
                assert attr == ""
            elif cat in ("bicycle", "motorcycle"):
                assert attr in ("with rider", "without rider")
            elif cat == "pedestrian":
                assert attr in ("moving", "standing")
            else:
                assert attr in ("moving", "parked", "stopped")
            assert attr == "" or attr in STATUS_VALUES


def test_the_ground_is_one_surface_layer_and_the_ego_box_is_free(labels):
    for lab in labels:
        sem = lab["semantics"]
        ground = sem[..., GROUND_LAYER]
        assert np.isin(ground[ground != FREE], GROUND_CLASSES).all()
        assert (sem[..., :GROUND_LAYER] == FREE).all()  # nothing under the surface
        assert not np.isin(sem[..., GROUND_LAYERS:], GROUND_CLASSES).any()
        # Labelled where the sweeps saw it: some ground, not all of it.
        assert 0.15 < (ground != FREE).mean() < 0.9
        # Ground top at -0.2 m: the lidar 1.84 m above it, at 1.64 m in the ego frame.
        assert voxel_centers_1d(2)[GROUND_LAYERS - 1] < GROUND_TOP_Z < voxel_centers_1d(2)[GROUND_LAYERS]
        ego = sem[95:105, 98:102, GROUND_LAYERS:6]  # 4 m x 1.6 m around the origin, up to 1.4 m
        assert (ego == FREE).all()


def test_same_seed_same_scene_other_seed_other_scene(scene, labels):
    again = generate_scene(name="another-name", seed=1234, num_frames=FRAMES)
    for a, b in zip(scene.frames, again.frames):
        assert {**a, "scene": ""} == {**b, "scene": ""}
    for i in (0, FRAMES - 1):
        for key, arr in again.render(i).items():
            assert np.array_equal(arr, labels[i][key])
    other = generate_scene(name="scene-0003", seed=np.uint32(1235), num_frames=2)  # as synthesize passes seeds
    assert not np.array_equal(other.render(0)["semantics"], labels[0]["semantics"])
    assert not {f["token"] for f in other.frames} & {f["token"] for f in scene.frames}


def test_every_class_appears_in_three_short_scenes():
    seen = np.zeros(FREE + 1, bool)
    for seed in (11, 22, 33):
        sc = generate_scene(name=f"s{seed}", seed=seed, num_frames=4)
        for i in range(4):
            seen |= np.bincount(sc.render(i)["semantics"].ravel(), minlength=FREE + 1) > 0
    assert [CLASS_NAMES[c] for c in range(FREE) if not seen[c]] == []


# ---------------------------------------------------------------- visibility


def _at(x: float, y: float, z: float) -> tuple[int, int, int]:
    return tuple(int(i) for i in metres_to_index(np.array([x, y, z])))


def _wall_world() -> np.ndarray:
    """Flat road, and a wall 4 m high from x = 10 to 12 m spanning y in [-8, 8] m."""
    sem = np.full(GRID_SHAPE, FREE, np.uint8)
    sem[..., GROUND_LAYER] = CLASS_INDEX["driveable_surface"]
    (ix0, iy0, _), (ix1, iy1, _) = _at(10.0, -8.0, 0.0), _at(12.0, 8.0, 0.0)
    sem[ix0:ix1, iy0:iy1, GROUND_LAYERS:12] = CLASS_INDEX["manmade"]
    return sem


def test_a_wall_hides_what_is_behind_it_and_shows_its_face():
    sem = _wall_world()
    lidar, camera = masks(sem)
    face, behind, inside = _at(10.1, 0.1, 0.7), _at(16.1, 0.1, 0.7), _at(11.3, 0.1, 0.7)
    before, ground_before, ground_behind = _at(6.1, 0.1, 0.7), _at(8.1, 0.1, -0.3), _at(20.1, 0.1, -0.3)
    for m in (lidar, camera):
        assert m[face] == 1 and m[before] == 1 and m[ground_before] == 1
        assert m[behind] == 0 and m[inside] == 0 and m[ground_behind] == 0
        assert (m[..., :GROUND_LAYER] == 0).all()  # under the ground surface
        assert 0 < m.mean() < 1
    assert not (camera & ~lidar).any()  # mask_camera lies inside mask_lidar
    # Beside the wall nothing is hidden, out to where the 32 beams cross every layer (~17 m).
    assert lidar[_at(8.1, 12.1, 0.7)] == 1 and lidar[_at(0.1, 14.1, -0.3)] == 1
    # A ray that returns nothing observes nothing: up into the sky beside the wall, the
    # lidar sees no voxel though its top beam passes; in front of the wall the same beam
    # returns from it and observes the air it crossed.
    assert lidar[_at(6.1, 14.1, 4.5)] == 0 and lidar[_at(8.1, 0.1, 3.3)] == 1
    # Far out, one sweep's beams meet the ground in rings: between two rings, nothing.
    ring = 1.84 / np.tan(np.deg2rad(-np.asarray(LIDAR.beams)[np.asarray(LIDAR.beams) < 0]))
    gap = next(float((a + b) / 2) for a, b in zip(sorted(ring), sorted(ring)[1:]) if 20 < a and b < 40 and b - a > 8)
    assert lidar[_at(0.1, gap, -0.3)] == 0


def test_in_a_scene_voxels_behind_a_visible_building_face_are_hidden(labels):
    """Step 3 m beyond camera-visible facade voxels (inside a facade, not at its edge): hidden.
    Lines of sight start at the middle of the six cameras (they sit within 1 m of it)."""
    origin = np.mean([cam.centre for cam in nuscenes_rig(72, 128)], axis=0)
    checked = 0
    for lab in labels:
        sem, cam = lab["semantics"], lab["mask_camera"]
        man = sem == CLASS_INDEX["manmade"]
        for idx in np.argwhere(man & (cam == 1))[::7]:
            x, y, z = idx
            centre = RANGE_MIN + (idx + 0.5) * VOXEL_SIZE
            d = centre - origin
            # The facade must continue around the voxel across the line of sight.
            patch = (
                man[x, y - 1 : y + 2, z - 1 : z + 2] if abs(d[0]) >= abs(d[1]) else man[x - 1 : x + 2, y, z - 1 : z + 2]
            )
            if patch.size != 9 or not patch.all():
                continue
            back = metres_to_index(centre + 3.0 * d / np.linalg.norm(d))
            if np.all(back >= 0) and np.all(back < GRID_SHAPE):
                assert cam[tuple(back)] == 0
                checked += 1
    assert checked > 20


def test_masks_are_partial_and_see_no_deeper_than_the_ground(labels):
    for lab in labels:
        lidar, cam = lab["mask_lidar"], lab["mask_camera"]
        assert 0.03 < lidar.mean() < 0.3 and 0.02 < cam.mean() < 0.3
        assert (lidar[..., :GROUND_LAYER] == 0).all() and (cam[..., :GROUND_LAYER] == 0).all()
        assert not (cam & ~lidar).any()


# ---------------------------------------------------------------- trajectories and labels


def test_ego_future_and_past_are_the_poses_seen_from_the_current_frame(scene):
    frames = scene.frames
    n = len(frames)
    for i, f in enumerate(frames):
        for k, (wp, m) in enumerate(zip(f["ego_future"], f["ego_future_mask"])):
            j = i + k + 1
            assert m == int(j < n)
            want = to_ego(f, frames[j]["ego_pose"]["translation"][:2]) if j < n else np.zeros(2)
            assert np.allclose(wp, want, atol=2e-3)
        for k, (wp, m) in enumerate(zip(f["ego_past"], f["ego_past_mask"])):
            j = i - len(f["ego_past"]) + k
            assert m == int(j >= 0)
            want = to_ego(f, frames[j]["ego_pose"]["translation"][:2]) if j >= 0 else np.zeros(2)
            assert np.allclose(wp, want, atol=2e-3)


def test_the_command_and_the_road_come_from_the_egos_route(scene):
    """The command is ST-P3's rule on the route's point max(speed, 2 m/s) x 3 s of arc ahead
    (as the closed loop takes it), not on the ego's own future; the road's points are the
    route's at ROUTE_ARC from the ego's arc length on it, seen from the ego."""
    for i, f in enumerate(scene.frames):
        s = float(scene.progress[i])
        ahead = s + max(f["ego_speed"], 2.0) * 3.0
        k = int(ahead / PATH_DS)
        point = scene.route.xy[k] + (ahead / PATH_DS - k) * (scene.route.xy[k + 1] - scene.route.xy[k])
        y = to_ego(f, point)[1]
        assert f["command"] == ("turn left" if y > 2 else "turn right" if y < -2 else "go straight"), i
        road = f["road"]
        arc = (s + np.asarray(ROUTE_ARC)) / PATH_DS
        k = arc.astype(int)
        want = scene.route.xy[k] + (arc - k)[:, None] * (scene.route.xy[k + 1] - scene.route.xy[k])
        assert np.allclose(to_global(f, road["route"]), want, atol=2e-3), i
        assert np.allclose(road["route"][0], 0.0, atol=2e-3)  # the expert drives on its route


def test_agents_move_by_their_velocity_and_futures_match_later_boxes(scene):
    frames = scene.frames
    moved = 0
    for i in range(len(frames) - 1):
        a, b = frames[i], frames[i + 1]
        later = {x["track_id"]: x for x in b["boxes"]}
        for box in a["boxes"]:
            nxt = later.get(box["track_id"])
            if nxt is None:
                continue
            assert nxt["category"] == box["category"]
            step = to_global(b, nxt["center"][:2]) - to_global(a, box["center"][:2])
            mean_v = (rotate_to_global(a, box["velocity"]) + rotate_to_global(b, nxt["velocity"])) / 2
            assert np.linalg.norm(step - mean_v * FRAME_DT) < 0.25
            moved += np.linalg.norm(step) > 1.0
    assert moved > 10
    for i, f in enumerate(frames):
        for box, fut, mask in zip(f["boxes"], f["agent_futures"], f["agent_future_mask"]):
            for k, (wp, m) in enumerate(zip(fut, mask)):
                j = i + k + 1
                assert m == int(j < len(frames))
                hit = [x for x in frames[j]["boxes"] if x["track_id"] == box["track_id"]] if j < len(frames) else []
                if hit:
                    assert np.allclose(to_global(f, wp), to_global(frames[j], hit[0]["center"][:2]), atol=3e-3)
                elif not m:
                    assert wp == [0.0, 0.0]


def test_static_structure_stays_put_between_frames(scene, labels):
    for i in range(len(labels) - 1):
        a, b = scene.frames[i], scene.frames[i + 1]
        ix, iy, iz = np.nonzero(
            np.isin(labels[i]["semantics"], [CLASS_INDEX["manmade"], CLASS_INDEX["vegetation"]] + GROUND_CLASSES)
        )
        xy = np.stack([voxel_centers_1d(0)[ix], voxel_centers_1d(1)[iy]], -1)
        j = metres_to_index(to_ego(b, to_global(a, xy)))
        ok = np.all((j >= 0) & (j < GRID_SHAPE[:2]), axis=1)
        got = labels[i + 1]["semantics"][j[ok, 0], j[ok, 1], iz[ok]]
        want = labels[i]["semantics"][ix[ok], iy[ok], iz[ok]]
        static = ~np.isin(got, list(MOVABLE))
        assert ok.sum() > 8_000
        # Labels are where the sweeps saw a surface; that edge is sampled from each frame's
        # rotated grid, so a few per cent of the voxels near it differ between frames.
        assert (got == want)[static].mean() > 0.9


@pytest.fixture(scope="module")
def long_scenes() -> list[SyntheticScene]:
    """Six 40-frame routes: between them every branch of the meta-action rule occurs."""
    return [generate_scene(name=f"m{seed}", seed=seed, num_frames=40) for seed in range(6)]


def test_meta_action_follows_the_documented_rule(long_scenes):
    branches = collections.Counter()
    for scene in long_scenes:
        frames = scene.frames
        for i in range(len(frames) - 6):
            f = frames[i]
            v = [frames[i + k]["ego_speed"] for k in range(3)]
            accel = (v[2] - v[0]) / 1.0
            speed = "maintain" if abs(accel) < META_ACCEL_THRESHOLD else "accelerate" if accel > 0 else "decelerate"
            turn = np.degrees(np.angle(np.exp(1j * (frames[i + 6]["ego_pose"]["yaw"] - f["ego_pose"]["yaw"]))))
            lateral = to_ego(f, frames[i + 6]["ego_pose"]["translation"][:2])[1]
            if max(v) <= STOP_SPEED:
                branch, direction = "stop", "stop"
            elif abs(turn) > SIDECAR_RULES.turn_heading_deg:
                branch, direction = "turn", "left" if turn > 0 else "right"
            elif abs(lateral) > SIDECAR_RULES.bear_lateral_m:
                branch, direction = "bear by offset", "bear left" if lateral > 0 else "bear right"
            elif abs(turn) > SIDECAR_RULES.bear_heading_deg:
                branch, direction = "bear by heading", "bear left" if turn > 0 else "bear right"
            else:
                branch, direction = "straight", "straight"
            assert f["meta_action"] == {"speed": speed, "direction": direction}, (scene.name, i)
            branches.update([speed, branch, direction])
    # Every branch of the rule was checked, not only the common ones.
    expected = {
        "maintain",
        "accelerate",
        "decelerate",
        "stop",
        "turn",
        "bear by offset",
        "bear by heading",
        "straight",
        "left",
        "right",
    }
    assert expected <= set(branches), branches


# ---------------------------------------------------------------- kinematics and variety


def test_motion_is_bounded_and_routes_vary_by_seed():
    commands, directions = set(), set()
    for seed in range(6):
        sc = generate_scene(name=f"v{seed}", seed=seed, num_frames=40)
        speed = np.array([f["ego_speed"] for f in sc.frames])
        assert np.all(np.abs([f["ego_accel"] for f in sc.frames]) <= 6.0 + 1e-6)
        assert np.all(np.abs([f["ego_yaw_rate"] for f in sc.frames]) < 1.0)
        assert np.all((speed >= 0) & (speed < 16))
        for f in sc.frames:
            for box in f["boxes"]:
                limit = 2.0 if box["category"] == "pedestrian" else 16.0
                assert np.hypot(*box["velocity"]) < limit
        commands |= {f["command"] for f in sc.frames}
        directions |= {f["meta_action"]["direction"] for f in sc.frames}
    assert commands == set(COMMANDS)
    assert {"straight", "left", "right", "stop"} <= directions
    assert directions & {"bear left", "bear right"}


# ---------------------------------------------------------------- looking like Occ3D-nuScenes


@pytest.fixture(scope="module")
def world_stats():
    """Three 40-frame scenes of the embedded world (the quickstart's scene length: what a
    scene's sweeps observe grows with its route), every fourth frame counted."""
    from pathlib import Path

    from occtrain.data.stats import _Counts

    counts = _Counts()
    for seed in (101, 202, 303):
        scene = generate_scene(name=f"w{seed}", seed=seed, num_frames=40)
        for i in range(0, 40, 4):
            counts.add(scene.render(i))
    return counts.result(Path("embedded"), "val", "v4")


def test_the_world_meets_the_occ3d_targets_but_one(world_stats):
    """Occupancy, columns, layers, both masks and the class shares are in their target
    ranges (``data.stats.TARGETS``). Missed, and pinned here so a change that meets it
    updates this test and docs/world.md: the occupied share inside mask_camera (target 30-70 %).
    Every ray that returns observes the free voxels it crosses, and in these streets that
    is about nine free voxels for each surface the cameras see."""
    missed = {k for k, ok in world_stats.targets().items() if not ok}
    assert missed == {"occupied_in_camera"}, world_stats
    assert 0.05 < world_stats.occupied_in_camera < 0.2


def test_surfaces_not_solids(world_stats):
    """The old world's 36 % occupied and 100 % occupied columns came from solid buildings
    and two solid ground layers; a real frame: 6.1 % and 39 %."""
    assert world_stats.per_layer[0] == 0  # under the ground surface
    assert world_stats.voxels_per_column < 3.5
    assert world_stats.camera_inside_lidar == 1.0


def test_a_longer_scene_gets_a_larger_road_grid_and_the_quickstarts_keeps_its_own():
    """A route of an 80-frame scene ran off the 800 m grid (no crossing left ahead: a raw
    StopIteration); the grid grows with the scene, and a 40-frame scene's is unchanged."""
    from occtrain.data.synth.scene import GRID_EXTENT, generate_scene, grid_extent
    from occtrain.data.synth.traffic import SIM_DT
    from occtrain.formats.occ3d import FRAME_DT, FUTURE_STEPS

    def steps(frames: int) -> int:
        return (frames + FUTURE_STEPS - 1) * round(FRAME_DT / SIM_DT) + 1

    assert grid_extent(steps(40)) == GRID_EXTENT and grid_extent(steps(80)) > 1.5 * GRID_EXTENT
    assert len(generate_scene("long", 0, 80).frames) == 80
