"""Closed-loop driving scores of one episode: what the ego did, judged as CARLA and NAVSIM judge it.

The simulator fills an :class:`EpisodeTrace` (the ego's state at every simulation step, the
route progress, the infractions it detected); :func:`score_episode` turns it into numbers.
Nothing here knows the world: the same scores apply to any simulator that fills the trace.

Sources of each term:

* **Route completion** (CARLA leaderboard): the share of the route driven, in percent. Here
  a route is the distance the simulator's expert covers in the episode's time, so the expert
  completes 100 %; distance driven off the drivable area or against the lane direction does
  not count towards it (the leaderboard's "outside route lanes" rule), and an ego that
  strays from its route ends its episode there (the leaderboard's "route deviation").
* **Driving score** (CARLA leaderboard): route completion times the product of a penalty
  per infraction, ``p ** count``: collision with a pedestrian 0.50, with a vehicle 0.60, with
  a static object 0.65, running a red light 0.70 (the leaderboard 1.0 coefficients).
* **PDM score** (NAVSIM v1): ``NC * DAC * (5 TTC + 5 EP + 2 C) / 12``: NC no at-fault
  collision (0 with a vehicle or pedestrian, 0.5 with a static object only, else 1), DAC the
  ego never left the drivable area, TTC the time to collision never fell below
  ``TTC_BOUND`` while the ego moved, EP progress over the expert's (1 when the expert moved
  less than ``EP_MIN_PROGRESS``), C comfort within nuPlan's bounds throughout. NAVSIM scores
  4 s of non-reactive simulation; here the whole reactive episode.
* **Comfort** (nuPlan ``ego_is_comfortable``): longitudinal acceleration in
  [-4.05, 2.40] m/s^2, |lateral acceleration| <= 4.89 m/s^2, |yaw rate| <= 0.95 rad/s,
  |yaw acceleration| <= 1.93 rad/s^2, |longitudinal jerk| <= 4.13 m/s^3, |jerk| <= 8.37 m/s^3.
  As nuPlan does, each signal and its derivative go through a Savitzky-Golay filter
  (quadratic, ``SMOOTHING_WINDOW`` steps here) before the bounds are checked.
* **Collision fault** (NAVSIM's rule): a collision is not the ego's fault when the ego stood
  still or the other hit it from behind.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Literal, get_args

import numpy as np
from scipy.signal import savgol_filter

InfractionKind = Literal[
    "collision_vehicle",
    "collision_pedestrian",
    "collision_static",
    "red_light",
    "off_road",
    "wrong_way",
    "route_deviation",
]

#: CARLA leaderboard 1.0 penalty per infraction (driving score = completion x product).
CARLA_PENALTY: dict[str, float] = {
    "collision_pedestrian": 0.50,
    "collision_vehicle": 0.60,
    "collision_static": 0.65,
    "red_light": 0.70,
}
#: nuPlan's comfort bounds.
MIN_LON_ACCEL, MAX_LON_ACCEL = -4.05, 2.40
MAX_ABS_LAT_ACCEL = 4.89
MAX_ABS_YAW_RATE = 0.95
MAX_ABS_YAW_ACCEL = 1.93
MAX_ABS_LON_JERK = 4.13
MAX_ABS_JERK = 8.37
#: Savitzky-Golay window (steps) of the comfort signals: 1.5 s at the simulator's 10 Hz.
SMOOTHING_WINDOW = 15
#: nuPlan's least time to collision (s) and the speed (m/s) under which the ego counts as still.
TTC_BOUND = 0.95
STOPPED_SPEED = 0.5
#: NAVSIM scores ego progress as 1 when the expert itself moved less than this (m).
EP_MIN_PROGRESS = 5.0
#: How driving results are tabled (the CLI, the dashboard, tools/drive_table.py): (header,
#: key in a driver's summary, format); who planned first (a score of frames the driver did
#: not plan is not its own), then open loop, then closed loop, infractions per route.
TABLE_COLUMNS = (
    ("planned itself (% of frames)", "planned_share", "{:.0f}"),
    ("fell back to constant velocity (%)", "fell_back_share", "{:.0f}"),
    ("open-loop L2 (m, `stp3`)", "open_loop_L2_stp3_avg", "{:.2f}"),
    ("open-loop collision (%, `stp3`)", "open_loop_collision_stp3_avg", "{:.2f}"),
    ("driving score", "driving_score", "{:.1f}"),
    ("PDM score", "pdm_score", "{:.1f}"),
    ("route completion (%)", "route_completion", "{:.1f}"),
    ("collisions", "collisions", "{:.2f}"),
    ("red lights", "red_lights", "{:.2f}"),
    ("off road", "off_road", "{:.2f}"),
    ("wrong way", "wrong_way", "{:.2f}"),
    ("left the route", "route_deviation", "{:.2f}"),
)
#: NAVSIM's PDM score weights.
PDM_WEIGHTS = {"ttc": 5.0, "ep": 5.0, "comfort": 2.0}


@dataclass(frozen=True)
class Infraction:
    """One infraction: what, when (s from the episode's start), against whom, and whose fault."""

    kind: InfractionKind
    time: float
    at_fault: bool = True
    other: str = ""


@dataclass
class EpisodeTrace:
    """What the simulator recorded of one episode, at its simulation step ``dt``.

    Per-step arrays have one entry per simulated step. ``progress`` is the distance (m) the
    ego advanced along its route, ``expert_progress`` the expert's over the same time;
    ``off_route`` (m) is the part of ``progress`` driven off the drivable area or against the
    lane direction. ``ttc`` is the least time to collision (s) at each step, ``inf`` when
    no one is on a collision course.
    """

    dt: float
    speed: np.ndarray
    lon_accel: np.ndarray
    lat_accel: np.ndarray
    yaw_rate: np.ndarray
    ttc: np.ndarray
    progress: float
    expert_progress: float
    off_route: float = 0.0
    infractions: list[Infraction] = field(default_factory=list)


@dataclass(frozen=True)
class DrivingScores:
    """The scores of one episode (percent where a percentage, counts where counts)."""

    route_completion: float
    driving_score: float
    infraction_penalty: float
    pdm_score: float
    no_at_fault_collision: float
    drivable_area_compliance: float
    ttc_within_bound: float
    ego_progress: float
    comfort: float
    collisions: int
    collisions_vehicle: int
    collisions_pedestrian: int
    collisions_static: int
    red_lights: int
    off_road: int
    wrong_way: int
    route_deviation: int
    min_ttc: float
    max_abs_lon_accel: float
    max_abs_jerk: float

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}


