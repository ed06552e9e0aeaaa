"""The six surround cameras of the synthetic world: ray casting through the voxel grid,
then shading from the world's state.

Geometry is the frame's own occupancy: each pixel's ray walks the grid voxel by voxel
(Amanatides and Woo) from the camera centre and stops at the first occupied voxel, so the
class and depth maps agree with the labels by construction. Cameras and grid are fixed in
the ego frame, so every ray's voxel sequence is computed once per process; a frame is one
gather of its occupancy along those sequences. The ground is a plane under everything:
a ray that reaches it where no sweep labelled it, or beyond the grid, shows the city
map's ground class there; a ray that meets nothing shows the sky.

Appearance comes from the world, not only from the 0.4 m voxels: a colour per class lit by
the sun through the face the ray entered, haze with distance, lane markings painted on the
road at the exact point each ray meets it, and the colour of the traffic light at the top
of each signal pole at the frame's time.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from occtrain.data.cameras import Camera, nuscenes_rig
from occtrain.data.geometry import ego_to_global, rotate_to_ego
from occtrain.data.synth.citymap import SIGNAL_POLE_M, StaticMap
from occtrain.data.synth.grid import GROUND_LAYERS, GROUND_TOP_Z
from occtrain.data.synth.roads import LANE_WIDTH, RoadNetwork, green_left
from occtrain.formats.occ3d import CLASS_INDEX, FREE, GRID_SHAPE, RANGE_MIN, VOXEL_SIZE

#: What each class looks like to a camera (Occ3D class order): asphalt, concrete, grass,
#: brick and foliage rather than the label palette, so a camera model learns appearance.
CAMERA_COLOURS = np.array(
    [
        (120, 110, 100),  # others
        (205, 205, 195),  # barrier
        (170, 40, 40),  # bicycle
        (225, 185, 40),  # bus
        (45, 75, 140),  # car
        (230, 150, 25),  # construction_vehicle
        (55, 55, 60),  # motorcycle
        (205, 125, 95),  # pedestrian
        (255, 110, 20),  # traffic_cone
        (150, 150, 160),  # trailer
        (195, 195, 205),  # truck
        (82, 82, 88),  # driveable_surface
        (140, 128, 115),  # other_flat
        (172, 168, 160),  # sidewalk
        (118, 142, 78),  # terrain
        (160, 118, 96),  # manmade
        (52, 112, 46),  # vegetation
    ],
    np.float64,
)
SKY_HORIZON = np.array([196, 214, 232], np.float64)
SKY_ZENITH = np.array([92, 136, 204], np.float64)
#: Sun direction in the global frame (high, from the south-west); shading rotates it into the ego frame.
SUN_GLOBAL = np.array([0.35, 0.45, 0.82]) / np.linalg.norm([0.35, 0.45, 0.82])
#: Distance over which haze halves the contrast.
HAZE_M = 110.0
#: Signal heads: the top this many metres of a pole at a crossing show the light's colour.
SIGNAL_HEAD_M = 1.2
LIGHT_COLOURS = {"red": (235, 40, 30), "amber": (250, 180, 20), "green": (40, 220, 80)}
#: Seconds of green left below which a light shows amber.
AMBER_S = 3.0
MARKING_WHITE = np.array([240, 240, 235], np.float64)
MARKING_YELLOW = np.array([235, 200, 40], np.float64)
#: Half widths of painted lines (m) and the dash pattern of lane dividers (m painted, m period).
LINE_HALF = 0.08
DASH = (3.0, 9.0)

DRIVEABLE = CLASS_INDEX["driveable_surface"]
MANMADE = CLASS_INDEX["manmade"]


@dataclass(frozen=True)
class _Rays:
    """Every pixel ray of one camera and the voxels it crosses, concatenated ray by ray."""

    origin: np.ndarray  # (3,) ego frame
    dirs: np.ndarray  # (R, 3) unit directions
    cos: np.ndarray  # (R,) cosine to the optical axis (camera-z depth = range x cos)
    voxel: np.ndarray  # (E,) int32 flat voxel index
    t: np.ndarray  # (E,) float32 distance at which the ray enters the voxel
    axis: np.ndarray  # (E,) int8 axis of the face it enters through (-1: the starting voxel)
    ray: np.ndarray  # (E,) int32 the ray of each entry (non-decreasing)
    starts: np.ndarray  # (R,) index of each ray's first entry
    ground: np.ndarray  # (E,) bool: the entry is in the ground layer (the ray meets the ground there)

    @property
    def ends(self) -> np.ndarray:
        """(R,) index of each ray's last entry."""
        return np.r_[self.starts[1:], len(self.voxel)] - 1


