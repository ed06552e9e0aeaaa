"""Who is on the road: the ego's start, route and speed plan, the traffic, the pedestrians.

Vehicles are spawned lane by lane along every road near the ego's route, gaps drawn at
random; a few are placed close to the ego's start so each scene begins with a cyclist, a
motorcycle, a bus and a truck towing a trailer in the oncoming lanes (and often a car
right ahead of the ego). Pedestrians walk along both sidewalks of every road (a
fifth of them stand still), keeping to the right of their sidewalk.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occtrain.data.synth.catalog import KINDS, pick
from occtrain.data.synth.grid import EGO_HEIGHT
from occtrain.data.synth.roads import HEADINGS, LaneState, RoadNetwork, build_route
from occtrain.data.synth.traffic import Mover, Walker
from occtrain.formats.occ3d import EGO_LENGTH, EGO_WIDTH

#: Desired speed ranges (m/s) and acceleration limits (m/s^2) per mover kind.
SPEEDS: dict[str, tuple[float, float]] = {
    "car": (8.0, 14.0),
    "truck": (7.0, 11.0),
    "tractor": (6.0, 10.0),
    "bus": (7.0, 11.0),
    "construction_vehicle": (4.0, 7.0),
    "motorcyclist": (9.0, 15.0),
    "cyclist": (3.5, 6.0),
}
ACCEL: dict[str, float] = {"car": 2.0, "motorcyclist": 2.5, "cyclist": 1.0}
HEAVY_ACCEL = 1.0
#: Kinds spawned in traffic (the kerb lane adds cyclists).
TRAFFIC = (
    ("car", 0.74),
    ("truck", 0.07),
    ("bus", 0.05),
    ("tractor", 0.04),
    ("motorcyclist", 0.07),
    ("construction_vehicle", 0.03),
)
KERB_TRAFFIC = TRAFFIC + (("cyclist", 0.08),)
#: Cyclists ride this far to the kerb side of their lane's centre.
CYCLIST_OFFSET = 0.9
#: Spawned vehicles in a lane are at least this far apart bumper to bumper, plus a random gap.
MIN_GAP = 6.0
MEAN_EXTRA_GAP = 50.0
#: Manoeuvre weights (straight, left, right) and lane-change chance for the traffic and the ego.
TRAFFIC_TURNS = (0.6, 0.15, 0.25)
EGO_TURNS = (0.4, 0.3, 0.3)
EGO_LANE_CHANGE = 0.35
#: The ego's desired speed is redrawn in this range every few seconds.
EGO_SPEED = (5.0, 13.5)
EGO_SPEED_HOLD = (4.0, 9.0)
#: Pedestrians: walking speeds, the share standing still, spacing along a sidewalk.
WALK_SPEED = (1.0, 1.6)
STANDING_SHARE = 0.2
MEAN_WALKER_GAP = 18.0
#: Lateral offset of a walker from the sidewalk's centre line, to its right.
WALK_KEEP_RIGHT = 0.55


@dataclass
class EgoPlan:
    """The ego's start on the network and where (along its travel direction) the features go."""

    start: LaneState
    feature_along: float


def ego_start(net: RoadNetwork, rng: np.random.Generator) -> tuple[RoadNetwork, EgoPlan]:
    """Pick the ego's road (given parking strips), heading, lane and start in the block at the origin."""
    axis = int(rng.integers(0, 2))
    road_i = net.nearest_road(axis, 0.0)
    net = net.with_road(axis, road_i, parking=2.5)
    heading = axis + 2 * int(rng.integers(0, 2))
    crossings = net.crossings(axis, heading)
    cross = net.roads[1 - axis]
    k = max(i for i, (_, a) in enumerate(crossings) if a <= 0.0)
    (c0, a0), (c1, a1) = crossings[k], crossings[k + 1]
    s0, s1 = a0 + cross[c0].half_width, a1 - cross[c1].half_width
    feature = rng.uniform(s0 + 25.0, s1 - 28.0)
    along = max(s0 + 3.0, feature - rng.uniform(10.0, 25.0))
    lane = int(rng.integers(0, net.roads[axis][road_i].lanes))
    return net, EgoPlan(LaneState(axis, road_i, heading, lane, along), feature)


