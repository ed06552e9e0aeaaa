"""Moving agents: vehicles and cyclists following lane routes, pedestrians on sidewalks.

Vehicles (the ego included) drive along their routes with the Intelligent Driver Model:
bounded acceleration and braking, a desired speed capped by a curvature envelope (so
turns are slow and the yaw rate stays bounded), car-following behind the nearest vehicle
ahead in the same direction, and stops at red traffic lights. Towed trailers follow their
tractor along the same route. Pedestrians walk along sidewalk lines at walking speed and
cross roads at the crosswalks only while the parallel traffic has green. Agents that would
still collide (crossing conflicts the simple model does not resolve) are removed, lowest
priority first, and the traffic is simulated again.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from occtrain.data.synth.catalog import KINDS, TrackSet
from occtrain.data.synth.roads import PATH_DS, Path, green_left

#: Simulation step (s); frames are every FRAME_DT, a whole number of steps.
SIM_DT = 0.1
#: Lateral acceleration allowed in curves (m/s^2) and the braking used to slow down for them.
LATERAL_ACCEL = 2.5
CURVE_BRAKING = 2.0
#: Hardest braking any vehicle uses (m/s^2).
MAX_BRAKING = 6.0
#: IDM jam distance (m) and the amber time (s) during which a vehicle that can stop does.
JAM_GAP = 2.0
AMBER = 3.0
#: Pedestrians: the largest change of walking speed (m/s^2).
WALK_ACCEL = 1.5
#: How often (in steps) collisions are checked and how many re-simulations are tried.
COLLISION_STRIDE = 2
PRUNE_ROUNDS = 5


@dataclass
class Mover:
    """A vehicle or cyclist on a route. ``host`` >= 0 makes it a trailer towed ``host_gap`` behind."""

    kind: str
    size: np.ndarray
    path: Path
    s0: float
    v0: float
    v_des: np.ndarray  # (steps,) desired speed over time
    priority: float
    lateral: float = 0.0  # offset to the right of the path (cyclists keep to the kerb)
    a_max: float = 1.8
    b_comf: float = 2.5
    headway: float = 1.5
    rider: int = -1
    host: int = -1  # index of the towing tractor in the scene's mover list
    host_gap: float = 0.0


@dataclass
class Walker:
    """A pedestrian on a straight sidewalk line; ``crossings`` are road stretches along it."""

    start: np.ndarray  # (2,) global
    direction: np.ndarray  # (2,) unit
    speed: float  # 0 for a standing pedestrian
    size: np.ndarray
    yaw: float
    crossings: list[tuple[float, float, np.ndarray, int]] = field(default_factory=list)  # (from, to, light, green axis)
    priority: float = 0.0


@dataclass
class MotionResult:
    """Per-step states of the movers that survived pruning (index 0 is the ego)."""

    movers: list[Mover]
    s: np.ndarray  # (N, steps)
    v: np.ndarray
    a: np.ndarray
    xy: np.ndarray  # (N, steps, 2)
    yaw: np.ndarray  # (N, steps)
    curvature: np.ndarray  # (N, steps)

    def subset(self, keep: list[int]) -> MotionResult:
        return MotionResult(
            [self.movers[i] for i in keep],
            self.s[keep],
            self.v[keep],
            self.a[keep],
            self.xy[keep],
            self.yaw[keep],
            self.curvature[keep],
        )


class _PathBank:
    """All movers' paths concatenated, for vectorised interpolation at arc lengths."""

    def __init__(self, paths: list[Path]):
        self.offset = np.cumsum([0] + [len(p.xy) for p in paths[:-1]])
        self.count = np.array([len(p.xy) for p in paths])
        self.xy = np.concatenate([p.xy for p in paths])
        self.heading = np.concatenate([p.heading for p in paths])
        self.curvature = np.concatenate([p.curvature for p in paths])
        # Speed envelope: the fastest speed from which the vehicle can still brake (at
        # CURVE_BRAKING) to every later curve's lateral-acceleration limit.
        env = []
        for p in paths:
            s = np.arange(len(p.xy)) * PATH_DS
            vmax2 = LATERAL_ACCEL / np.maximum(np.abs(p.curvature), 1e-4)
            reach = np.minimum.accumulate((vmax2 + 2 * CURVE_BRAKING * s)[::-1])[::-1]
            env.append(np.sqrt(np.maximum(reach - 2 * CURVE_BRAKING * s, 0.0)))
        self.envelope = np.concatenate(env)

    def lookup(self, s: np.ndarray, lateral: np.ndarray):
        """(xy, heading, curvature, speed envelope) at arc lengths ``s`` (one per path).

        Beyond either end of a path the pose continues straight along its end heading.
        """
        pos = s / PATH_DS
        i0 = np.clip(np.floor(pos).astype(np.int64), 0, self.count - 2)
        f = pos - i0
        g = self.offset + i0
        xy = self.xy[g] + f[:, None] * (self.xy[g + 1] - self.xy[g])
        fh = np.clip(f, 0.0, 1.0)
        hd = self.heading[g] + fh * (self.heading[g + 1] - self.heading[g])
        near = self.offset + np.clip(np.rint(pos).astype(np.int64), 0, self.count - 1)
        xy = xy + lateral[:, None] * np.stack([np.sin(hd), -np.cos(hd)], axis=1)
        return xy, hd, self.curvature[near], self.envelope[near]


