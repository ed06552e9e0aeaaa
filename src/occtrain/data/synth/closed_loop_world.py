"""Closed-loop driving in the synthetic world: a scene stepped at SIM_DT with the ego driven from outside.

A :class:`DrivingWorld` is built from a seed by the generator's own code (``scene.populate``
for the roads, the ego's route and the traffic; ``paint_city`` for the city; the same
rasteriser and cameras), so a planner sees in closed loop what it saw in training. The
traffic is :class:`~occtrain.data.synth.traffic.MoverTraffic` with the ego's row taken from
the driven ego: vehicles behind it follow it and stop for it. Pedestrians keep their walks
(they cross at crosswalks on green and do not react to the ego). Left to itself
(``advance(None)``), the ego is the route follower that generated the data: the expert.

At every step the world checks what the ego did (collisions, leaving the drivable area,
driving against the lane direction, red lights on its route, time to collision) and keeps
the trace :func:`occtrain.metrics.closed_loop_scores.score_episode` scores.

Occ3D labels a static surface only where some sweep of the scene saw it; here the sweeps are
the expert's, taken along the route (``observe_static``), as every training frame's were.
"""

from __future__ import annotations

import copy
import hashlib
from dataclasses import dataclass, field, replace

import numpy as np

from occtrain.data.geometry import ego_to_global, global_to_ego
from occtrain.data.schema import LATERAL_DECAY_S, Command, FrameAnnotation
from occtrain.data.synth.annotate import EgoMotion, frame_annotation, past_accels
from occtrain.data.synth.catalog import KINDS, PEDESTRIAN, TrackSet
from occtrain.data.synth.citymap import DRIVEABLE, paint_city
from occtrain.data.synth.closed_loop_view import ViewFrame
from occtrain.data.synth.grid import EGO_HEIGHT, layer_span
from occtrain.data.synth.raster import frame_semantics, masks, observe_static
from occtrain.data.synth.road_context import road_context, route_command, route_points
from occtrain.data.synth.roads import HEADINGS, PATH_DS, RoadNetwork, green_left, right_of
from occtrain.data.synth.scene import PAINT_MARGIN, Population, populate
from occtrain.data.synth.text import caption_for_frame, narration_for_frame
from occtrain.data.synth.traffic import AMBER, SIM_DT, MoverTraffic, footprint_discs, mover_tracks, walker_tracks
from occtrain.data.synth.vehicle import WHEELBASE, EgoState
from occtrain.formats.occ3d import EGO_LENGTH, EGO_WIDTH, FRAME_DT, FREE, FUTURE_STEPS
from occtrain.metrics.closed_loop_scores import STOPPED_SPEED, EpisodeTrace, Infraction, InfractionKind

#: The longest episode (s), and the road network's half extent (m) that keeps every route
#: of the ego and the traffic on the grid for that long (the generator's 800 m is sized for
#: its 23 s scenes).
MAX_SECONDS = 40.0
NETWORK_EXTENT = 1600.0
#: Simulation steps per planning frame.
STRIDE = int(round(FRAME_DT / SIM_DT))
#: Extra city painted around the expert's frames (m), for an ego that strays from its route.
STRAY_MARGIN = 30.0
#: Time-to-collision horizon and step (s), as nuPlan projects agents at constant velocity.
TTC_HORIZON, TTC_STEP = 1.0, 0.1
#: Only agents this close (m) are checked for collisions and time to collision.
NEAR = 40.0
#: The ego has left its route when this far (m) from it; the episode ends there.
ROUTE_DEVIATION = 8.0
#: Driving against the lane: the ego's heading more than 120 degrees from the lane's.
WRONG_WAY_COS = -0.5
EGO_SIZE = np.array([EGO_LENGTH, EGO_WIDTH, EGO_HEIGHT])
#: The first voxel layer above the ego's roof.
EGO_TOP_LAYER = int(layer_span(0.0, EGO_HEIGHT)[1])