def _smooth(x: np.ndarray, dt: float, deriv: int = 0) -> np.ndarray:
    """``x`` (or its derivative) through a quadratic Savitzky-Golay filter; short traces use finite differences."""
    if len(x) >= SMOOTHING_WINDOW:
        return savgol_filter(x, SMOOTHING_WINDOW, 2, deriv=deriv, delta=dt, mode="interp")
    if deriv == 0:
        return np.asarray(x, dtype=np.float64)
    return np.gradient(x, dt) if len(x) > 1 else np.zeros(len(x))


@dataclass(frozen=True)
class Comfort:
    """The smoothed comfort signals of an episode."""

    lon_accel: np.ndarray
    lat_accel: np.ndarray
    yaw_rate: np.ndarray
    yaw_accel: np.ndarray
    lon_jerk: np.ndarray
    jerk: np.ndarray

    @staticmethod
    def of(trace: EpisodeTrace) -> Comfort:
        lon_jerk = _smooth(trace.lon_accel, trace.dt, 1)
        return Comfort(
            lon_accel=_smooth(trace.lon_accel, trace.dt),
            lat_accel=_smooth(trace.lat_accel, trace.dt),
            yaw_rate=_smooth(trace.yaw_rate, trace.dt),
            yaw_accel=_smooth(trace.yaw_rate, trace.dt, 1),
            lon_jerk=lon_jerk,
            jerk=np.hypot(lon_jerk, _smooth(trace.lat_accel, trace.dt, 1)),
        )

    def within_bounds(self) -> bool:
        """nuPlan's six comfort bounds, all held at every step."""
        checks = (
            np.all((self.lon_accel >= MIN_LON_ACCEL) & (self.lon_accel <= MAX_LON_ACCEL)),
            np.all(np.abs(self.lat_accel) <= MAX_ABS_LAT_ACCEL),
            np.all(np.abs(self.yaw_rate) <= MAX_ABS_YAW_RATE),
            np.all(np.abs(self.yaw_accel) <= MAX_ABS_YAW_ACCEL),
            np.all(np.abs(self.lon_jerk) <= MAX_ABS_LON_JERK),
            np.all(self.jerk <= MAX_ABS_JERK),
        )
        return bool(all(checks))