def _traverse(origin: np.ndarray, dirs: np.ndarray, cos: np.ndarray) -> _Rays:
    """Walk every ray through the grid until it leaves it or enters a ground layer."""
    lo, n = RANGE_MIN, np.array(GRID_SHAPE)
    rays = len(dirs)
    idx = np.floor((origin - lo) / VOXEL_SIZE).astype(np.int64)[None].repeat(rays, 0)
    step = np.where(dirs >= 0, 1, -1)
    with np.errstate(divide="ignore"):
        inv = np.where(np.abs(dirs) < 1e-12, np.inf, 1.0 / np.abs(dirs))
    nxt = lo + (idx + (step > 0)) * VOXEL_SIZE
    t_max = np.where(np.isinf(inv), np.inf, (nxt - origin) * np.where(dirs >= 0, 1, -1) * inv)
    t_delta = VOXEL_SIZE * inv
    t_now = np.zeros(rays)
    axis_now = np.full(rays, -1, np.int64)
    live = np.arange(rays)
    parts: list[tuple[np.ndarray, ...]] = []
    while len(live):
        i = idx[live]
        flat = (i[:, 0] * n[1] + i[:, 1]) * n[2] + i[:, 2]
        parts.append((live, flat, t_now[live], axis_now[live]))
        live = live[i[:, 2] >= GROUND_LAYERS]  # a ground layer is always occupied: the ray ends there
        if not len(live):
            break
        tm = t_max[live]
        ax = np.argmin(tm, axis=1)
        r = np.arange(len(live))
        t_now[live] = tm[r, ax]
        axis_now[live] = ax
        idx[live, ax] += step[live, ax]
        t_max[live, ax] += t_delta[live, ax]
        j = idx[live, ax]
        inside = (j >= 0) & (j < n[ax])
        live = live[inside]
    ray = np.concatenate([p[0] for p in parts]).astype(np.int32)
    order = np.argsort(ray, kind="stable")  # parts are in step order: stable keeps each ray's order
    return _Rays(
        origin=origin,
        dirs=dirs,
        cos=cos,
        voxel=np.concatenate([p[1] for p in parts])[order].astype(np.int32),
        t=np.concatenate([p[2] for p in parts])[order].astype(np.float32),
        axis=np.concatenate([p[3] for p in parts])[order].astype(np.int8),
        ray=ray[order],
        starts=np.searchsorted(ray[order], np.arange(rays)).astype(np.int64),
        ground=(np.concatenate([p[1] for p in parts])[order] % n[2] < GROUND_LAYERS),
    )


@lru_cache(maxsize=4)
def camera_rays(height: int, width: int) -> tuple[tuple[Camera, _Rays], ...]:
    """The rig at ``height`` x ``width`` with each camera's traversal (computed once)."""
    out = []
    for cam in nuscenes_rig(height, width):
        dirs, cos = cam.pixel_rays()
        out.append((cam, _traverse(cam.centre, dirs.reshape(-1, 3), cos.reshape(-1))))
    return tuple(out)


@dataclass
class CameraView:
    """One rendered camera image with its per-pixel class and depth."""

    image: np.ndarray  # (H, W, 3) uint8
    classes: np.ndarray  # (H, W) uint8 Occ3D class, FREE where the ray meets nothing (sky)
    depth: np.ndarray  # (H, W) float32 camera-z metres, 0 for sky
    in_grid: np.ndarray  # (H, W) bool: the surface is a voxel of the grid (not ground or sky beyond)
    first_voxel: np.ndarray  # (H, W) int64 flat index of that voxel, -1 elsewhere


