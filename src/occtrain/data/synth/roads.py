"""The road network of the synthetic world: a grid of multi-lane roads, traffic lights, lane routes.

Roads run along global x or y (a Manhattan grid with uneven blocks), traffic keeps right.
A route is a lane-level path through the grid: straight stretches, lane changes with a
smooth lateral blend, and quarter-circle turns at intersections from the proper lane
(right turns from the kerb lane around the rounded kerb corner, left turns from the lane
next to the centre into the crossing road's lane next to its centre). Paths are resampled at
a fixed arc-length step so many of them can be interpolated at once.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

LANE_WIDTH = 3.5
#: Radius of the rounded kerb at every block corner.
CURB_RADIUS = 4.0
#: Distance from a crosswalk's centre line back to the vehicles' stop line.
STOP_LINE_GAP = 2.5
#: Medians stop this far before the crossing road's edge so left turns have room.
MEDIAN_END = 12.0
#: Length of a lane change.
LANE_CHANGE_LEN = 35.0
#: Arc-length step of resampled paths.
PATH_DS = 0.5
#: Range of block sizes (distance between neighbouring parallel road centres).
ROAD_SPACING = (80.0, 135.0)
#: Traffic lights: green time range per axis and the all-red gap between phases (s).
GREEN_TIME = (12.0, 22.0)
ALL_RED = 2.0

#: Unit vectors of the four headings: +x, +y, -x, -y (index + 1 is a left turn).
HEADINGS = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
STRAIGHT, LEFT, RIGHT = 0, 1, 2


def right_of(u: np.ndarray) -> np.ndarray:
    """The unit vector 90 degrees clockwise of ``u`` (the kerb side in right-hand traffic)."""
    return np.array([u[1], -u[0]])


@dataclass(frozen=True)
class Road:
    """A straight road along global x (axis 0, centre line y = centre) or y (axis 1, x = centre)."""

    axis: int
    centre: float
    lanes: int  # per direction
    median: float  # width of the central strip, 0 if none
    parking: float  # width of the parking strip on each side, 0 if none

    @property
    def half_width(self) -> float:
        return self.median / 2 + self.lanes * LANE_WIDTH + self.parking

    @property
    def normal(self) -> np.ndarray:
        """Unit vector across the road (the coordinate ``centre`` is measured along)."""
        return np.array([0.0, 1.0]) if self.axis == 0 else np.array([1.0, 0.0])

    def lane_offset(self, lane: int) -> float:
        """Distance from the centre line to lane ``lane``'s centre; lane 0 is the kerb lane."""
        return self.median / 2 + (self.lanes - 1 - lane + 0.5) * LANE_WIDTH

    def lane_point(self, heading: int, lane: int, along: float) -> np.ndarray:
        """Global point of a lane's centre line, ``along`` metres in the travel direction."""
        u = HEADINGS[heading]
        return u * along + self.normal * self.centre + right_of(u) * self.lane_offset(lane)


@dataclass(frozen=True)
class LaneState:
    """Where a vehicle is on the network: road, travel heading, lane, along-road coordinate."""

    axis: int
    road: int
    heading: int
    lane: int
    along: float


@dataclass
class Path:
    """A route resampled every PATH_DS metres, with the stop lines it meets.

    ``stops`` holds (arc length of the stop line, light parameters, approach axis) per
    intersection the path enters.
    """

    xy: np.ndarray  # (M, 2)
    heading: np.ndarray  # (M,) unwrapped, radians
    curvature: np.ndarray  # (M,) 1/m, positive to the left
    stops: list[tuple[float, np.ndarray, int]]

    @property
    def length(self) -> float:
        return (len(self.xy) - 1) * PATH_DS

    @staticmethod
    def from_points(points: np.ndarray, stops: list[tuple[float, np.ndarray, int]]) -> Path:
        step = np.linalg.norm(np.diff(points, axis=0), axis=1)
        keep = np.concatenate([[True], step > 1e-9])
        points = points[keep]
        s = np.concatenate([[0.0], np.cumsum(step[keep[1:]])])
        su = np.arange(0.0, s[-1] + 1e-9, PATH_DS)
        xy = np.stack([np.interp(su, s, points[:, 0]), np.interp(su, s, points[:, 1])], axis=1)
        d = np.gradient(xy, axis=0)
        heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        return Path(xy, heading, np.gradient(heading) / PATH_DS, stops)


