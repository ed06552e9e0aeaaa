"""The synthetic world's vertical convention on top of the Occ3D grid.

The world is flat: the ground surface lies at ``GROUND_TOP_Z`` in the ego frame. Of the
``GROUND_LAYERS`` voxel layers below it (z -1.0 .. -0.2 m) only the top one,
``GROUND_LAYER``, holds the ground, as a surface: what a lidar returns from is the
surface, and Occ3D labels surfaces. Every object stands on top of it. The ego frame's
origin is on the ego's centre, 0.2 m above the ground surface (the global pose's z is 0).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from occtrain.formats.occ3d import GRID_SHAPE, RANGE_MIN, VOXEL_SIZE, voxel_centers_1d

#: Ego-frame height (m) of the ground surface.
GROUND_TOP_Z = -0.2
#: Number of voxel layers whose centres lie below the ground surface (the ground layers).
GROUND_LAYERS = int(np.sum(voxel_centers_1d(2) < GROUND_TOP_Z))
#: The one layer that holds the ground surface (the layers under it stay free).
GROUND_LAYER = GROUND_LAYERS - 1
#: Layer bound that means "above the grid's top": a thing reaching it has no top in the grid.
ABOVE_GRID = GRID_SHAPE[2] + 1
#: Height of the ego's own box, kept free in every frame (Occ3D does not label the ego).
EGO_HEIGHT = 1.8


def layer_span(bottom: np.ndarray | float, top: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Half-open voxel layer range [lo, hi) of things from ``bottom`` to ``top`` metres above ground.

    A layer belongs to the thing when its centre lies inside the height interval; every
    thing that starts below the grid's top gets at least one layer, and nothing reaches
    into the ground layers. ``hi`` is ``ABOVE_GRID`` when the thing's top lies above the
    grid (its top surface, a roof or a crown, is then not in the grid).
    """
    zmin, n = RANGE_MIN[2], GRID_SHAPE[2]
    lo = np.ceil((GROUND_TOP_Z + np.asarray(bottom, np.float64) - zmin) / VOXEL_SIZE - 0.5)
    hi = np.ceil((GROUND_TOP_Z + np.asarray(top, np.float64) - zmin) / VOXEL_SIZE - 0.5)
    lo = np.clip(lo, GROUND_LAYERS, n).astype(np.int64)
    hi = np.clip(np.maximum(hi, lo + 1), GROUND_LAYERS, ABOVE_GRID).astype(np.int64)
    return lo, hi


@lru_cache(maxsize=1)
def column_centres() -> np.ndarray:
    """(X, Y, 2) ego-frame x-y centres of the grid columns (read-only)."""
    xs, ys = voxel_centers_1d(0), voxel_centers_1d(1)
    out = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1)
    out.setflags(write=False)
    return out