@dataclass(frozen=True)
class FrameWorld:
    """What shading needs of the world at one frame besides its occupancy."""

    static: StaticMap
    net: RoadNetwork
    pose_xy: np.ndarray
    pose_yaw: float
    time_s: float


def render_camera(cam: Camera, rays: _Rays, semantics: np.ndarray, world: FrameWorld) -> CameraView:
    """Cast ``cam``'s rays through ``semantics`` (X, Y, Z) and shade what they meet."""
    flat = semantics.reshape(-1)
    first = _first_hits(rays, flat != FREE)
    first = first[flat[rays.voxel[first]] != FREE]  # the ground plane, where unlabelled, is shaded below
    n = len(rays.dirs)
    cls = np.full(n, FREE, np.uint8)
    rng = np.zeros(n)
    axis = np.full(n, 2, np.int64)
    voxel = np.full(n, -1, np.int64)
    hit_rays = rays.ray[first]
    cls[hit_rays] = flat[rays.voxel[first]]
    rng[hit_rays] = rays.t[first]
    axis[hit_rays] = np.where(rays.axis[first] < 0, 2, rays.axis[first])
    voxel[hit_rays] = rays.voxel[first]
    in_grid = voxel >= 0

    # Beyond the grid: the ground plane (its class from the city map) or the sky.
    down = (~in_grid) & (rays.dirs[:, 2] < -1e-6)
    t_ground = (GROUND_TOP_Z - rays.origin[2]) / np.where(down, rays.dirs[:, 2], -1.0)
    rng[down] = t_ground[down]
    points = rays.origin + rays.dirs * rng[:, None]
    if down.any():
        gxy = ego_to_global(points[down, :2], world.pose_xy, world.pose_yaw)
        ix, iy = world.static.cells(gxy)
        cls[down] = world.static.ground[ix, iy]
    surface = in_grid | down

    colour = _shade(cls, axis, rays, rng, surface, points, world)
    depth = np.where(surface, rng * rays.cos, 0.0).astype(np.float32)
    shape = (cam.height, cam.width)
    return CameraView(
        colour.reshape(*shape, 3),
        cls.reshape(shape),
        depth.reshape(shape),
        in_grid.reshape(shape),
        voxel.reshape(shape),
    )


def _shade(cls, axis, rays: _Rays, rng, surface, points, world: FrameWorld) -> np.ndarray:
    base = CAMERA_COLOURS[np.minimum(cls, len(CAMERA_COLOURS) - 1)]
    sun = np.r_[rotate_to_ego(SUN_GLOBAL[:2], world.pose_yaw), SUN_GLOBAL[2]]
    # The face the ray entered through faces back along the ray on that axis.
    normal = np.zeros((len(cls), 3))
    normal[np.arange(len(cls)), axis] = -np.sign(rays.dirs[np.arange(len(cls)), axis])
    light = 0.55 + 0.45 * np.clip(normal @ sun, 0.0, 1.0)
    colour = base * light[:, None]

    ground_hit = surface & (cls == DRIVEABLE) & (axis == 2)  # met from above: the road's top
    if ground_hit.any():
        gxy = ego_to_global(points[ground_hit, :2], world.pose_xy, world.pose_yaw)
        paint = lane_markings(world.net, gxy)
        painted = paint > 0
        rows = np.flatnonzero(ground_hit)[painted]
        colour[rows] = np.where((paint[painted] == 2)[:, None], MARKING_YELLOW, MARKING_WHITE) * light[rows, None]

    heads = surface & (cls == MANMADE) & (points[:, 2] > GROUND_TOP_Z + SIGNAL_POLE_M - SIGNAL_HEAD_M)
    if heads.any() and len(world.static.signals):
        gxy = ego_to_global(points[heads, :2], world.pose_xy, world.pose_yaw)
        state = signal_colours(world.static, gxy, world.time_s)
        lit = state >= 0
        rows = np.flatnonzero(heads)[lit]
        colour[rows] = np.asarray(list(LIGHT_COLOURS.values()), np.float64)[state[lit]]

    haze = 1.0 - np.exp(-rng / HAZE_M * np.log(2))
    elevation = np.clip(rays.dirs[:, 2], 0.0, 1.0) ** 0.6
    sky = SKY_HORIZON * (1 - elevation[:, None]) + SKY_ZENITH * elevation[:, None]
    colour = colour * (1 - haze[:, None]) + SKY_HORIZON * haze[:, None]
    colour = np.where(surface[:, None], colour, sky)
    return np.clip(colour, 0, 255).astype(np.uint8)


