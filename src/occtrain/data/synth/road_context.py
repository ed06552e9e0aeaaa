"""What a map and a tracker tell a planner about the road ahead, and the route's driving command.

One function each, called the same way by the synthesized frames (``scene.generate_scene``:
the expert's route, its arc length and pose at the frame, the scene's tracks at the frame)
and by the closed-loop world (``DrivingWorld.frame_annotation``: the route, the driven ego's
projection on it and pose, the agents now), so a driven frame is annotated as the dataset
annotates it:

- :func:`road_context`: ``FrameAnnotation["road"]`` (``schema.RoadContext``): the route's
  centreline at ``schema.ROUTE_ARC`` in the ego frame, the largest curvature ahead, the lead
  vehicle and the pedestrian in the corridor measured along the route, and the next stop
  line with its light. The lead is the expert's leader (``traffic.MoverTraffic.advance``:
  the nearest vehicle ahead whose box overlaps the ego's sideways, heading the same way),
  with "ahead" and "sideways" taken along the route rather than the ego's axis, so a
  vehicle beyond a turn is ahead and one in the next lane of a curve is not; the stop line
  is the one the expert stops at (its front bumper's gap, the same 0.5 m of overshoot).
- :func:`route_command`: where the route goes in the next 3 s at the current speed (at
  least MIN_COMMAND_SPEED, so a standing ego still sees its next turn), by ST-P3's lateral
  rule (``geometry.driving_command``) on those route points.

Agents' positions are projected onto the route's polyline (the samples every PATH_DS) near
the ego: their arc length is the foot's, their offset the signed distance to it (left
positive).
"""

from __future__ import annotations

import numpy as np

from occtrain.data.geometry import driving_command, global_to_ego
from occtrain.data.schema import (
    PEDESTRIAN_CORRIDOR,
    PEDESTRIAN_REACH,
    ROAD_REACH,
    ROUTE_ARC,
    Command,
    CorridorAgent,
    LeadVehicle,
    LightState,
    RoadContext,
    StopLine,
)
from occtrain.data.synth.catalog import CYCLE_CLASSES, PEDESTRIAN, VEHICLE_CLASSES, TrackSet
from occtrain.data.synth.roads import PATH_DS, Path, green_left
from occtrain.data.synth.traffic import AMBER
from occtrain.formats.occ3d import EGO_LENGTH, EGO_WIDTH, FRAME_DT, FUTURE_STEPS

#: The expert's leader test (``MoverTraffic.advance``): boxes overlapping sideways with this
#: margin (m), headings within 60 degrees.
LEAD_MARGIN = 0.2
SAME_WAY_COS = 0.5
#: A stop line the front bumper passed by less than this (m) still holds the expert.
STOP_OVERSHOOT = 0.5
#: The command looks 3 s ahead at the current speed, but at least this fast (m/s).
MIN_COMMAND_SPEED = 2.0
#: Route kept behind the ego's projection and beyond the reach (m) when projecting agents,
#: so an agent just outside the range does not land on the window's ends.
_BEHIND, _BEYOND = 5.0, 15.0
_ROAD_CLASSES = np.array(sorted(VEHICLE_CLASSES | CYCLE_CLASSES))


def route_points(route: Path, arc: np.ndarray) -> np.ndarray:
    """Global (K, 2) points of ``route`` at arc lengths ``arc``, by linear interpolation of its
    samples; beyond either end the route goes on straight along its end segment (as the
    traffic's path lookup does)."""
    pos = np.asarray(arc, dtype=np.float64) / PATH_DS
    i0 = np.clip(np.floor(pos).astype(np.int64), 0, len(route.xy) - 2)
    f = (pos - i0)[:, None]
    return route.xy[i0] + f * (route.xy[i0 + 1] - route.xy[i0])


def route_command(route: Path, s: float, pose_xy: np.ndarray, pose_yaw: float, speed: float) -> Command:
    """The driving command of an ego at arc length ``s`` of ``route`` (its projection), posed at
    ``pose_xy`` / ``pose_yaw``: ST-P3's lateral rule on the route's points every FRAME_DT for
    FUTURE_STEPS frames at ``speed`` (at least MIN_COMMAND_SPEED), in the ego frame."""
    ahead = s + max(float(speed), MIN_COMMAND_SPEED) * FRAME_DT * np.arange(1, FUTURE_STEPS + 1)
    local = global_to_ego(route_points(route, ahead), pose_xy, pose_yaw)
    return driving_command(local, np.ones(FUTURE_STEPS))


def light_state(green: float) -> LightState:
    """The light a vehicle sees with ``green`` seconds of green left (``roads.green_left``)."""
    return "red" if green < 0 else ("amber" if green < AMBER else "green")


