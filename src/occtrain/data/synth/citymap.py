"""The static city around a route: a global column raster plus the static boxed objects.

Every block between roads is a rounded rectangle ringed by sidewalk. Blocks hold
buildings set back behind grass, plazas, hedges or fences, street trees, lamp posts, bins and bike racks, and
sometimes a parking lot or a fenced construction site at their frontage; some blocks are
parks. Roads get medians (other_flat, with hedges, trees or jersey barriers) and parking
strips with parked vehicles. The raster stores, per 0.2 m cell, the ground class and one
vertical segment (class, layer range) of whatever stands there; boxed objects (vehicles,
cycles, cones, barriers, standing pedestrians) are kept as tracks and drawn per frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from occtrain.data.synth.catalog import CYCLE_CLASSES, KINDS, TrackSet, pick
from occtrain.data.synth.grid import ABOVE_GRID, layer_span
from occtrain.data.synth.roads import CURB_RADIUS, HEADINGS, MEDIAN_END, LaneState, Road, RoadNetwork, right_of
from occtrain.formats.occ3d import CLASS_INDEX, FREE

#: Cell size (m) of the global static raster; finer than a voxel so rotated sampling is clean.
RASTER_RES = 0.2
#: Height of the signal poles at crossings (m); cameras light their top.
SIGNAL_POLE_M = 5.0
#: Height of the lamp posts between the street trees (m).
LAMP_POST_M = 7.0

DRIVEABLE = CLASS_INDEX["driveable_surface"]
OTHER_FLAT = CLASS_INDEX["other_flat"]
SIDEWALK = CLASS_INDEX["sidewalk"]
TERRAIN = CLASS_INDEX["terrain"]
MANMADE = CLASS_INDEX["manmade"]
VEGETATION = CLASS_INDEX["vegetation"]
OTHERS = CLASS_INDEX["others"]

#: Parked vehicles in parking strips (kind, weight).
STRIP_PARKING = (("car", 0.82), ("truck", 0.06), ("motorcycle", 0.07), ("trailer", 0.05))
#: Vehicles in a parking lot's stalls and along its back row.
LOT_STALLS = (("car", 0.92), ("motorcycle", 0.08))
LOT_LONG = (("truck", 0.4), ("trailer", 0.35), ("bus", 0.25))


#: Number of distinct layer bounds in a column code: 0..16, and ABOVE_GRID (17).
_BOUNDS = ABOVE_GRID + 1
#: Cells (0.2 m) within this many of a different standing thing are its surface; beyond
#: it a column is inside the thing. Three cells (0.6 m) so that voxel centres, sampled
#: 0.4 m apart at any rotation, always find a wall (a band needs 0.4 x sqrt(2) m).
SHELL_CELLS = 3


def column_key(ground, cls, lo, hi, shell) -> np.ndarray:
    """One integer per column from its ground class, standing class, layer range and
    whether the column is on the standing thing's surface (``shell``) or inside it."""
    g, c = np.asarray(ground, np.int32), np.asarray(cls, np.int32)
    key = ((g * (FREE + 1) + c) * _BOUNDS + np.asarray(lo, np.int32)) * _BOUNDS + np.asarray(hi, np.int32)
    return key * 2 + np.asarray(shell, np.int32)