def lane_markings(net: RoadNetwork, xy: np.ndarray) -> np.ndarray:
    """Per global point (N, 2): 0 no paint, 1 white (lane dividers, edge lines), 2 yellow
    (centre line or median edges). Nothing is painted inside crossings."""
    out = np.zeros(len(xy), np.int8)
    for axis in (0, 1):
        roads, cross = net.roads[axis], net.roads[1 - axis]
        across = xy[:, 1 - axis]  # a road along x is crossed along y
        along = xy[:, axis]
        centres = np.array([r.centre for r in roads])
        near = np.argmin(np.abs(across[:, None] - centres[None]), axis=1) if len(centres) else np.zeros(len(xy), int)
        c_centres = np.array([r.centre for r in cross])
        c_half = np.array([r.half_width for r in cross]) + net.sidewalk
        in_crossing = (np.abs(along[:, None] - c_centres[None]) < c_half[None]).any(1)
        for k, road in enumerate(roads):
            rows = np.flatnonzero((near == k) & ~in_crossing)
            if not len(rows):
                continue
            off = np.abs(across[rows] - road.centre)
            half_median = road.median / 2
            yellow = np.abs(off - half_median) < LINE_HALF if road.median else off < LINE_HALF
            white = np.abs(off - (half_median + road.lanes * LANE_WIDTH)) < LINE_HALF
            dashed = np.mod(along[rows], DASH[1]) < DASH[0]
            for lane in range(1, road.lanes):
                white |= (np.abs(off - (half_median + lane * LANE_WIDTH)) < LINE_HALF) & dashed
            out[rows] = np.where(yellow, 2, np.where(white, 1, out[rows]))
    return out


def signal_colours(static: StaticMap, xy: np.ndarray, time_s: float) -> np.ndarray:
    """Index into LIGHT_COLOURS (red, amber, green) of the signal head at each global point,
    -1 where the point is on no signal pole."""
    sig = static.signals  # (K, 9): x, y, axis, light parameters (6)
    d = np.abs(xy[:, None, :] - sig[None, :, :2]).max(-1)
    nearest = np.argmin(d, axis=1)
    on_pole = d[np.arange(len(xy)), nearest] <= 0.45
    left = green_left(sig[nearest, 3:9], sig[nearest, 2].astype(int), time_s)
    state = np.where(left < 0, 0, np.where(left < AMBER_S, 1, 2))
    return np.where(on_pole, state, -1)


#: Image size of the rays that decide ``mask_camera``: the default camera resolution (a ray
#: every ~0.5 degrees: under a voxel apart up to 45 m), fixed so the labels do not depend on
#: the resolution images are rendered at; surfaces met at a grazing angle are completed by
#: :func:`_with_faces_in_view`.
MASK_RAYS = (72, 128)


def _first_hits(rays: _Rays, occupied: np.ndarray) -> np.ndarray:
    """Index of the first entry of each ray that meets something (an occupied voxel or the
    ground layer), for the rays that do, in ray order."""
    entry = np.flatnonzero(occupied[rays.voxel] | rays.ground)
    return entry[np.r_[True, rays.ray[entry][1:] != rays.ray[entry][:-1]]] if len(entry) else entry


