"""One synthetic scene: build the world, run the traffic, then render and annotate frames."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occtrain.data.schema import STOP_SPEED, Command, FrameAnnotation, RoadContext
from occtrain.data.synth.annotate import EgoMotion, frame_annotation, past_accels
from occtrain.data.synth.catalog import TrackSet
from occtrain.data.synth.citymap import StaticMap, paint_city
from occtrain.data.synth.population import EgoPlan, ego_mover, ego_start, spawn_traffic, spawn_walkers
from occtrain.data.synth.raster import frame_semantics, masks, observe_static
from occtrain.data.synth.road_context import road_context, route_command
from occtrain.data.synth.roads import PATH_DS, Path, RoadNetwork
from occtrain.data.synth.traffic import (
    SIM_DT,
    MotionResult,
    Mover,
    Walker,
    mover_tracks,
    settle_traffic,
    simulate_movers,
    walker_tracks,
)
from occtrain.formats.occ3d import FRAME_DT, FUTURE_STEPS, RANGE_MAX

#: Margin (m) around the ego's possible route within which traffic is spawned.
SPAWN_MARGIN = 90.0
#: Margin around the ego's frames within which the city is painted: the grid's half
#: diagonal plus a little, so every frame's grid lies inside the painted region.
PAINT_MARGIN = float(np.hypot(*RANGE_MAX[:2])) + 3.0


@dataclass
class SyntheticScene:
    """A generated scene: its frames' annotations and what is needed to render each frame."""

    name: str
    seed: int
    frames: list[FrameAnnotation]
    static: StaticMap
    tracks: TrackSet
    ego: EgoMotion
    net: RoadNetwork
    #: (frames, X, Y, Z) bool lidar visibility of each frame, from ``observe_static``.
    lidar: np.ndarray
    #: The ego's route and its arc length on it at each frame (what the command and the
    #: road context are read from).
    route: Path
    progress: np.ndarray

    def render(self, i: int) -> dict[str, np.ndarray]:
        """Occ3D labels of frame ``i``: semantics, mask_lidar, mask_camera ((200, 200, 16) uint8)."""
        if not 0 <= i < len(self.frames):
            raise IndexError(f"scene {self.name} has {len(self.frames)} frames, asked for frame {i}")
        sem = self.semantics(i)
        lidar, camera = masks(sem, self.lidar[i])
        return {"semantics": sem, "mask_lidar": lidar, "mask_camera": camera}

    def semantics(self, i: int) -> np.ndarray:
        """(200, 200, 16) uint8 Occ3D classes of frame ``i``."""
        return frame_semantics(self.static, self.tracks, i, self.ego.xy[i], float(self.ego.yaw[i]))

    def cameras(self, i: int, semantics: np.ndarray, height: int, width: int) -> list:
        """The six camera views of frame ``i`` (``camera_render.CameraView``, CAMERA_NAMES order)."""
        from occtrain.data.synth.camera_render import FrameWorld, render_cameras

        world = FrameWorld(self.static, self.net, self.ego.xy[i], float(self.ego.yaw[i]), i * FRAME_DT)
        return render_cameras(semantics, world, height, width)


def prepare_sensors(camera_size: tuple[int, int] | None = None) -> None:
    """Compute the per-process sensor geometry once (the lidar's per-voxel beams, the mask
    cameras' ray walks and pixels, and the ray walks at ``camera_size`` if given), so that
    what follows measures or shows per-frame work only."""
    from occtrain.data.synth.camera_render import MASK_RAYS, camera_rays, voxels_in_view
    from occtrain.data.synth.raster import LIDAR, sensor_geometry

    sensor_geometry(LIDAR)
    camera_rays(*MASK_RAYS)
    voxels_in_view()
    if camera_size is not None:
        camera_rays(*camera_size)


