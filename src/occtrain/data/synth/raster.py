"""Per-frame occupancy in the ego frame and the lidar / camera visibility masks.

Semantics: the static raster is sampled at the grid columns' global positions (nearest
cell), expanded to the 16 layers, then every box whose footprint reaches the grid is drawn
as an oriented prism standing on the ground. The ego's own box stays free.

Lidar visibility is a z-buffer over (azimuth, elevation) bins around a sensor origin fixed in
the ego frame (camera visibility is ray cast: see ``camera_render``). Every occupied surface voxel above the ground writes its range into all
bins its cube covers; a voxel is visible when it lies inside the sensor's field of view
and is no farther than its bin's first hit plus half a voxel: the first occupied voxel
hit and the free voxels before it are visible, everything behind is not. The ground is a
plane below every sensor, so it never hides anything above it: its top layer is visible
where no object hides it and the layers underneath never are. Occluders and bins are
fixed in the ego frame, so the per-voxel geometry is computed once per process.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from occtrain.data.synth.catalog import TrackSet
from occtrain.data.synth.citymap import StaticMap, column_table
from occtrain.data.synth.grid import EGO_HEIGHT, GROUND_LAYERS, GROUND_TOP_Z, column_centres, layer_span
from occtrain.occ3d import EGO_LENGTH, EGO_WIDTH, FREE, GRID_SHAPE, RANGE_MIN, VOXEL_SIZE, voxel_centers_1d
from occtrain.data.geometry import ego_to_global, global_to_ego

#: Angular size of a z-buffer bin (both azimuth and elevation).
BIN_DEG = 0.5


@dataclass(frozen=True)
class Sensor:
    """A 360-degree sensor at ``height`` m above the ground seeing elevations [el_min, el_max] degrees."""

    height: float
    el_min: float
    el_max: float


#: nuScenes roof lidar: 1.84 m up, about -30..+10 degrees vertically, all around.
LIDAR = Sensor(1.84, -30.0, 10.0)


@dataclass(frozen=True)
class _Geometry:
    """Per-voxel (flattened) geometry seen from one sensor; bins index a z-buffer whose
    azimuth axis is doubled (width 2 * n_az) so a footprint never wraps."""

    rng: np.ndarray  # (V,) float32 range to the voxel centre
    bin: np.ndarray  # (V,) int32 z-buffer bin of the centre; the spare last bin outside the view
    base: np.ndarray  # (V,) int32 first bin of the cube's footprint
    na: np.ndarray  # (V,) int32 azimuth bins the footprint covers
    count: np.ndarray  # (V,) int32 bins the footprint covers (0 when entirely outside the view)
    below: int  # number of layers whose centre is below the sensor (their +z neighbour faces it)
    n_az: int
    n_el: int


@lru_cache(maxsize=None)
def _geometry(sensor: Sensor) -> _Geometry:
    xs, ys, zs = (voxel_centers_1d(a) for a in range(3))
    zs = zs - (GROUND_TOP_Z + sensor.height)
    x, y, z = (a.ravel() for a in np.meshgrid(xs, ys, zs, indexing="ij"))
    rho = np.hypot(x, y)
    r = np.sqrt(rho**2 + z**2)
    az = np.arctan2(y, x)
    el = np.arctan2(z, rho)
    step = np.deg2rad(BIN_DEG)
    n_az = int(round(360 / BIN_DEG))
    n_el = int(round((sensor.el_max - sensor.el_min) / BIN_DEG))
    el0 = np.deg2rad(sensor.el_min)
    # Angular half-extent of a voxel cube seen from the sensor (its projected width / range).
    half_az = np.minimum(0.5 * VOXEL_SIZE * (np.abs(np.cos(az)) + np.abs(np.sin(az))) / np.maximum(rho, 1e-6), np.pi)
    half_el = 0.5 * VOXEL_SIZE * (np.abs(np.cos(el)) + np.abs(np.sin(el))) / r
    a_lo = np.floor((az - half_az + np.pi) / step).astype(np.int64)
    a_hi = np.floor((az + half_az + np.pi) / step).astype(np.int64)
    na = np.minimum(a_hi - a_lo + 1, n_az)
    e_lo = np.floor((el - half_el - el0) / step).astype(np.int64)
    e_hi = np.floor((el + half_el - el0) / step).astype(np.int64)
    e0 = np.clip(e_lo, 0, n_el - 1)
    ne = np.where((e_hi < 0) | (e_lo >= n_el), 0, np.clip(e_hi, 0, n_el - 1) - e0 + 1)
    width = 2 * n_az
    e_c = np.floor((el - el0) / step).astype(np.int64)
    a_c = np.floor((az + np.pi) / step).astype(np.int64) % n_az
    centre_bin = np.where((e_c >= 0) & (e_c < n_el), e_c * width + a_c, n_el * width)
    return _Geometry(
        rng=r.astype(np.float32),
        bin=centre_bin.astype(np.int32),
        base=(e0 * width + a_lo % n_az).astype(np.int32),
        na=na.astype(np.int32),
        count=(na * ne).astype(np.int32),
        below=int(np.sum(zs < 0)),
        n_az=n_az,
        n_el=n_el,
    )


def _facing_free(occupied: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whether each voxel's x, y and z neighbours on either side are free (the border counts as free).

    Returns (x, y, z) where e.g. x[0] is "the -x neighbour is free" and x[1] "the +x one is".
    """
    free = ~occupied
    out = []
    for axis in range(3):
        minus = np.ones_like(free)
        plus = np.ones_like(free)
        src = [slice(None)] * 3
        dst = [slice(None)] * 3
        src[axis], dst[axis] = slice(None, -1), slice(1, None)
        minus[tuple(dst)] = free[tuple(src)]
        plus[tuple(src)] = free[tuple(dst)]
        out.append((minus, plus))
    return tuple(out)


