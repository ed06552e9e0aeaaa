"""Per-frame occupancy in the ego frame and the lidar / camera visibility masks, as Occ3D
builds them.

Semantics are surfaces. The static raster (``citymap``) is sampled at the grid columns'
global positions (nearest cell) and expanded to hulls by ``column_table`` (foliage, which
a lidar sees into, through); every box whose footprint reaches the grid is drawn as the
hull of an oriented prism standing on the ground. Occ3D aggregates a scene's lidar sweeps,
so a static surface is labelled only where some frame's lidar saw it (``observe_static``
records that over the scene); boxed objects are labelled whole, as Occ3D aggregates their
points in their own box frames. The ego's own box stays free.

Lidar visibility is a z-buffer over (beam, azimuth) bins of the 32-beam roof sensor, fixed
in the ego frame. Every occupied surface voxel above the ground writes its range into the
bins its cube covers, and the ground plane returns in every beam that looks down and meets
it within the sensor's range. A ray observes only when it returns: a voxel is seen when a
beam crosses it and it is the first hit of that bin (within half a voxel) or free and
before that hit; a bin that meets nothing, looking up into the sky, observes nothing. A
ground voxel is seen when a beam's ring on the ground crosses its column (the ego's motion
over a key frame's sweeps widens each ring) and nothing stands in front of it. The
per-voxel geometry is computed once per process.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache, lru_cache

import numpy as np

from occtrain.data.geometry import ego_to_global, global_to_ego
from occtrain.data.synth.catalog import TrackSet
from occtrain.data.synth.citymap import VEGETATION, StaticMap, column_table
from occtrain.data.synth.grid import EGO_HEIGHT, GROUND_LAYER, GROUND_LAYERS, GROUND_TOP_Z, column_centres, layer_span
from occtrain.formats.occ3d import EGO_LENGTH, EGO_WIDTH, FREE, GRID_SHAPE, RANGE_MIN, VOXEL_SIZE, voxel_centers_1d

#: Angular size of a z-buffer bin (both azimuth and elevation).
BIN_DEG = 0.5


@dataclass(frozen=True)
class Sensor:
    """A spinning sensor ``height`` m above the ground at the ego origin whose beams look
    at the elevations ``beams`` (degrees), all around, and return up to ``max_range`` m."""

    height: float
    beams: tuple[float, ...]
    max_range: float


#: nuScenes roof lidar (a 32-beam Velodyne HDL-32E): 1.84 m up, beams 1.33 degrees apart
#: from -30.67 to +10.67 degrees, returns up to about 70 m.
LIDAR = Sensor(1.84, tuple(np.round(np.linspace(-30.67, 10.67, 32), 4)), 70.0)
#: Sweeps accumulated per frame: the ego moves between them, which fills in the rings
#: single sweeps leave on the ground (the sweeps between two 2 Hz key frames).
SWEEPS = 10
#: How far the ego moves between two sweeps (m): 20 Hz at a city speed of 5 m/s.
SWEEP_SPREAD_M = 0.25


@dataclass(frozen=True)
class _Geometry:
    """Per-voxel (flattened) geometry seen from one sensor. Bins are (beam, azimuth) pairs
    of a z-buffer whose azimuth axis is doubled (width 2 * n_az) so a footprint never
    wraps; the spare last bin stands for "no beam"."""

    rng: np.ndarray  # (V,) float32 range to the voxel centre
    bin: np.ndarray  # (V,) int32 bin of the beam through the voxel nearest its centre; spare: none crosses it
    base: np.ndarray  # (V,) int32 first bin of the cube's footprint
    na: np.ndarray  # (V,) int32 azimuth bins the footprint covers
    count: np.ndarray  # (V,) int32 bins the footprint covers (0 when no beam crosses the cube)
    ground: np.ndarray  # (bins + 1,) float32 range at which each bin meets the ground plane (inf: never)
    column_bin: np.ndarray  # (X * Y,) int32 bin of a beam meeting each column's ground; spare: none
    column_rng: np.ndarray  # (X * Y,) float32 range to the column's ground surface point
    below: int  # number of layers whose centre is below the sensor (their +z neighbour faces it)
    n_az: int
    n_el: int


@cache
def sensor_geometry(sensor: Sensor) -> _Geometry:
    xs, ys, zs = (voxel_centers_1d(a) for a in range(3))
    zs = zs - (GROUND_TOP_Z + sensor.height)
    x, y, z = (a.ravel() for a in np.meshgrid(xs, ys, zs, indexing="ij"))
    rho = np.hypot(x, y)
    r = np.sqrt(rho**2 + z**2)
    az = np.arctan2(y, x)
    el = np.arctan2(z, rho)
    beams = np.deg2rad(np.asarray(sensor.beams))
    step = np.deg2rad(BIN_DEG)
    n_az, n_el = int(round(360 / BIN_DEG)), len(beams)
    width = 2 * n_az
    spare = n_el * width
    # Angular half-extent of a voxel cube seen from the sensor (its projected width / range).
    half_az = np.minimum(0.5 * VOXEL_SIZE * (np.abs(np.cos(az)) + np.abs(np.sin(az))) / np.maximum(rho, 1e-6), np.pi)
    half_el = 0.5 * VOXEL_SIZE * (np.abs(np.cos(el)) + np.abs(np.sin(el))) / r
    a_lo = np.floor((az - half_az + np.pi) / step).astype(np.int64)
    a_hi = np.floor((az + half_az + np.pi) / step).astype(np.int64)
    na = np.minimum(a_hi - a_lo + 1, n_az)
    e0 = np.searchsorted(beams, el - half_el)  # the beams inside the cube's elevation extent
    ne = np.searchsorted(beams, el + half_el, side="right") - e0
    nearest = np.clip(np.searchsorted(beams, el), 1, n_el - 1)
    nearest = np.where(np.abs(beams[nearest - 1] - el) < np.abs(beams[nearest] - el), nearest - 1, nearest)
    a_c = np.floor((az + np.pi) / step).astype(np.int64) % n_az
    centre = np.where(ne > 0, nearest * width + a_c, spare)
    with np.errstate(divide="ignore"):
        row = np.where(beams < 0, sensor.height / np.sin(-beams), np.inf)
    row[row > sensor.max_range] = np.inf  # too far to return
    ground = np.r_[np.repeat(row, width), -np.inf].astype(np.float32)  # the spare bin sees nothing
    # A column's ground is met when a beam's ring (or, as the ego moves over the sweeps,
    # one of its copies) crosses the column.
    cx, cy = (a.ravel() for a in np.meshgrid(xs, ys, indexing="ij"))
    c_rho = np.hypot(cx, cy)
    c_half = 0.5 * VOXEL_SIZE * (np.abs(np.cos(np.arctan2(cy, cx))) + np.abs(np.sin(np.arctan2(cy, cx))))
    ring = np.where(beams < 0, sensor.height / np.tan(-np.minimum(beams, -1e-9)), np.inf)
    ring[np.isinf(row)] = np.inf  # a beam whose ground is too far returns nothing from it
    reach = c_half[:, None] + SWEEP_SPREAD_M * (SWEEPS - 1) / 2
    crossing = np.abs(ring[None] - c_rho[:, None]) <= reach
    c_beam = np.where(crossing.any(1), np.argmax(crossing, axis=1), -1)
    c_az = np.floor((np.arctan2(cy, cx) + np.pi) / step).astype(np.int64) % n_az
    return _Geometry(
        rng=r.astype(np.float32),
        bin=centre.astype(np.int32),
        base=(np.minimum(e0, n_el - 1) * width + a_lo % n_az).astype(np.int32),
        na=na.astype(np.int32),
        count=(na * ne).astype(np.int32),
        ground=ground,
        column_bin=np.where(c_beam >= 0, c_beam * width + c_az, spare).astype(np.int32),
        column_rng=np.hypot(c_rho, sensor.height).astype(np.float32),
        below=int(np.sum(zs < 0)),
        n_az=n_az,
        n_el=n_el,
    )


#: Per axis (x, y, z): whether the neighbour on the minus side and on the plus side is free.
FacingFree = tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def _facing_free(occupied: np.ndarray) -> FacingFree:
    """Whether each voxel's x, y and z neighbours on either side are free (the border counts as free).

    Returns (x, y, z) where e.g. x[0] is "the -x neighbour is free" and x[1] "the +x one is".
    """
    free = ~occupied
    out: list[tuple[np.ndarray, np.ndarray]] = []
    for axis in range(3):
        minus = np.ones_like(free)
        plus = np.ones_like(free)
        src = [slice(None)] * 3
        dst = [slice(None)] * 3
        src[axis], dst[axis] = slice(None, -1), slice(1, None)
        minus[tuple(dst)] = free[tuple(src)]
        plus[tuple(src)] = free[tuple(dst)]
        out.append((minus, plus))
    return out[0], out[1], out[2]


def _front_surface(occupied: np.ndarray, free_nb: FacingFree, below: int) -> np.ndarray:
    """Occupied voxels above the ground with a free neighbour on a side facing the sensor.

    Any ray into a voxel enters through a face toward the sensor; if all those
    neighbours are occupied the voxel is never the first hit, so it needs no z-buffer entry.
    """
    (xm, xp), (ym, yp), (zm, zp) = free_nb
    hx, hy = GRID_SHAPE[0] // 2, GRID_SHAPE[1] // 2  # the sensor sits between these columns
    face = np.concatenate([xp[:hx], xm[hx:]], axis=0)
    face |= np.concatenate([yp[:, :hy], ym[:, hy:]], axis=1)
    face |= np.concatenate([zp[..., :below], zm[..., below:]], axis=2)
    face &= occupied
    face[..., :GROUND_LAYERS] = False
    return face


def visibility(semantics: np.ndarray, sensor: Sensor, free_nb: FacingFree | None = None) -> np.ndarray:
    """(X, Y, Z) bool: voxels the sensor observes (see the module docstring).

    ``free_nb`` may pass in :func:`_facing_free` of the occupancy when several sensors look
    at the same frame.
    """
    g = sensor_geometry(sensor)
    occupied = semantics != FREE
    if free_nb is None:
        free_nb = _facing_free(occupied)
    idx = np.flatnonzero(_front_surface(occupied, free_nb, g.below).ravel())
    count = g.count[idx]
    idx, count = idx[count > 0], count[count > 0]
    rep = np.repeat(np.arange(len(idx), dtype=np.int32), count)
    local = np.arange(len(rep), dtype=np.int32) - (np.cumsum(count, dtype=np.int32) - count)[rep]
    row, col = np.divmod(local, g.na[idx][rep])
    width = 2 * g.n_az
    standing = np.full(g.n_el * width + 1, np.inf, np.float32)
    np.minimum.at(standing, g.base[idx][rep] + row * width + col, g.rng[idx][rep])
    # Fold the doubled azimuth axis; the spare last bin (outside the view) sees nothing.
    grid = standing[:-1].reshape(g.n_el, width)
    grid[:, : g.n_az] = np.minimum(grid[:, : g.n_az], grid[:, g.n_az :])
    grid[:, g.n_az :] = grid[:, : g.n_az]
    standing[-1] = -np.inf
    first_hit = np.minimum(standing, g.ground)[g.bin]
    # A ray that returns observes the voxel it ends in and the free ones before it.
    returns = np.isfinite(first_hit)
    seen = np.where(occupied.ravel(), g.rng <= first_hit + VOXEL_SIZE / 2, returns & (g.rng < first_hit)).reshape(
        GRID_SHAPE
    )
    seen[..., :GROUND_LAYERS] = False
    ground_seen = standing[g.column_bin] >= g.column_rng - VOXEL_SIZE / 2
    seen[..., GROUND_LAYER] = ground_seen.reshape(GRID_SHAPE[:2])
    return seen


def masks(semantics: np.ndarray, lidar: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(mask_lidar, mask_camera) as uint8 0/1: what the roof lidar sees (the z-buffer
    above), and of that what the six cameras see (``camera_render.camera_mask``: voxels
    their rays cross up to the first surface, as Occ3D casts camera rays). ``lidar`` may
    pass in the lidar visibility when it is already known (``observe_static`` computes it)."""
    from occtrain.data.synth.camera_render import camera_mask

    if lidar is None:
        lidar = visibility(semantics, LIDAR)
    return lidar.astype(np.uint8), (camera_mask(semantics, among=lidar) & lidar).astype(np.uint8)