@dataclass
class Population:
    """Who is on the roads of a scene over ``steps`` simulation steps: the network, the
    ego's plan, the settled traffic (``motion.movers[0]`` is the ego, the route follower
    that generates the data) and the pedestrians with their walks."""

    net: RoadNetwork
    plan: EgoPlan
    motion: MotionResult
    #: (movers,) index in ``motion.movers`` of each mover's towing tractor, or -1.
    host: np.ndarray
    walkers: list[Walker]
    walk_hist: tuple[np.ndarray, np.ndarray, np.ndarray]


#: Half the side of the road grid (m) for scenes up to ``GRID_SECONDS`` long (40 frames and
#: their future); a longer scene's routes reach further, so its grid grows in proportion
#: (a route that ran out of crossings would have nowhere to go).
GRID_EXTENT, GRID_SECONDS = 800.0, 23.0


def grid_extent(steps: int) -> float:
    """The road grid's half side for a scene simulated ``steps`` steps."""
    return GRID_EXTENT * max(1.0, steps * SIM_DT / GRID_SECONDS)


def _ego_on_roads(seed: int, steps: int, extent: float | None) -> tuple[RoadNetwork, EgoPlan, Mover]:
    """Scene ``seed``'s roads, the ego's start and the ego (its route and speed plan)."""
    net = RoadNetwork.random(np.random.default_rng([seed, 0]), seed, extent or grid_extent(steps))
    route_rng = np.random.default_rng([seed, 1])
    net, plan = ego_start(net, route_rng)
    return net, plan, ego_mover(net, plan, route_rng, steps, SIM_DT)


def populate(seed: int, steps: int, extent: float | None = None) -> Population:
    """The roads (a grid over [-extent, extent]^2, by default ``grid_extent(steps)``), the
    ego's route and the traffic of scene ``seed``, simulated for ``steps`` steps."""
    net, plan, ego = _ego_on_roads(seed, steps, extent)
    reach = ego.path.xy[: int(ego.v_des.max() * steps * SIM_DT / PATH_DS) + 1]
    lo, hi = reach.min(0) - SPAWN_MARGIN, reach.max(0) + SPAWN_MARGIN
    traffic_rng = np.random.default_rng([seed, 2])
    movers = spawn_traffic(net, plan, ego, lo, hi, traffic_rng, steps, SIM_DT)
    walkers = spawn_walkers(net, lo, hi, traffic_rng)
    motion, walkers, walk_hist = settle_traffic(movers, walkers, steps)
    row = {id(m): k for k, m in enumerate(motion.movers)}
    host = np.array([row[id(movers[m.host])] if m.host >= 0 else -1 for m in motion.movers], dtype=np.int64)
    return Population(net, plan, motion, host, walkers, walk_hist)


def route_labels(
    motion: MotionResult, tracks: TrackSet, num_frames: int, stride: int
) -> list[tuple[Command, RoadContext]]:
    """The driving command and the road context of each of the first ``num_frames`` frames
    (every ``stride`` steps) of the ego (``motion``'s row 0, on its route ``motion.movers[0].path``)
    among ``tracks`` (sampled at the frames), by the functions the closed loop calls."""
    route = motion.movers[0].path
    out = []
    for i in range(num_frames):
        step = i * stride
        s, xy, yaw = float(motion.s[0, step]), motion.xy[0, step], float(motion.yaw[0, step])
        command = route_command(route, s, xy, yaw, float(motion.v[0, step]))
        out.append((command, road_context(route, s, xy, yaw, step * SIM_DT, tracks, i)))
    return out


#: A "red-light stop" frame: the ego stands (speed at most STOP_SPEED) this close (m) to a stop
#: line whose light is not green.
STOP_LINE_NEAR = 10.0


@dataclass
class SceneEvents:
    """How many of a scene's frames with a full future inside it (a clip's anchors; all of
    them in a scene too short to have one) show each situation a planner must read off the road."""

    turns: int  # the command turns
    red_stops: int  # the ego stands at a red or amber stop line (STOP_LINE_NEAR)
    leads: int  # a lead vehicle within ROAD_REACH