@dataclass
class Agents:
    """Everyone but the ego at one step (global): movers, then pedestrians, then placed objects."""

    ident: list[str]
    kind: list[InfractionKind]  # which collision touching it would be
    cls: np.ndarray
    size: np.ndarray  # (N, 3)
    xy: np.ndarray  # (N, 2)
    yaw: np.ndarray
    speed: np.ndarray
    parked: np.ndarray
    rider: np.ndarray

    def tracks(self) -> TrackSet:
        """A one-frame TrackSet of the agents, for the rasteriser and the annotator."""
        return TrackSet(
            cls=self.cls,
            size=self.size,
            xy=self.xy[:, None],
            yaw=self.yaw[:, None],
            speed=self.speed[:, None],
            parked=self.parked,
            rider=self.rider,
        )


@dataclass
class _Log:
    states: list[EgoState] = field(default_factory=list)
    ttc: list[float] = field(default_factory=list)
    infractions: list[Infraction] = field(default_factory=list)
    progress: list[float] = field(default_factory=list)
    off_route: float = 0.0


class DrivingWorld:
    """Scene ``seed`` driven for ``seconds`` from its first frame."""

    def __init__(self, seed: int, seconds: float):
        if not 0 < seconds <= MAX_SECONDS:
            raise ValueError(f"an episode lasts between 0 and {MAX_SECONDS:g} s, got {seconds:g}")
        self.seed = int(seed)
        self.frames = int(round(seconds / FRAME_DT)) + 1
        self.steps = (self.frames - 1) * STRIDE + 1
        # The traffic is simulated past the end so every mover has a desired speed there.
        pop: Population = populate(self.seed, self.steps + FUTURE_STEPS * STRIDE, NETWORK_EXTENT)
        self.net: RoadNetwork = pop.net
        self.route = pop.motion.movers[0].path
        self.expert = pop.motion
        self._walk = pop.walk_hist
        self._walk_size = np.array([w.size for w in pop.walkers]).reshape(-1, 3)
        frames = slice(None, self.steps, STRIDE)
        ex_xy, ex_yaw = pop.motion.xy[0, frames], pop.motion.yaw[0, frames]
        self.static, placed = paint_city(
            self.net,
            ex_xy.min(0) - PAINT_MARGIN - STRAY_MARGIN,
            ex_xy.max(0) + PAINT_MARGIN + STRAY_MARGIN,
            pop.plan.start,
            pop.plan.feature_along,
            np.random.default_rng([self.seed, 3]),
            self.frames + FUTURE_STEPS,
        )
        self._placed = placed
        logged = TrackSet.concat(
            [
                mover_tracks(pop.motion, STRIDE),
                walker_tracks(pop.walkers, pop.walk_hist, STRIDE),
                placed,
            ]
        )
        observe_static(self.static, logged, ex_xy, ex_yaw)
        self._names = [f"{m.kind} {i}" for i, m in enumerate(pop.motion.movers)]
        self.traffic = MoverTraffic(pop.motion.movers, pop.host)
        self.step = 0
        self._pose = self.traffic.pose()
        self._route_i = 0
        self._touching: set[str] = set()
        self._off_road = self._wrong_way = False
        self.log = _Log()
        xy, yaw = self._pose[0], self._pose[1]
        self.ego = EgoState(xy[0].copy(), float(yaw[0]), float(self.traffic.v[0]))
        self._check()

    # ---------------------------------------------------------------- stepping

    @property
    def time(self) -> float:
        return self.step * SIM_DT

    @property
    def done(self) -> bool:
        return self.step >= self.steps - 1 or self.deviated

    @property
    def deviated(self) -> bool:
        return any(i.kind == "route_deviation" for i in self.log.infractions)

    @property
    def at_frame(self) -> bool:
        """Whether this step is a planning frame (every FRAME_DT)."""
        return self.step % STRIDE == 0

    def advance(self, ego: EgoState | None) -> None:
        """One SIM_DT: the traffic reacts to the ego as it is now, then the ego becomes ``ego``
        (the next state of the driven ego), or, given None, drives on as the expert."""
        xy, yaw, _, env = self._pose
        if ego is not None:
            xy[0], yaw[0], self.traffic.v[0] = self.ego.xy, self.ego.yaw, self.ego.speed
        expert_accel = self.traffic.advance(self.step, xy, yaw, env)
        self.step += 1
        self._pose = self.traffic.pose()
        if ego is None:
            nxy, nyaw, curv, _ = self._pose
            steer = float(np.arctan(curv[0] * WHEELBASE))
            ego = EgoState(nxy[0].copy(), float(nyaw[0]), float(self.traffic.v[0]), float(expert_accel[0]), steer)
        self.ego = ego
        self._check()

    # ---------------------------------------------------------------- what the ego sees

    def agents(self) -> Agents:
        xy, yaw = self._pose[0], self._pose[1]
        movers = self.traffic.movers
        walk_xy, walk_yaw, walk_v = (a[:, self.step] for a in self._walk)
        placed = self._placed
        n_m, n_w, n_p = len(movers) - 1, len(walk_xy), len(placed)
        cls = np.concatenate([[KINDS[m.kind].cls for m in movers[1:]], np.full(n_w, PEDESTRIAN), placed.cls])
        vehicle: InfractionKind = "collision_vehicle"
        pedestrian: InfractionKind = "collision_pedestrian"
        static: InfractionKind = "collision_static"
        kind = [vehicle] * n_m + [pedestrian] * n_w + [static] * n_p
        return Agents(
            ident=self._names[1:] + [f"pedestrian {i}" for i in range(n_w)] + [f"object {i}" for i in range(n_p)],
            kind=kind,
            cls=cls.astype(np.int64),
            size=np.concatenate([np.array([m.size for m in movers[1:]]).reshape(-1, 3), self._walk_size, placed.size]),
            xy=np.concatenate([xy[1:], walk_xy, placed.xy[:, 0]]),
            yaw=np.concatenate([yaw[1:], walk_yaw, placed.yaw[:, 0]]),
            speed=np.concatenate([self.traffic.v[1:], walk_v, np.zeros(n_p)]),
            parked=np.concatenate([np.zeros(n_m + n_w, bool), placed.parked]),
            rider=np.concatenate([[m.rider for m in movers[1:]], np.full(n_w, -1), placed.rider]).astype(np.int64),
        )

    def render(self) -> dict[str, np.ndarray]:
        """Occ3D labels of the ego's view now: semantics, mask_lidar, mask_camera."""
        sem = frame_semantics(self.static, self.agents().tracks(), 0, self.ego.xy, self.ego.yaw)
        lidar, camera = masks(sem)
        return {"semantics": sem, "mask_lidar": lidar, "mask_camera": camera}

    def cameras(self, semantics: np.ndarray, height: int, width: int) -> list:
        """The six camera views now (``camera_render.CameraView``, CAMERA_NAMES order)."""
        from occtrain.data.synth.camera_render import FrameWorld, render_cameras

        world = FrameWorld(self.static, self.net, self.ego.xy, self.ego.yaw, self.time)
        return render_cameras(semantics, world, height, width)

    def command(self) -> Command:
        """The route's command: where the route goes in the next 3 s at the current speed, from
        the ego's projection on it (``road_context.route_command``, as the dataset's)."""
        return route_command(self.route, self.log.progress[-1], self.ego.xy, self.ego.yaw, self.ego.speed)

    def route_ahead(self, seconds: float = 3.0) -> np.ndarray:
        """Route points in the ego frame every FRAME_DT at the current speed (for the dashboard)."""
        s = self.log.progress[-1] + max(self.ego.speed, 0.0) * np.arange(1, int(seconds / FRAME_DT) + 1) * FRAME_DT
        pts = np.stack([np.interp(s, self._route_s, self.route.xy[:, i]) for i in (0, 1)], axis=1)
        return global_to_ego(pts, self.ego.xy, self.ego.yaw)

    def frame_annotation(self, scene: str, episode: str = "", future: np.ndarray | None = None) -> FrameAnnotation:
        """The FrameAnnotation of the planning frame now, by the generator's own annotator,
        as a stage reads it: the driven ego's pose, speed and past, the agents around it,
        the route's command and road context (the route ahead from the ego's projection on
        it, the lead vehicle, the pedestrian in the corridor, the next stop line and its
        light: ``road_context``, as the dataset's), a caption and a narration. What a stage
        is asked to predict is unknown in closed loop and filled in as driving on at constant
        velocity (the future waypoints, the meta action, the agents' futures), or, given
        ``future`` (FUTURE_STEPS waypoints, ego frame), as driving those: the ego's future
        and meta action then say what that plan does (how closed-loop training labels a
        frame with its expert's plan)."""
        if not self.at_frame:
            raise ValueError(f"step {self.step} is not a planning frame (every {STRIDE} steps)")
        i = self.step // STRIDE
        driven = self.log.states[::STRIDE]
        if future is None:
            heading = np.array([np.cos(self.ego.yaw), np.sin(self.ego.yaw)])
            ahead_xy = self.ego.xy + (np.arange(1, FUTURE_STEPS + 1) * FRAME_DT * self.ego.speed)[:, None] * heading
            ahead_speed = np.full(FUTURE_STEPS, self.ego.speed)
            ahead_yaw = np.full(FUTURE_STEPS, self.ego.yaw)
        else:
            ahead_xy = ego_to_global(
                np.asarray(future, dtype=np.float64).reshape(FUTURE_STEPS, 2), self.ego.xy, self.ego.yaw
            )
            moves = np.diff(np.concatenate([self.ego.xy[None], ahead_xy]), axis=0)
            ahead_speed = np.linalg.norm(moves, axis=1) / FRAME_DT
            # A heading where the plan moves; where it stands, the heading it had.
            ahead_yaw = np.empty(FUTURE_STEPS)
            yaw = self.ego.yaw
            for k, (dx, dy) in enumerate(moves):
                yaw = float(np.arctan2(dy, dx)) if np.hypot(dx, dy) > 0.05 else yaw
                ahead_yaw[k] = yaw
        xy = np.concatenate([[s.xy for s in driven], ahead_xy])
        n = len(xy)
        speed = np.concatenate([[s.speed for s in driven], ahead_speed])
        motion = EgoMotion(
            xy=xy,
            yaw=np.concatenate([[s.yaw for s in driven], ahead_yaw]),
            speed=speed,
            # As the dataset's: from the driven frames up to now (the future is a filler).
            accel=np.concatenate([past_accels(xy[: len(driven)], speed[: len(driven)]), np.zeros(FUTURE_STEPS)]),
            yaw_rate=np.concatenate([[s.yaw_rate for s in driven], np.zeros(FUTURE_STEPS)]),
        )
        now = self.agents().tracks()
        tracks = replace(
            now,
            xy=np.repeat(now.xy, n, axis=1),
            yaw=np.repeat(now.yaw, n, axis=1),
            speed=np.repeat(now.speed, n, axis=1),
        )
        road = road_context(self.route, self.log.progress[-1], self.ego.xy, self.ego.yaw, self.time, now, 0)
        frame = frame_annotation(scene, self.seed, i, n, motion, tracks, command=self.command(), road=road)
        frame["token"] = drive_token(self.seed, i, episode)
        frame["caption"] = caption_for_frame(frame)
        frame["narration"] = narration_for_frame(frame)
        return frame

    def expert_plan(self) -> np.ndarray:
        """The expert's next 3 s (its logged positions every FRAME_DT) in the ego frame."""
        idx = np.minimum(self.step + STRIDE * np.arange(1, FUTURE_STEPS + 1), self.expert.xy.shape[1] - 1)
        return global_to_ego(self.expert.xy[0, idx], self.ego.xy, self.ego.yaw)

    def expert_from_here(self) -> np.ndarray:
        """What the expert would drive from the ego's state now (ego frame, every FRAME_DT
        for FUTURE_STEPS frames): its controller (the IDM on its route, stopping at red
        lights and behind leaders) takes over at the ego's projection on the route and its
        speed, in a copy of the reactive traffic run forward; the world itself is untouched.
        Unlike ``expert_plan`` (where the expert went in the logged episode), it answers
        from any state the planner drives into, the label DAgger asks of an expert.

        Its progress is laid along the route, and an ego off the route keeps its offset
        from it, fading over ``LATERAL_DECAY_S``: a label from 2 m off the lane that jumped
        onto it in the first half second (36 % of pure-policy labels jumped over 1 m) is
        one no controller follows, and no planner can learn."""
        traffic = copy.copy(self.traffic)  # only the arc lengths and speeds change as it runs
        traffic.s, traffic.v = self.traffic.s.copy(), self.traffic.v.copy()
        traffic.s[0], traffic.v[0] = self.log.progress[-1], self.ego.speed
        arc = []
        for k in range(FUTURE_STEPS * STRIDE):
            xy, yaw, _, env = traffic.pose()
            traffic.advance(self.step + k, xy, yaw, env)
            if (k + 1) % STRIDE == 0:
                arc.append(float(traffic.s[0]))
        s = np.array([self.log.progress[-1], *arc])
        on = route_points(self.route, s)
        tangent = route_points(self.route, s + 0.5) - route_points(self.route, s - 0.5)
        left = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1) / np.linalg.norm(tangent, axis=1, keepdims=True)
        offset = float((self.ego.xy - on[0]) @ left[0])  # left of the route, at the ego's projection
        t = np.arange(1, FUTURE_STEPS + 1) * FRAME_DT
        ahead = on[1:] + (offset * np.exp(-t / LATERAL_DECAY_S))[:, None] * left[1:]
        return global_to_ego(ahead, self.ego.xy, self.ego.yaw)

    def view(self, plan: np.ndarray) -> ViewFrame:
        """The bird's-eye frame of now, with ``plan`` (ego frame) drawn."""
        agents = self.agents()
        return ViewFrame(
            time=self.time,
            ego_xy=self.ego.xy.copy(),
            ego_yaw=self.ego.yaw,
            speed=self.ego.speed,
            command=self.command(),
            plan=ego_to_global(np.asarray(plan, dtype=np.float64).reshape(-1, 2), self.ego.xy, self.ego.yaw),
            route=ego_to_global(self.route_ahead(), self.ego.xy, self.ego.yaw),
            agents_xy=agents.xy,
            agents_yaw=agents.yaw,
            agents_size=agents.size,
            agents_cls=agents.cls,
            infractions=[],
            lights=self._lights_ahead(),
        )

    def _lights_ahead(self, within: float = 60.0) -> list[tuple[np.ndarray, float, str]]:
        s = self.log.progress[-1]
        out = []
        for stop_s, light, axis in self.route.stops:
            if s - 5.0 <= stop_s <= s + within:
                i = min(int(stop_s / PATH_DS), len(self.route.xy) - 1)
                left = float(green_left(light, axis, self.time))
                state = "red" if left < 0 else ("amber" if left < AMBER else "green")
                out.append((self.route.xy[i], float(self.route.heading[i]), state))
        return out

    # ---------------------------------------------------------------- checks

    @property
    def _route_s(self) -> np.ndarray:
        return np.arange(len(self.route.xy)) * PATH_DS

    def _project(self) -> float:
        """Arc length of the ego's projection on its route (searched near the last one)."""
        lo = max(self._route_i - 20, 0)
        window = self.route.xy[lo : self._route_i + 120]
        d2 = np.sum((window - self.ego.xy) ** 2, axis=1)
        i = self._route_i = lo + int(np.argmin(d2))
        self._route_gap = float(np.sqrt(d2.min()))
        best = float(i * PATH_DS)
        xy = self.route.xy
        for a in (i - 1, i):  # the foot on either neighbouring segment
            if 0 <= a < len(xy) - 1:
                seg = xy[a + 1] - xy[a]
                u = float(np.clip((self.ego.xy - xy[a]) @ seg / max(seg @ seg, 1e-12), 0.0, 1.0))
                if 0.0 < u < 1.0:
                    best = (a + u) * PATH_DS
        return best

    def _check(self) -> None:
        ego, t, log = self.ego, self.time, self.log
        prev_s = log.progress[-1] if log.progress else None
        s = self._project()
        moved = float(np.linalg.norm(ego.xy - log.states[-1].xy)) if log.states else 0.0
        log.states.append(ego)
        log.progress.append(s)
        agents = self.agents()
        near = np.flatnonzero(np.hypot(*(agents.xy - ego.xy).T) < NEAR)

        # Collisions with agents, counted when contact begins.
        touching = set()
        if len(near):
            hit = _overlap(ego.xy, ego.yaw, agents.xy[near], agents.yaw[near], agents.size[near])
            for k in near[hit]:
                name = agents.ident[k]
                touching.add(name)
                if name not in self._touching:
                    log.infractions.append(Infraction(agents.kind[k], t, self._at_fault(agents, k), name))
        # Static structure (buildings, poles, trunks, hedges) under the ego's footprint and
        # below its roof: a tree's crown over the road is above it.
        probe = _footprint_points(ego.xy, ego.yaw)
        ix, iy = self.static.cells(probe)
        if np.any((self.static.cls[ix, iy] != FREE) & (self.static.lo[ix, iy] < EGO_TOP_LAYER)):
            touching.add("structure")
            if "structure" not in self._touching:
                log.infractions.append(Infraction("collision_static", t, ego.speed >= STOPPED_SPEED, "structure"))
        self._touching = touching

        off = bool(np.any(self.static.ground[ix, iy] != DRIVEABLE))
        if off and not self._off_road:
            log.infractions.append(Infraction("off_road", t))
        wrong = _against_lane(self.net, ego.xy, ego.yaw)
        if wrong and not self._wrong_way:
            log.infractions.append(Infraction("wrong_way", t))
        if off or wrong:
            log.off_route += moved
        self._off_road, self._wrong_way = off, wrong

        # Red lights: the front bumper crosses a stop line of the route while its light is red.
        if prev_s is not None:
            front0, front1 = prev_s + EGO_LENGTH / 2, s + EGO_LENGTH / 2
            for stop_s, light, axis in self.route.stops:
                if front0 < stop_s <= front1 and float(green_left(light, axis, t)) < 0:
                    log.infractions.append(Infraction("red_light", t))

        if self._route_gap > ROUTE_DEVIATION:
            log.infractions.append(Infraction("route_deviation", t))
        log.ttc.append(self._ttc(agents, near, touching))

    def _at_fault(self, agents: Agents, k: int) -> bool:
        """NAVSIM's rule: not the ego's fault when it stood still or was hit from behind."""
        ego = self.ego
        if ego.speed < STOPPED_SPEED:
            return False
        local = global_to_ego(agents.xy[k], ego.xy, ego.yaw)
        from_behind = local[0] < -EGO_LENGTH / 4 and agents.speed[k] > ego.speed
        return not from_behind

    def _ttc(self, agents: Agents, near: np.ndarray, touching: set[str]) -> float:
        """Least time (s) within TTC_HORIZON to a collision at constant velocity with an agent ahead."""
        ego = self.ego
        keep = [k for k in near if agents.ident[k] not in touching]
        if not keep:
            return float("inf")
        idx = np.array(keep)
        local = global_to_ego(agents.xy[idx], ego.xy, ego.yaw)
        idx = idx[local[:, 0] > -EGO_LENGTH / 2]  # the ego answers for what is ahead of it
        if not len(idx):
            return float("inf")
        heading = np.array([np.cos(ego.yaw), np.sin(ego.yaw)])
        a_dir = np.stack([np.cos(agents.yaw[idx]), np.sin(agents.yaw[idx])], axis=1)
        for tau in np.arange(TTC_STEP, TTC_HORIZON + 1e-9, TTC_STEP):
            e_xy = ego.xy + heading * ego.speed * tau
            a_xy = agents.xy[idx] + a_dir * agents.speed[idx, None] * tau
            if np.any(_overlap(e_xy, ego.yaw, a_xy, agents.yaw[idx], agents.size[idx])):
                return float(tau)
        return float("inf")

    def trace(self) -> EpisodeTrace:
        """The episode so far, for ``metrics.closed_loop_scores.score_episode``."""
        states = self.log.states
        speed = np.array([s.speed for s in states])
        yaw_rate = np.array([s.yaw_rate for s in states])
        expert_s = self.expert.s[0, : self.step + 1]
        return EpisodeTrace(
            dt=SIM_DT,
            speed=speed,
            lon_accel=np.array([s.accel for s in states]),
            lat_accel=speed * yaw_rate,
            yaw_rate=yaw_rate,
            ttc=np.array(self.log.ttc),
            progress=self.log.progress[-1] - self.log.progress[0],
            expert_progress=float(expert_s[-1] - expert_s[0]),
            off_route=self.log.off_route,
            infractions=list(self.log.infractions),
        )