@lru_cache(maxsize=1)
def _columns() -> np.ndarray:
    return column_table(GRID_SHAPE[2], GROUND_LAYERS)


def static_semantics(static: StaticMap, pose_xy: np.ndarray, pose_yaw: float, observed_only: bool = True) -> np.ndarray:
    """(X, Y, Z) uint8 classes of the static world seen from an ego pose (nearest raster cell).

    With ``observed_only`` (and ``static.observed`` recorded), surfaces no sensor saw over
    the scene are free, as in Occ3D's aggregated labels.
    """
    ix, iy = static.cells(ego_to_global(column_centres(), pose_xy, pose_yaw))
    sem = _columns()[static.column_key[ix, iy]]
    if observed_only and static.observed is not None:
        sem[~static.observed[ix, iy]] = FREE
    return sem


def draw_boxes(sem: np.ndarray, centre: np.ndarray, yaw: np.ndarray, size: np.ndarray, cls: np.ndarray) -> None:
    """Draw the hulls of oriented boxes standing on the ground into ``sem`` in place (ego frame).

    A column belongs to a box when its centre lies inside the footprint; the column under
    the box centre always does, so small things (cones, pedestrians) never vanish. A column
    with a neighbour outside the footprint holds the box's whole height (its sides); one
    inside holds the top and the bottom layer (roof and underbody, which the sweeps of a
    scene see from all around).
    """
    if len(centre) == 0:
        return
    nx, ny, _ = GRID_SHAPE
    c, s = np.cos(yaw), np.sin(yaw)
    hl, hw = size[:, 0] / 2, size[:, 1] / 2
    ext = np.stack([np.abs(c) * hl + np.abs(s) * hw, np.abs(s) * hl + np.abs(c) * hw], axis=1)
    lo_i = np.floor((centre - ext - RANGE_MIN[:2]) / VOXEL_SIZE).astype(np.int64)
    hi_i = np.floor((centre + ext - RANGE_MIN[:2]) / VOXEL_SIZE).astype(np.int64)
    lo_i = np.maximum(lo_i, 0)
    hi_i = np.minimum(hi_i, [nx - 1, ny - 1])
    span = hi_i - lo_i + 1
    keep = np.all(span > 0, axis=1)
    if not keep.any():
        return
    centre, c, s, hl, hw, lo_i, span, cls = (
        centre[keep],
        c[keep],
        s[keep],
        hl[keep],
        hw[keep],
        lo_i[keep],
        span[keep],
        cls[keep],
    )
    lo_k, hi_k = layer_span(np.zeros(int(keep.sum())), size[keep, 2])
    counts = span[:, 0] * span[:, 1]
    rep = np.repeat(np.arange(len(counts)), counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    ix = lo_i[rep, 0] + local // span[rep, 1]
    iy = lo_i[rep, 1] + local % span[rep, 1]
    own = np.floor((centre - RANGE_MIN[:2]) / VOXEL_SIZE).astype(np.int64)

    def inside(dx_cells: int, dy_cells: int) -> np.ndarray:
        dx = RANGE_MIN[0] + (ix + dx_cells + 0.5) * VOXEL_SIZE - centre[rep, 0]
        dy = RANGE_MIN[1] + (iy + dy_cells + 0.5) * VOXEL_SIZE - centre[rep, 1]
        within = (np.abs(c[rep] * dx + s[rep] * dy) <= hl[rep]) & (np.abs(-s[rep] * dx + c[rep] * dy) <= hw[rep])
        return within | ((ix + dx_cells == own[rep, 0]) & (iy + dy_cells == own[rep, 1]))

    here = inside(0, 0)
    side = ~(inside(-1, 0) & inside(1, 0) & inside(0, -1) & inside(0, 1))
    rep, ix, iy, side = rep[here], ix[here], iy[here], side[here]
    k = np.arange(GRID_SHAPE[2])
    lo, hi = lo_k[rep, None], hi_k[rep, None]
    layers = (k >= lo) & (k < hi) & (side[:, None] | (k == lo) | (k == hi - 1))
    cols = sem.reshape(nx * ny, -1)
    rows = ix * ny + iy
    cols[rows] = np.where(layers, cls[rep, None].astype(np.uint8), cols[rows])


def clear_ego(sem: np.ndarray) -> None:
    """Free the ego's own box (Occ3D never labels the ego vehicle)."""
    xs, ys = voxel_centers_1d(0), voxel_centers_1d(1)
    ix = np.flatnonzero(np.abs(xs) <= EGO_LENGTH / 2)
    iy = np.flatnonzero(np.abs(ys) <= EGO_WIDTH / 2)
    _, hi = layer_span(0.0, EGO_HEIGHT)
    sem[ix[0] : ix[-1] + 1, iy[0] : iy[-1] + 1, GROUND_LAYERS : int(hi)] = FREE


def draw_tracks(sem: np.ndarray, tracks: TrackSet, t: int, pose_xy: np.ndarray, pose_yaw: float) -> None:
    """Draw frame ``t``'s boxed objects near the grid into ``sem`` (ego frame), then free the ego's box."""
    centre = global_to_ego(tracks.xy[:, t], pose_xy, pose_yaw)
    reach = np.hypot(tracks.size[:, 0], tracks.size[:, 1]) / 2
    near = np.all(np.abs(centre) <= -RANGE_MIN[:2] + reach[:, None], axis=1)
    draw_boxes(sem, centre[near], tracks.yaw[near, t] - pose_yaw, tracks.size[near], tracks.cls[near])
    clear_ego(sem)


def frame_semantics(static: StaticMap, tracks: TrackSet, t: int, pose_xy: np.ndarray, pose_yaw: float) -> np.ndarray:
    """(X, Y, Z) uint8 Occ3D classes of frame ``t`` seen from the ego pose."""
    sem = static_semantics(static, pose_xy, pose_yaw)
    draw_tracks(sem, tracks, t, pose_xy, pose_yaw)
    return sem


#: Cells (0.2 m) an observation spreads to around the cell it was made in: another frame
#: samples the same voxel's centre from a rotated grid, up to 0.28 m away.
OBSERVED_SPREAD = 2


def observe_static(
    static: StaticMap, tracks: TrackSet, poses_xy: np.ndarray, poses_yaw: np.ndarray
) -> list[np.ndarray]:
    """Record in ``static.observed`` the static surfaces the lidar saw from any of the poses
    (Occ3D's aggregation of a scene's sweeps), and return each pose's lidar visibility.

    Each frame is seen with everything in it, boxed objects included (they hide what is
    behind them). Observing the labelled frame again gives the same visibility: only
    surfaces no ray reached are removed, and those hid nothing.
    """
    nx, ny = static.ground.shape
    observed = np.zeros((nx, ny, GRID_SHAPE[2]), bool)
    seen_per_frame = []
    for t in range(len(poses_xy)):
        bare = static_semantics(static, poses_xy[t], float(poses_yaw[t]), observed_only=False)
        sem = bare.copy()
        draw_tracks(sem, tracks, t, poses_xy[t], float(poses_yaw[t]))
        is_static = (bare != FREE) & (sem == bare)
        seen = visibility(sem, LIDAR)
        seen_per_frame.append(seen)
        x, y, z = np.nonzero(seen & is_static)
        ix, iy = static.cells(ego_to_global(column_centres()[x, y], poses_xy[t], float(poses_yaw[t])))
        observed[ix, iy, z] = True
    for axis in (0, 1):  # spread each observation over the cells the same voxel may sample
        spread = observed.copy()
        for d in range(1, OBSERVED_SPREAD + 1):
            lo, hi = [slice(None)] * 3, [slice(None)] * 3
            lo[axis], hi[axis] = slice(None, -d), slice(d, None)
            spread[tuple(lo)] |= observed[tuple(hi)]
            spread[tuple(hi)] |= observed[tuple(lo)]
        observed = spread
    # Foliage is porous (see column_table): where a sweep saw into a crown or a hedge, it
    # saw all of that column's foliage.
    porous = static.cls == VEGETATION
    observed[porous] = observed[porous].any(axis=1, keepdims=True)
    static.observed = observed
    return seen_per_frame