def _stop_table(movers: list[Mover]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    k = max(1, max(len(m.path.stops) for m in movers))
    s = np.full((len(movers), k), np.inf)
    light = np.zeros((len(movers), k, 6))
    light[..., 0] = 1.0
    axis = np.zeros((len(movers), k), np.int64)
    for i, m in enumerate(movers):
        for j, (si, li, ai) in enumerate(m.path.stops):
            s[i, j], light[i, j], axis[i, j] = si, li, ai
    return s, light, axis


class MoverTraffic:
    """The movers' IDM traffic, one SIM_DT step at a time.

    The generator runs it from t = 0 to the end of a scene (``simulate_movers``); closed-loop
    driving runs the same steps with the ego's state supplied from outside (``pose``, then the
    ego's row of the returned xy and yaw and of ``v`` overwritten, then ``advance``), so the
    traffic reacts to wherever the driven ego is exactly as it reacts to the generator's ego.
    """

    def __init__(self, movers: list[Mover], host: np.ndarray):
        self.movers = movers
        self.host = host
        self.bank = _PathBank([m.path for m in movers])
        size = np.array([m.size for m in movers])
        self.length, self.width = size[:, 0], size[:, 1]
        self.lateral = np.array([m.lateral for m in movers])
        self.a_max = np.array([m.a_max for m in movers])
        self.b_comf = np.array([m.b_comf for m in movers])
        self.headway = np.array([m.headway for m in movers])
        self.v_des = np.stack([m.v_des for m in movers])
        self.host_gap = np.array([m.host_gap for m in movers])
        self.towed = host >= 0
        self.free = ~self.towed
        self.stop_s, self.stop_light, self.stop_axis = _stop_table(movers)
        self.rows = np.arange(len(movers))
        self.s = np.array([m.s0 for m in movers], dtype=np.float64)
        self.v = np.array([m.v0 for m in movers], dtype=np.float64)

    def pose(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(xy, yaw, curvature, speed envelope) of every mover now, trailers pulled to their tractors."""
        towed, host = self.towed, self.host
        self.s[towed] = self.s[host[towed]] - self.host_gap[towed]
        self.v[towed] = self.v[host[towed]]
        return self.bank.lookup(self.s, self.lateral)

    def advance(self, step: int, xy: np.ndarray, yaw: np.ndarray, env: np.ndarray) -> np.ndarray:
        """One IDM step from the poses ``xy``, ``yaw`` at step ``step``; returns each mover's acceleration."""
        s, v, rows = self.s, self.v, self.rows
        width, length = self.width, self.length
        a_max, b_comf = self.a_max, self.b_comf
        t = step * SIM_DT

        # Leader: nearest vehicle ahead whose box overlaps ours sideways and heads our way.
        c, si = np.cos(yaw), np.sin(yaw)
        d = xy[None, :, :] - xy[:, None, :]
        dx = d[..., 0] * c[:, None] + d[..., 1] * si[:, None]
        dy = -d[..., 0] * si[:, None] + d[..., 1] * c[:, None]
        same_way = np.cos(yaw[None, :] - yaw[:, None]) > 0.5
        ahead = (dx > 0) & (np.abs(dy) < (width[:, None] + width[None, :]) / 2 + 0.2) & same_way
        ahead[rows, rows] = False
        gap = np.where(ahead, dx - (length[:, None] + length[None, :]) / 2, np.inf)
        lead = np.argmin(gap, axis=1)
        lead_gap = gap[rows, lead]
        lead_v = v[lead] * np.cos(yaw[lead] - yaw)

        # Stop line of the next intersection when its light is red (or amber and stoppable).
        front = s + length / 2
        nxt = np.argmax(self.stop_s - front[:, None] > -0.5, axis=1)
        line_gap = self.stop_s[rows, nxt] - front
        left = green_left(self.stop_light[rows, nxt], self.stop_axis[rows, nxt], t)
        can_stop = v**2 / (2 * np.maximum(line_gap, 0.1)) < 1.5 * b_comf
        halt = np.isfinite(line_gap) & (line_gap > -0.5) & ((left < 0) | ((left < AMBER) & can_stop))

        v0 = np.maximum(np.minimum(self.v_des[:, step], env), 0.1)
        acc = a_max * (1 - (v / v0) ** 4)
        for g_, dv in ((lead_gap, v - lead_v), (np.where(halt, line_gap, np.inf), v)):
            want = JAM_GAP + np.maximum(0.0, v * self.headway + v * dv / (2 * np.sqrt(a_max * b_comf)))
            acc = acc - np.where(np.isfinite(g_), a_max * (want / np.maximum(g_, 0.1)) ** 2, 0.0)
        acc = np.clip(acc, -MAX_BRAKING, a_max)
        v_new = np.maximum(v + acc * SIM_DT, 0.0)
        free = self.free
        self.s = np.where(free, s + (v + v_new) / 2 * SIM_DT, s)
        self.v = np.where(free, v_new, v)
        return np.where(free, (v_new - v) / SIM_DT, 0.0)


def simulate_movers(movers: list[Mover], steps: int, host: np.ndarray) -> MotionResult:
    """Run the IDM traffic for ``steps`` steps of SIM_DT from t = 0.

    ``host[i]`` is the index (in ``movers``) of the tractor towing mover i, or -1.
    """
    n = len(movers)
    traffic = MoverTraffic(movers, host)
    out = {k: np.zeros((n, steps)) for k in ("s", "v", "a", "yaw", "curvature")}
    out_xy = np.zeros((n, steps, 2))
    for step in range(steps):
        xy, yaw, curv, env = traffic.pose()
        out["s"][:, step], out["v"][:, step], out["yaw"][:, step], out["curvature"][:, step] = (
            traffic.s,
            traffic.v,
            yaw,
            curv,
        )
        out_xy[:, step] = xy
        out["a"][:, step] = traffic.advance(step, xy, yaw, env)
    towed = traffic.towed
    out["a"][towed] = out["a"][host[towed]]
    return MotionResult(movers, out["s"], out["v"], out["a"], out_xy, out["yaw"], out["curvature"])


def simulate_walkers(walkers: list[Walker], steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Walk the pedestrians for ``steps`` steps; returns xy (P, steps, 2), yaw (P, steps), speed."""
    p = len(walkers)
    if p == 0:
        return np.zeros((0, steps, 2)), np.zeros((0, steps)), np.zeros((0, steps))
    k = max(1, max(len(w.crossings) for w in walkers))
    # Padding crossings lie far beyond any walk.
    c_from = np.full((p, k), 1e9)
    c_to = np.full((p, k), 1e9)
    c_light = np.zeros((p, k, 6))
    c_light[..., 0] = 1.0
    c_axis = np.zeros((p, k), np.int64)
    for i, w in enumerate(walkers):
        for j, (a, b, light, axis) in enumerate(w.crossings):
            c_from[i, j], c_to[i, j], c_light[i, j], c_axis[i, j] = a, b, light, axis
    want = np.array([w.speed for w in walkers])
    rows = np.arange(p)
    s = np.zeros(p)
    v = want.copy()
    s_hist = np.zeros((p, steps))
    v_hist = np.zeros((p, steps))
    for step in range(steps):
        t = step * SIM_DT
        s_hist[:, step], v_hist[:, step] = s, v
        nxt = np.argmax(c_to > s[:, None], axis=1)
        kerb = c_from[rows, nxt] - 0.3
        before = s < kerb
        need = (c_to[rows, nxt] - c_from[rows, nxt]) / np.maximum(want, 0.1) + 1.0
        may_go = green_left(c_light[rows, nxt], c_axis[rows, nxt], t) >= need
        brake_dist = v**2 / (2 * WALK_ACCEL) + 0.2
        wait = before & ~may_go & (kerb - s < brake_dist + v * SIM_DT)
        target = np.where(wait, 0.0, want)
        v_new = v + np.clip(target - v, -WALK_ACCEL * SIM_DT, WALK_ACCEL * SIM_DT)
        s_new = s + (v + v_new) / 2 * SIM_DT
        s = np.where(wait, np.minimum(s_new, np.maximum(kerb, s)), s_new)
        v = v_new
    start = np.array([w.start for w in walkers])
    direction = np.array([w.direction for w in walkers])
    xy = start[:, None, :] + s_hist[..., None] * direction[:, None, :]
    yaw = np.broadcast_to(np.array([w.yaw for w in walkers])[:, None], (p, steps)).copy()
    return xy, yaw, v_hist


#: Discs per footprint in the collision test (enough that adjacent lanes never touch).
COLLISION_DISCS = 7


def footprint_discs(xy: np.ndarray, yaw: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Discs covering box footprints: centres (E, D, 2) and radius (E,) for E poses."""
    step = np.maximum(size[:, 0] - size[:, 1], 0.0) / (COLLISION_DISCS - 1)
    offs = (np.arange(COLLISION_DISCS) - (COLLISION_DISCS - 1) / 2)[None, :] * step[:, None]
    u = np.stack([np.cos(yaw), np.sin(yaw)], axis=-1)
    return xy[:, None, :] + offs[:, :, None] * u[:, None, :], np.hypot(size[:, 1] / 2, step / 2)


def colliding_pairs(
    xy: np.ndarray, yaw: np.ndarray, size: np.ndarray, ignore: set[tuple[int, int]]
) -> list[tuple[int, int]]:
    """Index pairs (i < j) of agents whose footprints overlap at some sampled time.

    ``xy`` (N, T, 2), ``yaw`` (N, T), ``size`` (N, 3); pairs in ``ignore`` never count.
    Pairs are narrowed down by trajectory bounding boxes, then by centre distance per
    time, before the footprints' discs are compared.
    """
    reach = np.hypot(size[:, 0], size[:, 1]) / 2
    lo = xy.min(axis=1) - reach[:, None]
    hi = xy.max(axis=1) + reach[:, None]
    overlap = np.all((lo[:, None] <= hi[None, :]) & (lo[None, :] <= hi[:, None]), axis=-1)
    ii, jj = np.nonzero(np.triu(overlap, 1))
    d2 = np.sum((xy[ii] - xy[jj]) ** 2, axis=-1)  # (P, T)
    pair, t = np.nonzero(d2 < ((reach[ii] + reach[jj]) ** 2)[:, None])
    if len(pair) == 0:
        return []
    a, b = ii[pair], jj[pair]
    ca, ra = footprint_discs(xy[a, t], yaw[a, t], size[a])
    cb, rb = footprint_discs(xy[b, t], yaw[b, t], size[b])
    gap2 = np.sum((ca[:, :, None, :] - cb[:, None, :, :]) ** 2, axis=-1)
    hit = np.any(gap2 < ((ra + rb) ** 2)[:, None, None], axis=(1, 2))
    found = sorted({(int(i), int(j)) for i, j in zip(a[hit], b[hit])})
    return [p for p in found if p not in ignore]


def settle_traffic(
    movers: list[Mover], walkers: list[Walker], steps: int
) -> tuple[MotionResult, list[Walker], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Simulate, then remove colliding agents (lowest priority first) and simulate again.

    ``movers[0]`` is the ego and is never removed; a tractor and its trailer go together.
    After PRUNE_ROUNDS re-simulations every agent still in a collision is dropped without
    another run. Returns the movers' motion, the surviving walkers and their (xy, yaw,
    speed) histories.
    """
    w_hist = simulate_walkers(walkers, steps)
    active = list(range(len(movers)))
    for round_ in range(PRUNE_ROUNDS + 1):
        sub = [movers[i] for i in active]
        pos = {old: new for new, old in enumerate(active)}
        host = np.array([pos[m.host] if m.host >= 0 else -1 for m in sub], dtype=np.int64)
        motion = simulate_movers(sub, steps, host)
        nm = len(sub)
        sl = slice(None, None, COLLISION_STRIDE)
        pairs = colliding_pairs(
            np.concatenate([motion.xy[:, sl], w_hist[0][:, sl]]),
            np.concatenate([motion.yaw[:, sl], w_hist[1][:, sl]]),
            np.array([m.size for m in sub] + [w.size for w in walkers]).reshape(-1, 3),
            {(int(min(i, h)), int(max(i, h))) for i, h in enumerate(host) if h >= 0},
        )
        if not pairs:
            break
        prio = [m.priority for m in sub] + [w.priority for w in walkers]
        final = round_ == PRUNE_ROUNDS
        losers = {x for pair in pairs for x in pair} if final else {i if prio[i] < prio[j] else j for i, j in pairs}
        losers.discard(0)
        drop_m = {x for x in losers if x < nm}
        for i, h in enumerate(host):
            if h >= 0 and (i in drop_m or h in drop_m):
                drop_m |= {i, int(h)}
        keep_w = [k for k in range(len(walkers)) if k + nm not in losers]
        walkers = [walkers[k] for k in keep_w]
        w_hist = (w_hist[0][keep_w], w_hist[1][keep_w], w_hist[2][keep_w])
        if final:
            motion = motion.subset([i for i in range(nm) if i not in drop_m])
        active = [a for i, a in enumerate(active) if i not in drop_m]
    return motion, walkers, w_hist


def mover_tracks(motion: MotionResult, frame_stride: int) -> TrackSet:
    """The non-ego movers as tracks sampled every ``frame_stride`` steps."""
    sl = slice(None, None, frame_stride)
    others = motion.movers[1:]
    return TrackSet(
        cls=np.array([KINDS[m.kind].cls for m in others], dtype=np.int64),
        size=np.array([m.size for m in others]).reshape(-1, 3),
        xy=motion.xy[1:, sl],
        yaw=motion.yaw[1:, sl],
        speed=motion.v[1:, sl],
        parked=np.zeros(len(others), bool),
        rider=np.array([m.rider for m in others], dtype=np.int64),
    )


def walker_tracks(walkers: list[Walker], hist: tuple, frame_stride: int) -> TrackSet:
    """The pedestrians as tracks sampled every ``frame_stride`` steps."""
    xy, yaw, v = hist
    sl = slice(None, None, frame_stride)
    return TrackSet(
        cls=np.full(len(walkers), KINDS["pedestrian"].cls, dtype=np.int64),
        size=np.array([w.size for w in walkers]).reshape(-1, 3),
        xy=xy[:, sl],
        yaw=yaw[:, sl],
        speed=v[:, sl],
        parked=np.zeros(len(walkers), bool),
        rider=np.full(len(walkers), -1, dtype=np.int64),
    )