def ego_mover(net: RoadNetwork, plan: EgoPlan, rng: np.random.Generator, steps: int, dt: float) -> Mover:
    """The ego: a route with turns and lane changes and a desired speed redrawn every few seconds."""
    horizon = steps * dt
    path = build_route(net, plan.start, EGO_SPEED[1] * horizon + 60.0, rng, EGO_TURNS, EGO_LANE_CHANGE)
    v_des = np.empty(steps)
    t = 0
    while t < steps:
        hold = int(rng.uniform(*EGO_SPEED_HOLD) / dt)
        v_des[t : t + hold] = rng.uniform(*EGO_SPEED)
        t += hold
    v0 = 0.0 if rng.random() < 0.15 else v_des[0] * rng.uniform(0.3, 1.0)
    size = np.array([EGO_LENGTH, EGO_WIDTH, EGO_HEIGHT])
    return Mover("car", size, path, 0.0, v0, v_des, priority=np.inf, a_max=2.0, b_comf=2.5)


class TrafficSpawner:
    """Places movers lane by lane without overlapping the ones already placed."""

    def __init__(self, net: RoadNetwork, ego: Mover, rng: np.random.Generator, steps: int, dt: float):
        self.net, self.rng, self.steps, self.dt = net, rng, steps, dt
        self.movers: list[Mover] = [ego]
        self._taken: dict[tuple[int, int, int, int], list[tuple[float, float]]] = {}

    def reserve(self, lane: tuple[int, int, int, int], rear: float, front: float) -> None:
        self._taken.setdefault(lane, []).append((rear, front))

    def free(self, lane: tuple[int, int, int, int], rear: float, front: float) -> bool:
        return all(front + MIN_GAP <= r0 or rear - MIN_GAP >= r1 for r0, r1 in self._taken.get(lane, []))

    def spawn(self, kind: str, state: LaneState, priority: float) -> bool:
        """Add a mover of ``kind`` (a tractor brings its trailer) at ``state`` if the lane is free there."""
        rng = self.rng
        size = KINDS[kind].sample_size(rng)
        trailer = KINDS["trailer"].sample_size(rng) if kind == "tractor" else None
        tow_gap = size[0] / 2 + 0.8 + trailer[0] / 2 if trailer is not None else 0.0
        rear = state.along - (tow_gap + trailer[0] / 2 if trailer is not None else size[0] / 2)
        front = state.along + size[0] / 2
        lane = (state.axis, state.road, state.heading, state.lane)
        if not self.free(lane, rear, front):
            return False
        self.reserve(lane, rear, front)
        v_lo, v_hi = SPEEDS[kind]
        horizon = self.steps * self.dt
        path = build_route(self.net, state, v_hi * horizon + 40.0, rng, TRAFFIC_TURNS, 0.0)
        v_des = np.full(self.steps, rng.uniform(v_lo, v_hi))
        a_max = ACCEL.get(kind, HEAVY_ACCEL)
        mover = Mover(
            kind,
            size,
            path,
            0.0,
            v_des[0] * rng.uniform(0.5, 1.0),
            v_des,
            priority,
            lateral=CYCLIST_OFFSET if kind == "cyclist" else 0.0,
            a_max=a_max,
            rider=1 if kind in ("cyclist", "motorcyclist") else -1,
        )
        self.movers.append(mover)
        if trailer is not None:
            host = len(self.movers) - 1
            self.movers.append(
                Mover(
                    "trailer",
                    trailer,
                    path,
                    -tow_gap,
                    mover.v0,
                    v_des,
                    priority,
                    a_max=a_max,
                    host=host,
                    host_gap=tow_gap,
                )
            )
        return True

    def fill_lane(
        self, axis: int, road: int, heading: int, lane: int, lo: float, hi: float, avoid: list[float], cyclists: bool
    ) -> None:
        """Random traffic in one lane between along coordinates lo and hi, away from ``avoid`` spots.

        Cyclists only ride in kerb lanes, and only where ``cyclists`` allows.
        """
        rng, net = self.rng, self.net
        crossings = [(a, net.roads[1 - axis][i].half_width) for i, a in net.crossings(axis, heading)]
        a = lo + rng.exponential(MEAN_EXTRA_GAP / 2)
        while a < hi:
            kind = pick(rng, KERB_TRAFFIC if lane == 0 and cyclists else TRAFFIC)
            clear = all(abs(a - c) > hw + 10.0 for c, hw in crossings) and all(abs(a - p) > 15.0 for p in avoid)
            if clear:
                self.spawn(kind, LaneState(axis, road, heading, lane, a), rng.random())
            a += MIN_GAP + 12.0 + rng.exponential(MEAN_EXTRA_GAP)