class RoadNetwork:
    """The grid of roads (x-roads and y-roads, each sorted by centre) plus sidewalk width and lights."""

    def __init__(self, roads: tuple[list[Road], list[Road]], sidewalk: float, seed: int):
        self.roads = roads
        self.sidewalk = sidewalk
        self._seed = seed
        self._lights: dict[tuple[int, int], np.ndarray] = {}

    @staticmethod
    def random(rng: np.random.Generator, seed: int, extent: float = 800.0) -> RoadNetwork:
        """A grid covering [-extent, extent]^2 with random block sizes and road profiles."""
        roads: tuple[list[Road], list[Road]] = ([], [])
        for axis in (0, 1):
            centres = [float(rng.uniform(-20, 20))]
            while centres[-1] < extent:
                centres.append(centres[-1] + rng.uniform(*ROAD_SPACING))
            while centres[0] > -extent:
                centres.insert(0, centres[0] - rng.uniform(*ROAD_SPACING))
            for c in centres:
                lanes = int(rng.integers(1, 3))
                median = float(rng.uniform(1.5, 3.0)) if lanes == 2 and rng.random() < 0.5 else 0.0
                parking = 2.5 if rng.random() < 0.5 else 0.0
                roads[axis].append(Road(axis, c, lanes, median, parking))
        return RoadNetwork(roads, sidewalk=float(rng.uniform(3.0, 4.0)), seed=seed)

    def with_road(self, axis: int, index: int, **changes) -> RoadNetwork:
        """A copy with one road's profile changed (lights stay the same)."""
        roads = (list(self.roads[0]), list(self.roads[1]))
        roads[axis][index] = replace(roads[axis][index], **changes)
        return RoadNetwork(roads, self.sidewalk, self._seed)

    def nearest_road(self, axis: int, coord: float) -> int:
        return int(np.argmin([abs(r.centre - coord) for r in self.roads[axis]]))

    def crossings(self, axis: int, heading: int) -> list[tuple[int, float]]:
        """(index, along coordinate of its centre line) of every road crossing a road of ``axis``,
        in the order a vehicle travelling with ``heading`` meets them."""
        u = HEADINGS[heading]
        out = [(i, float(r.centre * (u @ r.normal))) for i, r in enumerate(self.roads[1 - axis])]
        return sorted(out, key=lambda x: x[1])

    def stop_along(self, crossing: Road, along_centre: float) -> float:
        """Along coordinate of the stop line before a crossing road (its centre at ``along_centre``)."""
        return along_centre - crossing.half_width - self.sidewalk / 2 - STOP_LINE_GAP

    def light(self, xroad: int, yroad: int) -> np.ndarray:
        """[period, offset, green start/end for x-road traffic, green start/end for y-road traffic]."""
        key = (xroad, yroad)
        if key not in self._lights:
            rng = np.random.default_rng([self._seed, 77, xroad, yroad])
            gx, gy = rng.uniform(*GREEN_TIME, size=2)
            period = gx + gy + 2 * ALL_RED
            self._lights[key] = np.array([period, rng.uniform(0, period), 0.0, gx, gx + ALL_RED, gx + ALL_RED + gy])
        return self._lights[key]


def green_left(light: np.ndarray, axis: np.ndarray | int, t: float) -> np.ndarray:
    """Seconds of green left at time ``t`` for traffic along ``axis`` (negative while red).

    ``light`` is (..., 6) as returned by RoadNetwork.light; vectorised over leading dims.
    """
    light = np.asarray(light)
    axis = np.asarray(axis)
    phase = np.mod(t + light[..., 1], light[..., 0])
    start = np.where(axis == 0, light[..., 2], light[..., 4])
    end = np.where(axis == 0, light[..., 3], light[..., 5])
    return np.where((phase >= start) & (phase < end), end - phase, -1.0)