def _along_route(route: Path, s: float, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(arc length, offset left of the centreline, route heading there) of each point of ``xy``
    (N, 2), projected on the route's polyline between ``s - _BEHIND`` and ``s + ROAD_REACH + _BEYOND``."""
    k0 = int(np.floor((s - _BEHIND) / PATH_DS))
    k1 = int(np.ceil((s + ROAD_REACH + _BEYOND) / PATH_DS))
    arcs = np.arange(k0, k1 + 1) * PATH_DS
    pts = route_points(route, arcs)
    a, d = pts[:-1], np.diff(pts, axis=0)  # (K, 2)
    len2 = np.maximum(np.sum(d * d, axis=1), 1e-12)
    rel = xy[:, None, :] - a[None]  # (N, K, 2)
    u = np.clip(np.sum(rel * d[None], axis=2) / len2, 0.0, 1.0)
    gap = rel - u[..., None] * d[None]
    seg = np.argmin(np.sum(gap * gap, axis=2), axis=1)
    rows = np.arange(len(xy))
    t = d[seg] / np.sqrt(len2[seg])[:, None]
    g = gap[rows, seg]
    arc = arcs[seg] + u[rows, seg] * PATH_DS
    return arc, t[:, 0] * g[:, 1] - t[:, 1] * g[:, 0], np.arctan2(t[:, 1], t[:, 0])


def _lead(tracks: TrackSet, frame: int, near: np.ndarray, ahead, offset, heading) -> LeadVehicle | None:
    yaw = tracks.yaw[near, frame]
    width = tracks.size[near, 1]
    lead = (
        np.isin(tracks.cls[near], _ROAD_CLASSES)
        & (ahead > 0.0)
        & (ahead <= ROAD_REACH)
        & (np.abs(offset) < (EGO_WIDTH + width) / 2 + LEAD_MARGIN)
        & (np.cos(yaw - heading) > SAME_WAY_COS)
    )
    if not lead.any():
        return None
    k = np.flatnonzero(lead)[np.argmin(ahead[lead])]
    n = near[k]
    return {
        "gap": round(float(ahead[k] - (EGO_LENGTH + tracks.size[n, 0]) / 2), 4),
        "speed": round(float(tracks.speed[n, frame] * np.cos(yaw[k] - heading[k])), 4),
    }


def _pedestrian(tracks: TrackSet, frame: int, near: np.ndarray, ahead, offset) -> CorridorAgent | None:
    inside = (
        (tracks.cls[near] == PEDESTRIAN)
        & (ahead >= 0.0)
        & (ahead <= PEDESTRIAN_REACH)
        & (np.abs(offset) <= PEDESTRIAN_CORRIDOR)
    )
    if not inside.any():
        return None
    k = np.flatnonzero(inside)[np.argmin(ahead[inside])]
    return {
        "distance": round(float(ahead[k]), 4),
        "offset": round(float(offset[k]), 4),
        "speed": round(float(tracks.speed[near[k], frame]), 4),
    }


def _stop_line(route: Path, s: float, t: float) -> StopLine | None:
    front = s + EGO_LENGTH / 2
    for stop_s, light, axis in route.stops:
        gap = stop_s - front
        if gap > -STOP_OVERSHOOT:
            if gap > ROAD_REACH:
                return None
            green = float(green_left(light, axis, t))
            return {"distance": round(float(gap), 4), "light": light_state(green), "green_left": round(green, 4)}
    return None


def road_context(
    route: Path, s: float, pose_xy: np.ndarray, pose_yaw: float, t: float, tracks: TrackSet, frame: int
) -> RoadContext:
    """``FrameAnnotation["road"]`` of an ego at arc length ``s`` of ``route`` (its projection on
    it), posed at ``pose_xy`` / ``pose_yaw`` (global), at time ``t`` (s, for the lights),
    among the agents of ``tracks`` at index ``frame`` (global positions; the ego not among
    them). The fields are defined in ``schema.RoadContext``."""
    pose_xy = np.asarray(pose_xy, dtype=np.float64)
    points = global_to_ego(route_points(route, s + np.asarray(ROUTE_ARC)), pose_xy, pose_yaw)
    lo = max(int(np.floor(s / PATH_DS)), 0)
    hi = min(int(np.ceil((s + ROAD_REACH) / PATH_DS)), len(route.curvature) - 1)
    curvature = float(np.abs(route.curvature[lo : hi + 1]).max()) if hi >= lo else 0.0
    xy = tracks.xy[:, frame]
    # Only agents that could lie on the route's next ROAD_REACH m (plus a margin) are projected.
    near = np.flatnonzero(np.hypot(*(xy - pose_xy).T) < ROAD_REACH + _BEYOND + PEDESTRIAN_CORRIDOR)
    arc, offset, heading = _along_route(route, s, xy[near])
    ahead = arc - s
    return {
        "route": np.round(points, 4).tolist(),
        "curvature": round(curvature, 5),
        "lead": _lead(tracks, frame, near, ahead, offset, heading),
        "pedestrian": _pedestrian(tracks, frame, near, ahead, offset),
        "stop_line": _stop_line(route, s, t),
    }