def score_episode(trace: EpisodeTrace) -> DrivingScores:
    """CARLA's driving score and NAVSIM's PDM score of one episode, with their terms."""
    at_fault = [i for i in trace.infractions if i.at_fault]
    count = {kind: sum(1 for i in at_fault if i.kind == kind) for kind in get_args(InfractionKind)}
    if trace.expert_progress <= 0:
        completion = 100.0 if trace.progress >= 0 else 0.0
    else:
        on_route = max(trace.progress - trace.off_route, 0.0)
        completion = 100.0 * min(on_route / trace.expert_progress, 1.0)
    penalty = float(np.prod([CARLA_PENALTY[k] ** n for k, n in count.items() if k in CARLA_PENALTY]))

    hits_agent = count["collision_vehicle"] + count["collision_pedestrian"]
    nc = 0.0 if hits_agent else (0.5 if count["collision_static"] else 1.0)
    dac = 0.0 if count["off_road"] else 1.0
    moving = trace.speed >= STOPPED_SPEED
    min_ttc = float(trace.ttc[moving].min()) if moving.any() else float("inf")
    ttc_ok = 0.0 if min_ttc < TTC_BOUND else 1.0
    if trace.expert_progress < EP_MIN_PROGRESS:
        ep = 1.0
    else:
        ep = float(np.clip(trace.progress / trace.expert_progress, 0.0, 1.0))
    smooth = Comfort.of(trace)
    comfort = 1.0 if smooth.within_bounds() else 0.0
    weighted = PDM_WEIGHTS["ttc"] * ttc_ok + PDM_WEIGHTS["ep"] * ep + PDM_WEIGHTS["comfort"] * comfort
    pdm = nc * dac * weighted / sum(PDM_WEIGHTS.values())

    collisions = count["collision_vehicle"] + count["collision_pedestrian"] + count["collision_static"]
    return DrivingScores(
        route_completion=completion,
        driving_score=completion * penalty,
        infraction_penalty=penalty,
        pdm_score=100.0 * pdm,
        no_at_fault_collision=nc,
        drivable_area_compliance=dac,
        ttc_within_bound=ttc_ok,
        ego_progress=ep,
        comfort=comfort,
        collisions=collisions,
        collisions_vehicle=count["collision_vehicle"],
        collisions_pedestrian=count["collision_pedestrian"],
        collisions_static=count["collision_static"],
        red_lights=count["red_light"],
        off_road=count["off_road"],
        wrong_way=count["wrong_way"],
        route_deviation=count["route_deviation"],
        min_ttc=min_ttc,
        max_abs_lon_accel=float(np.abs(smooth.lon_accel).max()) if len(trace.lon_accel) else 0.0,
        max_abs_jerk=float(smooth.jerk.max()) if len(trace.lon_accel) else 0.0,
    )


def aggregate(scores: list[DrivingScores]) -> dict[str, float]:
    """Mean of every score over episodes (counts become rates per episode), as CARLA and NAVSIM average routes."""
    if not scores:
        return {}
    rows = [s.as_dict() for s in scores]
    out = {}
    for key in rows[0]:
        values = np.array([r[key] for r in rows])
        finite = values[np.isfinite(values)]
        out[key] = float(finite.mean()) if len(finite) else float("inf")
    out["episodes"] = float(len(scores))
    out["episodes_without_at_fault_collision"] = float(sum(s.no_at_fault_collision == 1.0 for s in scores))
    return out