def count_events(labels: list[tuple[Command, RoadContext]], speed: np.ndarray) -> SceneEvents:
    """SceneEvents of frames labelled ``labels`` (``route_labels``) with ego speeds ``speed``."""
    n = len(labels)
    frames = range(n - FUTURE_STEPS) if n > FUTURE_STEPS else range(n)
    turns = stops = leads = 0
    for i in frames:
        command, road = labels[i]
        line = road["stop_line"]
        turns += command != "go straight"
        leads += road["lead"] is not None
        stops += bool(
            speed[i] <= STOP_SPEED and line and line["light"] != "green" and line["distance"] <= STOP_LINE_NEAR
        )
    return SceneEvents(turns, stops, leads)


def scene_events(seed: int, num_frames: int, traffic: bool = True) -> SceneEvents:
    """SceneEvents of scene ``seed`` at ``num_frames`` frames, from its traffic (a fraction of
    the scene's cost: no city, no rendering; the city's placed objects, parked off the lanes,
    are left out of the lead test). Without ``traffic``, of the ego driving its route alone,
    a fifth of that cost again: no lead then, and the turns and stops of an ego that no
    vehicle holds up (traffic only ever took some away, in 40 draws measured)."""
    stride = int(round(FRAME_DT / SIM_DT))
    steps = (num_frames + FUTURE_STEPS - 1) * stride + 1
    if traffic:
        pop = populate(int(seed), steps)
        motion = pop.motion
        tracks = TrackSet.concat([mover_tracks(motion, stride), walker_tracks(pop.walkers, pop.walk_hist, stride)])
    else:
        motion = simulate_movers([_ego_on_roads(int(seed), steps, None)[2]], steps, np.array([-1]))
        tracks = mover_tracks(motion, stride)  # nobody
    return count_events(route_labels(motion, tracks, num_frames, stride), motion.v[0, ::stride])


def generate_scene(name: str, seed: int, num_frames: int = 40) -> SyntheticScene:
    """Build scene ``name`` deterministically from ``seed`` (the name only labels it).

    Frames are FRAME_DT apart; the world is simulated FUTURE_STEPS frames past the last
    one so futures and meta actions near the end exist.
    """
    if num_frames < 1:
        raise ValueError(f"num_frames must be at least 1, got {num_frames}")
    seed = int(seed)  # numpy integer seeds would overflow in the timestamp arithmetic
    stride = int(round(FRAME_DT / SIM_DT))
    total_frames = num_frames + FUTURE_STEPS
    steps = (total_frames - 1) * stride + 1

    pop = populate(seed, steps)
    motion, walkers, walk_hist, net, plan = pop.motion, pop.walkers, pop.walk_hist, pop.net, pop.plan

    sl = slice(None, None, stride)
    ego_motion = EgoMotion(
        xy=motion.xy[0, sl],
        yaw=motion.yaw[0, sl],
        speed=motion.v[0, sl],
        accel=past_accels(motion.xy[0, sl], motion.v[0, sl]),
        yaw_rate=motion.v[0, sl] * motion.curvature[0, sl],
    )
    static, placed = paint_city(
        net,
        ego_motion.xy.min(0) - PAINT_MARGIN,
        ego_motion.xy.max(0) + PAINT_MARGIN,
        plan.start,
        plan.feature_along,
        np.random.default_rng([seed, 3]),
        total_frames,
    )
    tracks = TrackSet.concat([mover_tracks(motion, stride), walker_tracks(walkers, walk_hist, stride), placed])
    lidar = observe_static(static, tracks, ego_motion.xy[:num_frames], ego_motion.yaw[:num_frames])
    labels = route_labels(motion, tracks, num_frames, stride)
    frames = [
        frame_annotation(name, seed, i, num_frames, ego_motion, tracks, command=command, road=road)
        for i, (command, road) in enumerate(labels)
    ]
    progress = motion.s[0, : num_frames * stride : stride]
    return SyntheticScene(
        name, seed, frames, static, tracks, ego_motion, net, np.stack(lidar), pop.motion.movers[0].path, progress
    )