@lru_cache(maxsize=1)
def voxels_in_view() -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...]:
    """Per camera of the mask rig: the voxels whose centre it images (flat index), the
    pixel of each centre and its distance from the camera (computed once per process)."""
    centres = np.stack(
        np.meshgrid(*(RANGE_MIN[a] + (np.arange(GRID_SHAPE[a]) + 0.5) * VOXEL_SIZE for a in range(3)), indexing="ij"),
        -1,
    )
    centres = centres.reshape(-1, 3)
    out = []
    for cam, _ in camera_rays(*MASK_RAYS):
        uv, _, inside = cam.project(centres)
        idx = np.flatnonzero(inside)
        pix = np.floor(uv[idx, 1]).astype(np.int64) * cam.width + np.floor(uv[idx, 0]).astype(np.int64)
        out.append((idx, pix, np.linalg.norm(centres[idx] - cam.centre, axis=1).astype(np.float32)))
    return tuple(out)


#: A voxel's centre lies at most half its diagonal beyond the point where a ray enters it.
_HALF_DIAGONAL = VOXEL_SIZE * np.sqrt(3) / 2


def camera_mask(semantics: np.ndarray, among: np.ndarray | None = None) -> np.ndarray:
    """(X, Y, Z) bool: voxels some camera ray crosses up to and including the surface it
    meets. A ray that meets nothing in the grid counts only when it looks down (it meets
    the ground beyond); one into the sky, like a lidar ray without return, shows no depth.

    Each voxel is judged by the ray through the pixel its centre falls in (the surface a
    ray meets always counts); ``among`` (bool, X x Y x Z) limits the judging to those
    voxels, as Occ3D limits the camera mask to what the lidar observed.
    """
    occupied = semantics.reshape(-1) != FREE
    seen = np.zeros(occupied.shape, bool)
    for (_, rays), (idx, pix, rng) in zip(camera_rays(*MASK_RAYS), voxels_in_view()):
        first = _first_hits(rays, occupied)
        # How far each pixel's ray observes: to the surface it meets, everything when it
        # looks down and leaves the grid, nothing when it goes into the sky.
        reach = np.where(rays.dirs[:, 2] < -1e-6, np.inf, -np.inf).astype(np.float32)
        reach[rays.ray[first]] = rays.t[first]
        seen[rays.voxel[first]] = True
        if among is not None:
            keep = among.reshape(-1)[idx]
            idx, pix, rng = idx[keep], pix[keep], rng[keep]
        slack = np.where(occupied[idx], _HALF_DIAGONAL, 0.0)
        seen[idx[rng <= reach[pix] + slack]] = True
    return _with_faces_in_view(seen.reshape(semantics.shape), semantics != FREE)


def _with_faces_in_view(seen: np.ndarray, occupied: np.ndarray) -> np.ndarray:
    """Add the occupied voxels whose face toward the cameras borders free space a ray crossed.

    Rays sample a surface met at a grazing angle sparsely (on the road, pixel rows lie
    metres apart), so a voxel between two sampled ones is missed though its face is in
    view: the free voxel in front of that face was crossed, so the face is seen.
    """
    centre = np.mean([cam.centre for cam, _ in camera_rays(*MASK_RAYS)], axis=0)
    toward = np.floor((centre - RANGE_MIN) / VOXEL_SIZE).astype(int)  # the cameras' voxel
    free_seen = seen & ~occupied
    out = seen.copy()
    for axis in range(3):
        n = occupied.shape[axis]
        front = np.zeros_like(seen)
        lo, hi = [slice(None)] * 3, [slice(None)] * 3
        # Beyond the cameras along this axis the face toward them is on the lower side.
        lo[axis], hi[axis] = slice(toward[axis] + 1, n), slice(toward[axis], n - 1)
        front[tuple(lo)] = free_seen[tuple(hi)]
        lo[axis], hi[axis] = slice(0, toward[axis]), slice(1, toward[axis] + 1)
        front[tuple(lo)] = free_seen[tuple(hi)]
        out |= occupied & front
    return out


def render_cameras(semantics: np.ndarray, world: FrameWorld, height: int, width: int) -> list[CameraView]:
    """The six views of one frame, in CAMERA_NAMES order."""
    return [render_camera(cam, rays, semantics, world) for cam, rays in camera_rays(height, width)]


__all__ = [
    "CAMERA_COLOURS",
    "CameraView",
    "FrameWorld",
    "camera_mask",
    "camera_rays",
    "lane_markings",
    "render_camera",
    "render_cameras",
]