def drive_token(seed: int, index: int, episode: str = "") -> str:
    """The sample token of planning frame ``index`` of ``episode`` on scene ``seed``: apart
    from every dataset's (whose tokens are ``annotate.sample_token``'s) and from every other
    episode's on the route, whose frame ``index`` saw another scene (a stage's caches are
    keyed by token)."""
    return hashlib.md5(f"occtrain-drive/{seed}/{episode}/{index}".encode()).hexdigest()


def _footprint_points(xy: np.ndarray, yaw: float) -> np.ndarray:
    """The ego's corners and edge midpoints (global)."""
    hx, hy = EGO_LENGTH / 2, EGO_WIDTH / 2
    local = np.array([[sx * hx, sy * hy] for sx in (-1, 0, 1) for sy in (-1, 0, 1) if (sx, sy) != (0, 0)])
    return ego_to_global(local, xy, yaw)


def _overlap(ego_xy: np.ndarray, ego_yaw: float, xy: np.ndarray, yaw: np.ndarray, size: np.ndarray) -> np.ndarray:
    """(N,) whether the ego's footprint overlaps each box, by the traffic model's footprint discs."""
    ce, re = footprint_discs(ego_xy[None], np.array([ego_yaw]), EGO_SIZE[None])
    ca, ra = footprint_discs(xy, yaw, size)
    gap2 = np.sum((ce[:, :, None, :] - ca[:, None, :, :]) ** 2, axis=-1)  # (N, D, D)
    return np.any(gap2 < ((re + ra) ** 2)[:, None, None], axis=(1, 2))


def _against_lane(net: RoadNetwork, xy: np.ndarray, yaw: float) -> bool:
    """Whether the ego drives against the lane it is in (not judged inside intersections)."""
    on = []
    for axis in (0, 1):
        for road in net.roads[axis]:
            d = float(xy @ road.normal) - road.centre
            if abs(d) < road.half_width:
                on.append((road, d))
    if len(on) != 1:  # off the roads, or in an intersection
        return False
    road, d = on[0]
    if abs(d) <= road.median / 2 or abs(d) >= road.half_width - road.parking:
        return False  # on the median or a parking strip: no lane to drive against
    heading = np.array([np.cos(yaw), np.sin(yaw)])
    for h in (road.axis, road.axis + 2):
        u = HEADINGS[h]
        if np.sign(right_of(u) @ road.normal) == np.sign(d):
            return bool(heading @ u < WRONG_WAY_COS)
    return False


__all__ = ["Agents", "DrivingWorld", "drive_token"]
