"""Forecast targets without code synonyms, and the cells where an agent moved."""

from __future__ import annotations

import torch

from occtrain.core.forecast_targets import CANONICAL_AGREEMENT, canonical_codes, mover_cells
from occtrain.formats.occ3d import CLASS_INDEX, FREE

HW = (25, 25)  # 8 x 8 voxels a cell over the 200 x 200 grid


def scene() -> torch.Tensor:
    labels = torch.full((200, 200, 16), FREE, dtype=torch.long)
    labels[:, :, 0] = CLASS_INDEX["driveable_surface"]
    return labels


def test_a_target_code_that_differs_where_the_scene_did_not_is_the_querys():
    query, target = torch.arange(2 * 625) % 7, (torch.arange(2 * 625) % 7 + 1) % 7  # every code differs
    present, future = scene(), scene()
    future[8:16, 0:8, 3] = CLASS_INDEX["car"]  # cell (1, 0): 64 of its 1024 voxels changed
    future[0:8, 8:9, 5:7] = CLASS_INDEX["manmade"]  # cell (0, 1): 16 voxels, within 2 %
    codes = canonical_codes(query, target, present, future, books=2, hw=HW)
    grid, want = codes.reshape(2, 25, 25), query.reshape(2, 25, 25).clone()
    want[:, 1, 0] = target.reshape(2, 25, 25)[:, 1, 0]  # the cell that changed keeps the future's code
    assert torch.equal(grid, want)
    assert 16 / 1024 <= 1 - CANONICAL_AGREEMENT < 64 / 1024


def test_mover_cells_are_where_a_movable_voxel_came_or_went():
    present, future = scene(), scene()
    present[40:48, 40:48, 1:3] = CLASS_INDEX["car"]  # the car was in cell (5, 5) ...
    future[48:56, 40:48, 1:3] = CLASS_INDEX["car"]  # ... and is now in cell (6, 5)
    present[100:108, 100:108, 1:3] = future[100:108, 100:108, 1:3] = CLASS_INDEX["car"]  # a parked one
    future[160:168, 0:8, 1:8] = CLASS_INDEX["manmade"]  # a static change is no mover
    movers = mover_cells(present, future, HW)
    assert movers.nonzero().tolist() == [[5, 5], [6, 5]]