def _front_surface(occupied: np.ndarray, free_nb, below: int) -> np.ndarray:
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


def visibility(semantics: np.ndarray, sensor: Sensor, free_nb=None) -> np.ndarray:
    """(X, Y, Z) bool: voxels the sensor observes (see the module docstring).

    ``free_nb`` may pass in :func:`_facing_free` of the occupancy when several sensors look
    at the same frame.
    """
    g = _geometry(sensor)
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
    first_hit = np.full(g.n_el * width + 1, np.inf, np.float32)
    np.minimum.at(first_hit, g.base[idx][rep] + row * width + col, g.rng[idx][rep])
    # Fold the doubled azimuth axis; the spare last bin (outside the view) sees nothing.
    grid = first_hit[:-1].reshape(g.n_el, width)
    grid[:, : g.n_az] = np.minimum(grid[:, : g.n_az], grid[:, g.n_az :])
    grid[:, g.n_az :] = grid[:, : g.n_az]
    first_hit[-1] = -np.inf
    seen = (g.rng <= first_hit[g.bin] + VOXEL_SIZE / 2).reshape(GRID_SHAPE)
    seen[..., : GROUND_LAYERS - 1] = False
    return seen


def masks(semantics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mask_lidar, mask_camera) as uint8 0/1: what the roof lidar sees (the z-buffer
    above), and what the six cameras' rays cross up to the first occupied voxel
    (``camera_render.camera_mask``, as Occ3D casts camera rays)."""
    from occtrain.data.synth.camera_render import camera_mask

    lidar = visibility(semantics, LIDAR)
    return lidar.astype(np.uint8), camera_mask(semantics).astype(np.uint8)


@lru_cache(maxsize=1)
def _columns() -> np.ndarray:
    return column_table(GRID_SHAPE[2], GROUND_LAYERS)


def static_semantics(static: StaticMap, pose_xy: np.ndarray, pose_yaw: float) -> np.ndarray:
    """(X, Y, Z) uint8 classes of the static world seen from an ego pose (nearest raster cell)."""
    ix, iy = static.cells(ego_to_global(column_centres(), pose_xy, pose_yaw))
    return _columns()[static.column_key[ix, iy]]


def draw_boxes(sem: np.ndarray, centre: np.ndarray, yaw: np.ndarray, size: np.ndarray, cls: np.ndarray) -> None:
    """Draw oriented boxes standing on the ground into ``sem`` in place (ego frame).

    A column belongs to a box when its centre lies inside the footprint; the column under
    the box centre always does, so small things (cones, pedestrians) never vanish.
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
    centre, c, s, hl, hw, lo_i, span, cls = centre[keep], c[keep], s[keep], hl[keep], hw[keep], lo_i[keep], span[keep], cls[keep]
    lo_k, hi_k = layer_span(np.zeros(int(keep.sum())), size[keep, 2])
    counts = span[:, 0] * span[:, 1]
    rep = np.repeat(np.arange(len(counts)), counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    ix = lo_i[rep, 0] + local // span[rep, 1]
    iy = lo_i[rep, 1] + local % span[rep, 1]
    dx = RANGE_MIN[0] + (ix + 0.5) * VOXEL_SIZE - centre[rep, 0]
    dy = RANGE_MIN[1] + (iy + 0.5) * VOXEL_SIZE - centre[rep, 1]
    inside = (np.abs(c[rep] * dx + s[rep] * dy) <= hl[rep]) & (np.abs(-s[rep] * dx + c[rep] * dy) <= hw[rep])
    own = np.floor((centre - RANGE_MIN[:2]) / VOXEL_SIZE).astype(np.int64)
    inside |= (ix == own[rep, 0]) & (iy == own[rep, 1])
    rep, ix, iy = rep[inside], ix[inside], iy[inside]
    k = np.arange(GRID_SHAPE[2])
    layers = (k >= lo_k[rep, None]) & (k < hi_k[rep, None])
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


def frame_semantics(static: StaticMap, tracks: TrackSet, t: int, pose_xy: np.ndarray, pose_yaw: float) -> np.ndarray:
    """(X, Y, Z) uint8 Occ3D classes of frame ``t`` seen from the ego pose."""
    sem = static_semantics(static, pose_xy, pose_yaw)
    centre = global_to_ego(tracks.xy[:, t], pose_xy, pose_yaw)
    reach = np.hypot(tracks.size[:, 0], tracks.size[:, 1]) / 2
    near = np.all(np.abs(centre) <= -RANGE_MIN[:2] + reach[:, None], axis=1)
    draw_boxes(sem, centre[near], tracks.yaw[near, t] - pose_yaw, tracks.size[near], tracks.cls[near])
    clear_ego(sem)
    return sem