def column_table(layers: int, ground_layers: int) -> np.ndarray:
    """(codes, layers) uint8: the voxel column of every possible column code.

    Occ3D labels surfaces, so a standing thing is its hull: a surface column holds the
    whole segment; a column inside it only its top (a roof, a crown; absent when the top is
    above the grid) and, when it floats, its underside (a crown seen from below). The ground
    is one layer, and is absent inside anything standing on it (no sensor reaches it there).
    """
    code = np.arange(2 * (FREE + 1) ** 2 * _BOUNDS**2)
    shell = (code % 2).astype(bool)[:, None]
    rest = code // 2
    hi = (rest % _BOUNDS)[:, None]
    lo = (rest // _BOUNDS % _BOUNDS)[:, None]
    cls = rest // _BOUNDS**2 % (FREE + 1)
    ground = rest // (_BOUNDS**2 * (FREE + 1))
    k = np.arange(layers)[None]
    solid = (k >= lo) & (k < hi)
    floats = lo > ground_layers
    # Foliage is porous: a lidar returns from inside a crown or a hedge, so vegetation is
    # labelled through, not as a hull.
    hull = shell | (k == hi - 1) | ((k == lo) & floats) | (cls == VEGETATION)[:, None]
    table = np.where(solid & hull, cls[:, None], FREE).astype(np.uint8)
    covered = (cls[:, None] != FREE) & ~shell & ~floats
    table[:, :ground_layers] = FREE
    table[:, ground_layers - 1] = np.where(covered[:, 0], FREE, ground)
    return table


def _window_extremes(a: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
    """Minimum and maximum of ``a`` over the (2r+1) x (2r+1) window around each cell."""
    from numpy.lib.stride_tricks import sliding_window_view

    def run(x: np.ndarray, fn, axis: int) -> np.ndarray:
        pad = [(0, 0), (0, 0)]
        pad[axis] = (r, r)
        return fn(sliding_window_view(np.pad(x, pad, mode="edge"), 2 * r + 1, axis=axis), axis=-1)

    return run(run(a, np.min, 0), np.min, 1), run(run(a, np.max, 0), np.max, 1)


@dataclass
class StaticMap:
    """Global column raster: ground class and one standing segment per cell.

    ``cls`` is FREE where nothing stands; otherwise layers [lo, hi) of the column hold it.
    ``observed`` ((NX, NY, layers) bool, set by ``raster.observe_static``) marks the cells
    and layers a sensor saw over the scene: Occ3D labels only what the scene's sweeps hit.
    """

    origin: np.ndarray  # (2,) global xy of the raster's lower corner
    ground: np.ndarray  # (NX, NY) uint8
    cls: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    #: Signal poles at crossings: (K, 9) rows of global x, y, the axis of the traffic the
    #: head faces, and that crossing's light parameters (``RoadNetwork.light``).
    signals: np.ndarray = field(default_factory=lambda: np.zeros((0, 9)))
    observed: np.ndarray | None = None

    @cached_property
    def shell(self) -> np.ndarray:
        """(NX, NY) bool: the cell is within SHELL_CELLS of a different standing thing (or
        of where nothing stands), so it is on its thing's surface."""
        seg = (self.cls.astype(np.int32) * _BOUNDS + self.lo) * _BOUNDS + self.hi
        seg = np.where(self.cls == FREE, -1, seg)
        lo, hi = _window_extremes(seg, SHELL_CELLS)
        return (lo != seg) | (hi != seg)

    @cached_property
    def column_key(self) -> np.ndarray:
        """(NX, NY) int32 code of each cell's whole column; see :func:`column_key`."""
        return column_key(self.ground, self.cls, self.lo, self.hi, self.shell)

    def cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest raster cell (clipped to the raster) of global points ``xy`` (..., 2)."""
        idx = np.floor((xy - self.origin) / RASTER_RES).astype(np.int64)
        return np.clip(idx[..., 0], 0, self.ground.shape[0] - 1), np.clip(idx[..., 1], 0, self.ground.shape[1] - 1)


@dataclass
class _Placed:
    """A static boxed object before it becomes a track."""

    kind: str
    xy: np.ndarray
    yaw: float
    size: np.ndarray
    parked: bool
    rider: int


def _inward(side: int) -> np.ndarray:
    """Unit vector into a block from its side (0 south, 1 north, 2 west, 3 east)."""
    return np.array([[0.0, 1.0], [0.0, -1.0], [1.0, 0.0], [-1.0, 0.0]])[side]


class CityPainter:
    """Paints the static city of one scene inside a rectangular region of the global plane."""

    def __init__(self, net: RoadNetwork, lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator):
        self.net = net
        self.rng = rng
        origin = np.floor(lo / RASTER_RES) * RASTER_RES
        shape = tuple(np.ceil((hi - origin) / RASTER_RES).astype(int))
        self.map = StaticMap(
            origin,
            np.full(shape, DRIVEABLE, np.uint8),
            np.full(shape, FREE, np.uint8),
            np.zeros(shape, np.uint8),
            np.zeros(shape, np.uint8),
        )
        self.lo, self.hi = origin, origin + np.array(shape) * RASTER_RES
        self.objects: list[_Placed] = []

    # ------------------------------------------------------------ primitives

    def _window(self, x0: float, x1: float, y0: float, y1: float):
        i0, j0 = np.floor((np.array([x0, y0]) - self.lo) / RASTER_RES).astype(int)
        i1, j1 = np.ceil((np.array([x1, y1]) - self.lo) / RASTER_RES).astype(int)
        nx, ny = self.map.ground.shape
        i0, i1, j0, j1 = max(i0, 0), min(i1, nx), max(j0, 0), min(j1, ny)
        if i0 >= i1 or j0 >= j1:
            return None
        xs = self.lo[0] + (np.arange(i0, i1) + 0.5) * RASTER_RES
        ys = self.lo[1] + (np.arange(j0, j1) + 0.5) * RASTER_RES
        return (slice(i0, i1), slice(j0, j1)), xs[:, None], ys[None, :]

    def _paint(self, win, mask: np.ndarray | None, ground: int | None, solid: tuple[int, float, float] | None):
        sl = win[0]
        m = np.ones(self.map.ground[sl].shape, bool) if mask is None else mask
        if ground is not None:
            self.map.ground[sl][m] = ground
        if solid is not None:
            cls, bottom, top = solid
            lo, hi = layer_span(bottom, top)
            self.map.cls[sl][m] = cls
            self.map.lo[sl][m] = lo
            self.map.hi[sl][m] = hi

    def rect(self, x0, x1, y0, y1, ground: int | None = None, solid: tuple[int, float, float] | None = None):
        """Fill an axis-aligned rectangle (global metres)."""
        win = self._window(min(x0, x1), max(x0, x1), min(y0, y1), max(y0, y1))
        if win is not None:
            self._paint(win, None, ground, solid)

    def clear(self, x0, x1, y0, y1, ground: int):
        """Remove whatever stands in a rectangle (raster and placed objects), give it a new ground."""
        x0, x1, y0, y1 = min(x0, x1), max(x0, x1), min(y0, y1), max(y0, y1)
        win = self._window(x0, x1, y0, y1)
        if win is not None:
            self.map.ground[win[0]] = ground
            self.map.cls[win[0]] = FREE
        self.objects = [o for o in self.objects if not (x0 <= o.xy[0] <= x1 and y0 <= o.xy[1] <= y1)]

    def disc(self, cx, cy, r, ground: int | None = None, solid: tuple[int, float, float] | None = None):
        win = self._window(cx - r, cx + r, cy - r, cy + r)
        if win is not None:
            self._paint(win, (win[1] - cx) ** 2 + (win[2] - cy) ** 2 <= r * r, ground, solid)

    def tree(self, x: float, y: float):
        """A trunk with a round canopy starting 1.5-2.8 m up."""
        r = self.rng.uniform(1.4, 3.0)
        base = self.rng.uniform(1.5, 2.8)
        self.disc(x, y, r, solid=(VEGETATION, base, base + self.rng.uniform(2.5, 6.0)))
        t = self.rng.uniform(0.2, 0.3)
        self.rect(x - t, x + t, y - t, y + t, solid=(VEGETATION, 0.0, base + 0.4))

    def place(self, kind: str, xy, yaw: float, parked: bool = True) -> None:
        """Add a static boxed object (drawn per frame, annotated with a box); static cycles have no rider."""
        if np.all(xy >= self.lo) and np.all(xy <= self.hi):
            size = KINDS[kind].sample_size(self.rng)
            rider = 0 if KINDS[kind].cls in CYCLE_CLASSES else -1
            self.objects.append(_Placed(kind, np.asarray(xy, float), float(yaw), size, parked, rider))

    def tracks(self, frames: int) -> TrackSet:
        """The placed objects as motionless tracks over ``frames`` frames."""
        n = len(self.objects)
        xy = np.array([o.xy for o in self.objects]).reshape(n, 1, 2)
        yaw = np.array([o.yaw for o in self.objects]).reshape(n, 1)
        return TrackSet(
            cls=np.array([KINDS[o.kind].cls for o in self.objects], dtype=np.int64),
            size=np.array([o.size for o in self.objects]).reshape(n, 3),
            xy=np.repeat(xy, frames, axis=1),
            yaw=np.repeat(yaw, frames, axis=1),
            speed=np.zeros((n, frames)),
            parked=np.array([o.parked for o in self.objects], bool),
            rider=np.array([o.rider for o in self.objects], dtype=np.int64),
        )

    # ------------------------------------------------------------ blocks

    def blocks(self) -> list[np.ndarray]:
        """[x0, x1, y0, y1] of every block (the land between neighbouring roads) touching the region."""
        xr, yr = self.net.roads
        out = []
        for i in range(len(yr) - 1):
            x0, x1 = yr[i].centre + yr[i].half_width, yr[i + 1].centre - yr[i + 1].half_width
            if x1 < self.lo[0] or x0 > self.hi[0]:
                continue
            for j in range(len(xr) - 1):
                y0, y1 = xr[j].centre + xr[j].half_width, xr[j + 1].centre - xr[j + 1].half_width
                if y1 < self.lo[1] or y0 > self.hi[1]:
                    continue
                out.append(np.array([x0, x1, y0, y1]))
        return out

    def signal_poles(self, box: np.ndarray) -> None:
        """A signal pole (manmade) on the sidewalk at each corner of a block, where two roads
        cross; the heads at its top face traffic along x at two opposite corners, along y at
        the other two. Cameras show the light's colour; occupancy shows only the pole."""
        x0, x1, y0, y1 = box
        w = self.net.sidewalk
        inset = CURB_RADIUS - (CURB_RADIUS - w / 2) / np.sqrt(2)  # the middle of the rounded corner's sidewalk
        rows = []
        for sx, cx in ((1, x0), (-1, x1)):
            for sy, cy in ((1, y0), (-1, y1)):
                x, y = cx + sx * inset, cy + sy * inset
                light = self.net.light(self.net.nearest_road(0, cy - sy), self.net.nearest_road(1, cx - sx))
                self.rect(x - 0.2, x + 0.2, y - 0.2, y + 0.2, solid=(MANMADE, 0.0, SIGNAL_POLE_M))
                rows.append([x, y, 0.0 if sx == sy else 1.0, *light])
        self.map.signals = np.concatenate([self.map.signals, np.array(rows)])

    def block_ground(self, box: np.ndarray, interior: int) -> None:
        """Rounded-corner block: sidewalk ring of the network's width around ``interior`` ground."""
        x0, x1, y0, y1 = box
        win = self._window(x0, x1, y0, y1)
        if win is None:
            return
        _, xs, ys = win
        cx, cy, hx, hy = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 2, (y1 - y0) / 2
        qx = np.abs(xs - cx) - (hx - CURB_RADIUS)
        qy = np.abs(ys - cy) - (hy - CURB_RADIUS)
        sdf = np.hypot(np.maximum(qx, 0), np.maximum(qy, 0)) + np.minimum(np.maximum(qx, qy), 0) - CURB_RADIUS
        self._paint(win, sdf <= -self.net.sidewalk, interior, None)
        self._paint(win, (sdf <= 0) & (sdf > -self.net.sidewalk), SIDEWALK, None)

    def building_block(self, box: np.ndarray, bus_stop: bool = False) -> None:
        """Buildings behind a setback strip, street trees, hedges, bins and bike racks.

        A block with a bus stop keeps a deep setback free of hedges and racks for the shelter.
        """
        rng, w = self.rng, self.net.sidewalk
        x0, x1, y0, y1 = box + np.array([w, -w, w, -w])
        strip = int(rng.choice([TERRAIN, SIDEWALK, OTHER_FLAT], p=[0.65, 0.3, 0.05]))
        setback = rng.uniform(4.5, 6.0) if bus_stop else rng.uniform(1.0, 4.0)
        self.rect(x0, x1, y0, y1, ground=strip)
        bx0, bx1, by0, by1 = x0 + setback, x1 - setback, y0 + setback, y1 - setback
        if bx1 - bx0 < 6 or by1 - by0 < 6:
            return
        self.rect(bx0, bx1, by0, by1, ground=TERRAIN)
        depth = rng.uniform(9.0, 16.0)
        # A ring of buildings; the courtyard keeps a few trees.
        for side in range(4):
            horizontal = side < 2
            a0, a1 = (bx0, bx1) if horizontal else (by0 + depth, by1 - depth)
            a = a0
            while a < a1 - 4:
                ln = min(rng.uniform(10.0, 28.0), a1 - a)
                h = rng.uniform(6.0, 30.0)
                if horizontal:
                    yy = (by0, min(by0 + depth, by1)) if side == 0 else (max(by1 - depth, by0), by1)
                    self.rect(a, a + ln, *yy, ground=SIDEWALK, solid=(MANMADE, 0.0, h))
                else:
                    xx = (bx0, min(bx0 + depth, bx1)) if side == 2 else (max(bx1 - depth, bx0), bx1)
                    self.rect(*xx, a, a + ln, ground=SIDEWALK, solid=(MANMADE, 0.0, h))
                a += ln + (rng.uniform(2.0, 5.0) if rng.random() < 0.4 else 0.0)
        if bx1 - bx0 > 2 * depth + 8 and by1 - by0 > 2 * depth + 8:
            for _ in range(int(rng.integers(0, 4))):
                self.tree(rng.uniform(bx0 + depth + 3, bx1 - depth - 3), rng.uniform(by0 + depth + 3, by1 - depth - 3))
        edge = str(rng.choice(["hedge", "fence", "open"], p=[0.3, 0.45, 0.25]))
        for side in range(4):
            self._frontage(box, side, furnished=not bus_stop and setback > 3.0, edge="open" if bus_stop else edge)

    def _frontage(self, box: np.ndarray, side: int, furnished: bool, edge: str) -> None:
        """Street trees, lamp posts and bins at the kerb along one side of a block; behind the
        sidewalk a hedge, a fence or wall (``edge``) or nothing, and (``furnished``: the setback
        has room, nothing closes it) maybe a bike rack."""
        rng, w = self.rng, self.net.sidewalk
        x0, x1, y0, y1 = box
        # Side 0: south (y0), 1: north (y1), 2: west (x0), 3: east (x1); "out" points to the road.
        a0, a1 = (x0, x1) if side < 2 else (y0, y1)
        # A known bug, kept as is until the world version is bumped (fixing it changes every
        # synthesized world): this coordinate used to overwrite the ``edge`` argument, so the
        # ``edge == "hedge"`` / ``"fence"`` / ``"open"`` tests below compare it with a string
        # and never fire. They read ``road_edge`` to keep exactly that.
        road_edge = (y0, y1, x0, x1)[side]
        out = -1.0 if side in (0, 2) else 1.0

        def at(a: float, depth: float) -> np.ndarray:
            """Point ``depth`` metres inside the block from the road edge, at along-side ``a``."""
            p = road_edge - out * depth
            return np.array([a, p]) if side < 2 else np.array([p, a])

        a = a0 + CURB_RADIUS + rng.uniform(2, 8)
        while a < a1 - CURB_RADIUS - 2:
            x, y = at(a, 0.55)
            if rng.random() < 0.8:
                self.tree(x, y)
            else:
                self.rect(x - 0.15, x + 0.15, y - 0.15, y + 0.15, solid=(MANMADE, 0.0, LAMP_POST_M))
            a += rng.uniform(6.0, 10.0)
        if road_edge == "hedge":
            p0, p1 = at(a0 + w + 1, w + 0.2), at(a1 - w - 1, w + 1.0)
            self.rect(p0[0], p1[0], p0[1], p1[1], solid=(VEGETATION, 0.0, rng.uniform(1.0, 2.0)))
        elif road_edge == "fence":
            p0, p1 = at(a0 + w + 1, w + 0.2), at(a1 - w - 1, w + 0.5)
            self.rect(p0[0], p1[0], p0[1], p1[1], solid=(MANMADE, 0.0, rng.uniform(1.2, 2.2)))
        for a in rng.uniform(a0 + 8, a1 - 8, size=int(rng.integers(0, 3))):
            c = at(a, 0.5)
            self.rect(c[0] - 0.3, c[0] + 0.3, c[1] - 0.3, c[1] + 0.3, solid=(OTHERS, 0.0, rng.uniform(0.9, 1.3)))
        if furnished and road_edge == "open" and rng.random() < 0.5:
            self.bike_rack(side, at(rng.uniform(a0 + 12, a1 - 12), w + 0.6))

    def bike_rack(self, side: int, centre: np.ndarray) -> None:
        """A rack (others) inside the sidewalk with bicycles without rider parked across it."""
        along = np.array([1.0, 0.0]) if side < 2 else np.array([0.0, 1.0])
        inward = _inward(side)
        lo, hi = centre - 1.2 * along - 0.3 * np.abs(inward), centre + 1.2 * along + 0.3 * np.abs(inward)
        self.rect(lo[0], hi[0], lo[1], hi[1], solid=(OTHERS, 0.0, 0.9))
        yaw = float(np.arctan2(inward[1], inward[0]))
        for k in range(int(self.rng.integers(1, 4))):
            self.place("bicycle", centre + along * (-0.8 + 0.8 * k) + inward * 1.2, yaw)

    def bus_stop(self, box: np.ndarray, side: int, a_mid: float) -> None:
        """A shelter just inside the sidewalk with two or three people standing by it."""
        shelter = self.frontage_rect(box, side, a_mid, 4.0, 1.6)
        x0, x1, y0, y1 = shelter
        self.clear(x0, x1, y0, y1, ground=OTHER_FLAT)  # a raised platform: nuScenes' flat.other
        self.rect(x0, x1, y0, y1, solid=(MANMADE, 0.0, 2.6))
        centre = np.array([(shelter[0] + shelter[1]) / 2, (shelter[2] + shelter[3]) / 2])
        along = np.array([1.0, 0.0]) if side < 2 else np.array([0.0, 1.0])
        for k in range(int(self.rng.integers(2, 4))):
            spot = centre + _inward(side) * 1.5 + along * (1.1 * k - 1.1)
            self.place("pedestrian", spot, self.rng.uniform(-np.pi, np.pi), parked=False)

    def park_block(self, box: np.ndarray) -> None:
        """Grass, trees, hedges around, footpaths across, benches and bins."""
        rng, w = self.rng, self.net.sidewalk
        x0, x1, y0, y1 = box + np.array([w, -w, w, -w])
        if x1 - x0 < 8 or y1 - y0 < 8:
            return
        self.rect(x0 + 0.3, x0 + 1.3, y0 + 6, y1 - 6, solid=(VEGETATION, 0.0, 1.1))
        self.rect(x1 - 1.3, x1 - 0.3, y0 + 6, y1 - 6, solid=(VEGETATION, 0.0, 1.1))
        cx, cy = rng.uniform(x0 + 10, x1 - 10), rng.uniform(y0 + 10, y1 - 10)
        self.rect(x0, x1, cy - 1.25, cy + 1.25, ground=SIDEWALK)
        self.rect(cx - 1.25, cx + 1.25, y0, y1, ground=SIDEWALK)
        n = int((x1 - x0) * (y1 - y0) / 200)
        for x, y in zip(rng.uniform(x0 + 3, x1 - 3, n), rng.uniform(y0 + 3, y1 - 3, n)):
            if abs(x - cx) > 3.5 and abs(y - cy) > 3.5:
                self.tree(x, y)
        for _ in range(int(rng.integers(1, 4))):
            x = rng.uniform(x0 + 4, x1 - 4)
            self.rect(x - 0.9, x + 0.9, cy + 1.5, cy + 2.1, solid=(MANMADE, 0.0, 0.8))
            self.rect(x + 1.2, x + 1.8, cy + 1.5, cy + 2.1, solid=(OTHERS, 0.0, 1.0))

    def frontage_rect(self, box: np.ndarray, side: int, a_mid: float, length: float, depth: float) -> np.ndarray:
        """[x0, x1, y0, y1] of a site just inside the sidewalk of one side, centred at ``a_mid``."""
        w = self.net.sidewalk
        x0, x1, y0, y1 = box
        lim = (x0, x1) if side < 2 else (y0, y1)
        half = min(length, lim[1] - lim[0] - 2 * w - 4) / 2
        a_mid = float(np.clip(a_mid, lim[0] + w + 2 + half, lim[1] - w - 2 - half))
        if side == 0:
            return np.array([a_mid - half, a_mid + half, y0 + w, y0 + w + depth])
        if side == 1:
            return np.array([a_mid - half, a_mid + half, y1 - w - depth, y1 - w])
        if side == 2:
            return np.array([x0 + w, x0 + w + depth, a_mid - half, a_mid + half])
        return np.array([x1 - w - depth, x1 - w, a_mid - half, a_mid + half])

    def parking_lot(self, site: np.ndarray, side: int) -> None:
        """Stalls in rows perpendicular to the road side, long vehicles along the back."""
        rng = self.rng
        x0, x1, y0, y1 = site
        self.clear(x0, x1, y0, y1, DRIVEABLE)
        horizontal = side < 2  # rows run along x
        a0, a1, b0, b1 = (x0, x1, y0, y1) if horizontal else (y0, y1, x0, x1)
        # Back row for long vehicles, then stall rows of 5.5 m with 7 m aisles.
        back_at_b1 = side in (0, 2)
        b_back = b1 - 1.6 if back_at_b1 else b0 + 1.6
        along_yaw = 0.0 if horizontal else np.pi / 2
        a = a0 + 2
        while a < a1 - 13:
            if rng.random() < 0.6:
                kind = pick(rng, LOT_LONG)
                ln = KINDS[kind].size_hi[0]
                self.place(kind, self._xy(horizontal, a + ln / 2, b_back), along_yaw)
                a += ln + 1.5
            else:
                a += 6.0
        stall_yaw = np.pi / 2 if horizontal else 0.0
        row = b0 + 3.5 if back_at_b1 else b1 - 3.5
        step = 12.5 if back_at_b1 else -12.5
        while (row < b1 - 6.5) if back_at_b1 else (row > b0 + 6.5):
            for a in np.arange(a0 + 2.5, a1 - 2.5, 2.7):
                if rng.random() < 0.7:
                    self.place(
                        pick(rng, LOT_STALLS), self._xy(horizontal, a, row), stall_yaw + np.pi * rng.integers(0, 2)
                    )
            row += step
        for a in np.arange(a0 + 6, a1 - 3, 18.0):
            p = self._xy(horizontal, a, b0 + 0.6 if back_at_b1 else b1 - 0.6)
            self.rect(p[0] - 0.25, p[0] + 0.25, p[1] - 0.25, p[1] + 0.25, solid=(MANMADE, 0.0, 7.0))

    @staticmethod
    def _xy(horizontal: bool, a: float, b: float) -> np.ndarray:
        return np.array([a, b]) if horizontal else np.array([b, a])

    def construction_site(self, site: np.ndarray, side: int) -> None:
        """A fenced site (barriers) with a gate marked by cones, a construction vehicle, debris
        and material piles (others) and an unfinished structure (manmade) at the back."""
        rng = self.rng
        x0, x1, y0, y1 = site
        self.clear(x0, x1, y0, y1, TERRAIN)
        horizontal = side < 2
        a0, a1, b0, b1 = (x0, x1, y0, y1) if horizontal else (y0, y1, x0, x1)
        inward = 1.0 if side in (0, 2) else -1.0
        front, back = (b0, b1) if inward > 0 else (b1, b0)
        depth = b1 - b0
        along_yaw, across_yaw = (0.0, np.pi / 2) if horizontal else (np.pi / 2, 0.0)
        gate = rng.uniform(a0 + 6, a1 - 12)
        for a in np.arange(a0 + 1.3, a1 - 1.0, 2.7):
            if not gate - 1 < a < gate + 9:
                self.place("barrier", self._xy(horizontal, a, front + inward * 0.4), along_yaw)
        for b in np.arange(b0 + 1.5, b1 - 1.0, 2.7):
            for a in (a0 + 0.4, a1 - 0.4):
                self.place("barrier", self._xy(horizontal, a, b), across_yaw)
        n = int(rng.integers(3, 6))
        for k in range(n):
            self.place("traffic_cone", self._xy(horizontal, gate + 8.0 * k / (n - 1), front + inward * 0.4), 0.0)
        vehicle_a = gate + 4.0
        self.place(
            "construction_vehicle",
            self._xy(horizontal, vehicle_a, front + inward * rng.uniform(6, max(6.5, depth - 10))),
            rng.uniform(-np.pi, np.pi),
        )
        for _ in range(int(rng.integers(1, 4))):
            a = rng.uniform(a0 + 3, a1 - 3)
            if abs(a - vehicle_a) > 6:
                p = self._xy(horizontal, a, front + inward * rng.uniform(3, depth - 6))
                self.disc(p[0], p[1], rng.uniform(1.0, 2.0), solid=(OTHERS, 0.0, rng.uniform(0.8, 2.2)))
        p0 = self._xy(horizontal, a1 - rng.uniform(12, 18), back - inward * rng.uniform(4, 6))
        p1 = self._xy(horizontal, a1 - 2, back - inward * 1.5)
        self.rect(p0[0], p1[0], p0[1], p1[1], solid=(MANMADE, 0.0, 12.0))

    # ------------------------------------------------------------ roads

    def median(self, road: Road, a0: float, a1: float) -> None:
        """The central strip between two intersections (along-road coordinates a0 < a1)."""
        rng = self.rng
        hm = road.median / 2
        c = road.centre
        box = (a0, a1, c - hm, c + hm) if road.axis == 0 else (c - hm, c + hm, a0, a1)
        self.rect(*box, ground=OTHER_FLAT)
        style = rng.choice(["plain", "hedge", "trees", "barriers"], p=[0.3, 0.3, 0.2, 0.2])
        if style == "hedge":
            inner = (a0 + 2, a1 - 2, c - hm + 0.4, c + hm - 0.4)
            self.rect(
                *(inner if road.axis == 0 else (inner[2], inner[3], inner[0], inner[1])), solid=(VEGETATION, 0.0, 1.0)
            )
        elif style == "trees":
            for a in np.arange(a0 + 4, a1 - 4, rng.uniform(9, 15)):
                self.tree(*((a, c) if road.axis == 0 else (c, a)))
        elif style == "barriers":
            yaw = 0.0 if road.axis == 0 else np.pi / 2
            for a in np.arange(a0 + 6, a1 - 6, 2.7):
                self.place("barrier", np.array([a, c]) if road.axis == 0 else np.array([c, a]), yaw)

    def parking_strip(self, road: Road, side: float, a0: float, a1: float, reserved: list[tuple[float, float]]) -> None:
        """Parked vehicles along one kerb (``side`` +1: the larger cross coordinate), facing the
        traffic of their side, avoiding the along-road intervals ``reserved``."""
        rng = self.rng
        lateral = road.centre + side * (road.half_width - road.parking / 2)
        yaw = _kerb_yaw(road, side)
        a = a0 + rng.uniform(0, 4)
        while a < a1:
            kind = pick(rng, STRIP_PARKING)
            ln = KINDS[kind].size_hi[0]
            if rng.random() < 0.7 and not any(r0 - 1 < a + ln and a < r1 + 1 for r0, r1 in reserved) and a + ln < a1:
                p = np.array([a + ln / 2, lateral]) if road.axis == 0 else np.array([lateral, a + ln / 2])
                self.place(kind, p, yaw)
            a += ln + rng.uniform(0.8, 5.0)

    def stretches(self, road: Road) -> list[tuple[float, float]]:
        """Along-road intervals between the kerbs of consecutive crossing roads, inside the region."""
        cross = self.net.roads[1 - road.axis]
        k = 0 if road.axis == 0 else 1
        out = []
        for c0, c1 in zip(cross[:-1], cross[1:]):
            a0, a1 = c0.centre + c0.half_width, c1.centre - c1.half_width
            if a1 > self.lo[k] and a0 < self.hi[k]:
                out.append((a0, a1))
        return out

    def roads_in_region(self) -> list[Road]:
        return [
            r
            for r in self.net.roads[0] + self.net.roads[1]
            if self.lo[1 - r.axis] - r.half_width < r.centre < self.hi[1 - r.axis] + r.half_width
        ]


def _kerb_yaw(road: Road, side: float) -> float:
    """Heading of right-hand traffic next to the kerb on global side ``side`` (+1/-1) of ``road``."""
    if road.axis == 0:
        return np.pi if side > 0 else 0.0
    return np.pi / 2 if side > 0 else -np.pi / 2


def _facing_side(road: Road, g: float) -> int:
    """Side index (0 south, 1 north, 2 west, 3 east) of a block on global side ``g`` of ``road``."""
    if road.axis == 0:
        return 0 if g > 0 else 1
    return 2 if g > 0 else 3


def paint_city(
    net: RoadNetwork,
    lo: np.ndarray,
    hi: np.ndarray,
    ego: LaneState,
    feature_along: float,
    rng: np.random.Generator,
    frames: int,
) -> tuple[StaticMap, TrackSet]:
    """Paint the region [lo, hi] (global metres) and place its static objects over ``frames``.

    The road the ego starts on (which must have parking strips) always gets, around
    ``feature_along`` (along the ego's travel direction): a bus stopped at a bus stop
    with people waiting on one side; a construction site behind a parking strip holding
    a truck, motorcycles, a trailer and cones on the other. So every scene shows every
    class early on.
    """
    painter = CityPainter(net, lo, hi, rng)
    road = net.roads[ego.axis][ego.road]
    u = HEADINGS[ego.heading]
    along_axis = np.array([1.0, 0.0]) if ego.axis == 0 else np.array([0.0, 1.0])
    axis_a = float(u @ along_axis) * feature_along  # the features' global coordinate along the road

    def point(a: float, cross: float) -> np.ndarray:
        return np.array([a, cross]) if ego.axis == 0 else np.array([cross, a])

    bus_side = int(rng.choice([-1, 1]))  # +1: on the ego's right
    bus_g = bus_side * float(right_of(u) @ road.normal)  # +1: the larger cross coordinate
    site_g = -bus_g
    probes = {
        "site": point(axis_a, road.centre + site_g * (road.half_width + 10)),
        "bus": point(axis_a, road.centre + bus_g * (road.half_width + 10)),
    }

    for box in painter.blocks():
        forced = next((k for k, p in probes.items() if box[0] <= p[0] <= box[1] and box[2] <= p[1] <= box[3]), None)
        painter.block_ground(box, TERRAIN)
        if forced is None and rng.random() < 0.12:
            painter.park_block(box)
            continue
        painter.building_block(box, bus_stop=forced == "bus")
        if forced == "site":
            side = _facing_side(road, site_g)
            site = painter.frontage_rect(box, side, axis_a, rng.uniform(28, 45), rng.uniform(16, 24))
            painter.construction_site(site, side)
        elif forced == "bus":
            painter.bus_stop(box, _facing_side(road, bus_g), axis_a)
        elif rng.random() < 0.35:
            side = int(rng.integers(0, 4))
            lim = (box[0], box[1]) if side < 2 else (box[2], box[3])
            lot = painter.frontage_rect(box, side, rng.uniform(*lim), rng.uniform(25, 50), rng.uniform(18, 30))
            if rng.random() < 0.75:
                painter.parking_lot(lot, side)
            else:
                painter.construction_site(lot, side)

    reserved = {bus_g: [(axis_a - 9.0, axis_a + 9.0)], site_g: [(axis_a - 17.0, axis_a + 27.0)]}
    for r in painter.roads_in_region():
        for a0, a1 in painter.stretches(r):
            if r.median > 0 and a1 - a0 > 2 * MEDIAN_END + 10:
                painter.median(r, a0 + MEDIAN_END, a1 - MEDIAN_END)
            if r.parking > 0:
                for g in (-1.0, 1.0):
                    busy = reserved[g] if r is road and a0 < axis_a < a1 else []
                    painter.parking_strip(r, g, a0 + 8.0, a1 - 8.0, busy)

    for box in painter.blocks():  # last, so nothing paints over them
        painter.signal_poles(box)

    strip = road.half_width - road.parking / 2
    painter.place("bus", point(axis_a, road.centre + bus_g * (strip - 0.2)), _kerb_yaw(road, bus_g), parked=False)
    a = axis_a - 16.0
    for kind in ("truck", "motorcycle", "motorcycle", "trailer"):
        ln = KINDS[kind].size_hi[0]
        painter.place(kind, point(a + ln / 2, road.centre + site_g * strip), _kerb_yaw(road, site_g))
        a += ln + 1.0
    for k in range(5):
        painter.place("traffic_cone", point(a + 1.0 + 2.0 * k, road.centre + site_g * (strip - 0.2 * k)), 0.0)
    return painter.map, painter.tracks(frames)