def spawn_traffic(
    net: RoadNetwork,
    plan: EgoPlan,
    ego: Mover,
    lo: np.ndarray,
    hi: np.ndarray,
    rng: np.random.Generator,
    steps: int,
    dt: float,
) -> list[Mover]:
    """The ego (first) and traffic on every lane of every road crossing the box [lo, hi]."""
    sp = TrafficSpawner(net, ego, rng, steps, dt)
    st = plan.start
    road = net.roads[st.axis][st.road]
    sp.reserve((st.axis, st.road, st.heading, st.lane), st.along - ego.size[0] / 2, st.along + ego.size[0] / 2)
    opposite = (st.heading + 2) % 4
    if rng.random() < 0.5:
        sp.spawn("car", LaneState(st.axis, st.road, st.heading, st.lane, st.along + rng.uniform(12.0, 25.0)), 10.0)
    for kind, heading, lane, dist in (
        ("cyclist", opposite, 0, rng.uniform(15.0, 35.0)),
        ("motorcyclist", opposite, 0, rng.uniform(40.0, 60.0)),
        ("bus", opposite, road.lanes - 1, rng.uniform(55.0, 80.0)),
        ("tractor", opposite, 0, rng.uniform(80.0, 110.0)),
    ):
        along = st.along + dist if heading == st.heading else -(st.along + dist)
        for shift in range(6):
            if sp.spawn(kind, LaneState(st.axis, st.road, heading, lane, along + 8.0 * shift), 10.0 + rng.random()):
                break
    ego_spot = st.along
    for axis in (0, 1):
        k = 0 if axis == 0 else 1
        for ri, r in enumerate(net.roads[axis]):
            if not lo[1 - k] - r.half_width < r.centre < hi[1 - k] + r.half_width:
                continue
            for heading in (axis, axis + 2):
                sign = HEADINGS[heading][k]
                a_lo, a_hi = sorted((sign * lo[k], sign * hi[k]))
                ego_way = (axis, ri, heading) == (st.axis, st.road, st.heading)
                for lane in range(r.lanes):
                    # No cyclist ahead of the ego in its own direction: it would be stuck behind it.
                    sp.fill_lane(axis, ri, heading, lane, a_lo, a_hi, [ego_spot] if ego_way else [], not ego_way)
    return sp.movers


def spawn_walkers(net: RoadNetwork, lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator) -> list[Walker]:
    """Pedestrians along both sidewalks of every road crossing the box [lo, hi]."""
    walkers: list[Walker] = []
    w = net.sidewalk
    for axis in (0, 1):
        k = 0 if axis == 0 else 1
        cross = net.roads[1 - axis]
        for ri, r in enumerate(net.roads[axis]):
            if not lo[1 - k] - r.half_width - w < r.centre < hi[1 - k] + r.half_width + w:
                continue
            for side in (-1.0, 1.0):
                line = r.centre + side * (r.half_width + w / 2)
                a = lo[k] + rng.exponential(MEAN_WALKER_GAP)
                while a < hi[k]:
                    on_road = any(abs(a - c.centre) < c.half_width + 1.5 for c in cross)
                    if not on_road:
                        walkers.append(_walker(net, axis, ri, line, side, a, rng))
                    a += 3.0 + rng.exponential(MEAN_WALKER_GAP)
    return walkers


def _walker(
    net: RoadNetwork, axis: int, ri: int, line: float, side: float, a: float, rng: np.random.Generator
) -> Walker:
    """One pedestrian on the sidewalk line ``line`` of road ``ri``, at global along coordinate ``a``."""
    k = 0 if axis == 0 else 1
    sign = float(rng.choice([-1.0, 1.0]))
    direction = np.zeros(2)
    direction[k] = sign
    # Keep right: the right of the walking direction, as an offset of the cross coordinate.
    keep = -sign * WALK_KEEP_RIGHT if axis == 0 else sign * WALK_KEEP_RIGHT
    start = np.zeros(2)
    start[k], start[1 - k] = a, line + keep
    standing = rng.random() < STANDING_SHARE
    crossings = []
    for ci, c in enumerate(net.roads[1 - axis]):
        ends = sorted(
            (sign * (c.centre - c.half_width - 1.0) - sign * a, sign * (c.centre + c.half_width + 1.0) - sign * a)
        )
        if ends[1] > 0:
            light = net.light(ri, ci) if axis == 0 else net.light(ci, ri)
            crossings.append((ends[0], ends[1], light, axis))
    crossings.sort(key=lambda c: c[0])
    return Walker(
        start=start,
        direction=direction,
        speed=0.0 if standing else rng.uniform(*WALK_SPEED),
        size=KINDS["pedestrian"].sample_size(rng),
        yaw=rng.uniform(-np.pi, np.pi) if standing else float(np.arctan2(direction[1], direction[0])),
        crossings=crossings[:4],
        priority=rng.random() - 1.0,
    )