def _segment(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    n = max(1, int(np.ceil(np.linalg.norm(b - a) / PATH_DS)))
    return a + (b - a) * (np.arange(1, n + 1) / n)[:, None]


def build_route(
    net: RoadNetwork,
    start: LaneState,
    length: float,
    rng: np.random.Generator,
    turn_weights: tuple[float, float, float],
    lane_change_prob: float,
) -> Path:
    """A lane-level route of at least ``length`` metres from ``start``.

    At each intersection the manoeuvre (straight, left, right) is drawn with
    ``turn_weights``; a turn needs its lane (left: next to the centre, right: kerb lane)
    and a lane change to reach it when there is room, else the vehicle goes straight.
    On straight stretches a lane change happens with ``lane_change_prob``.
    """
    axis, ri, h, k, along = start.axis, start.road, start.heading, start.lane, start.along
    pts = [net.roads[axis][ri].lane_point(h, k, along)[None]]
    total = 0.0
    stops: list[tuple[float, np.ndarray, int]] = []

    def extend(new: np.ndarray) -> None:
        nonlocal total
        total += float(np.linalg.norm(np.diff(np.vstack([pts[-1][-1:], new]), axis=0), axis=1).sum())
        pts.append(new)

    while total < length:
        road = net.roads[axis][ri]
        u = HEADINGS[h]
        ci, along_c = next(
            (i, a) for i, a in net.crossings(axis, h) if net.stop_along(net.roads[1 - axis][i], a) > along + 1.0
        )
        cross = net.roads[1 - axis][ci]
        stop_a = net.stop_along(cross, along_c)
        maneuver = int(rng.choice(3, p=turn_weights))
        target = {STRAIGHT: k, LEFT: road.lanes - 1, RIGHT: 0}[maneuver]
        if maneuver == STRAIGHT and road.lanes > 1 and rng.random() < lane_change_prob:
            target = int(rng.choice([j for j in range(road.lanes) if j != k]))
        room = stop_a - along - 5.0
        if target != k:
            if room >= LANE_CHANGE_LEN:
                a0 = along + rng.uniform(0, room - LANE_CHANGE_LEN)
                extend(_segment(pts[-1][-1], road.lane_point(h, k, a0)))
                t = np.arange(1, int(LANE_CHANGE_LEN / PATH_DS) + 1) * PATH_DS
                blend = (1 - np.cos(np.pi * t / LANE_CHANGE_LEN)) / 2
                shift = road.lane_offset(target) - road.lane_offset(k)
                lc = road.lane_point(h, k, a0)[None] + u * t[:, None] + right_of(u) * (shift * blend)[:, None]
                extend(lc)
                k, along = target, a0 + LANE_CHANGE_LEN
            else:
                maneuver = STRAIGHT
        stops.append((total + stop_a - along, net.light(*((ri, ci) if axis == 0 else (ci, ri))), axis))
        if maneuver == STRAIGHT:
            along = along_c + cross.half_width
            extend(_segment(pts[-1][-1], road.lane_point(h, k, along)))
            continue
        h2 = (h + 1) % 4 if maneuver == LEFT else (h - 1) % 4
        k2 = cross.lanes - 1 if maneuver == LEFT else 0
        u2 = HEADINGS[h2]
        corner = u * ((cross.normal * cross.centre + right_of(u2) * cross.lane_offset(k2)) @ u) + (
            road.normal * road.centre + right_of(u) * road.lane_offset(k)
        )
        if maneuver == LEFT:
            # The arc starts at the crossing road's near kerb line, past the stop line.
            radius = cross.half_width + cross.lane_offset(k2)
        else:
            kerb_gap = (road.half_width - road.lane_offset(k)) + (cross.half_width - cross.lane_offset(k2))
            radius = CURB_RADIUS + kerb_gap / 2
        arc_start = corner - u * radius
        extend(_segment(pts[-1][-1], arc_start))
        centre = arc_start + u2 * radius
        theta0 = np.arctan2(*(-u2)[::-1])
        sign = 1.0 if maneuver == LEFT else -1.0
        phi = np.linspace(0, np.pi / 2, int(np.ceil(radius * np.pi / 2 / (PATH_DS / 2))) + 1)[1:]
        ang = theta0 + sign * phi
        extend(centre + radius * np.stack([np.cos(ang), np.sin(ang)], axis=1))
        axis, ri, h, k = 1 - axis, ci, h2, k2
        along = float(u2 @ pts[-1][-1])
    return Path.from_points(np.vstack(pts), stops)
