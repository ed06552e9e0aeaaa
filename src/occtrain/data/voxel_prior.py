"""The per-voxel prior: each voxel's commonest label over a dataset's train frames.

It reads no input at all, only where things usually are in the ego's grid (road below and
ahead, sidewalks and buildings to the sides), so it is the floor under every
reconstruction and forecast: a tokenizer or a world model that does not beat it has
learned no more than the layout of the average frame. Computed once per dataset and kept
in a cache directory under the dataset's key (``data.shards.world_key``), so an edited
dataset counts afresh.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from occtrain.data.layout import DatasetIndex
from occtrain.errors import DataError
from occtrain.formats.io import atomic_write_npz
from occtrain.formats.occ3d import GRID_SHAPE, NUM_CLASSES
from occtrain.progress import progress_bar

PRIOR_PREFIX = "voxel-prior-"


def voxel_prior(root: str | Path, cache_dir: Path | None = None, split: str = "train") -> np.ndarray:
    """(X, Y, Z) uint8: each voxel's commonest label over the ``split`` frames of the
    dataset at ``root`` (ties to the lower class index). Read from ``cache_dir`` when it
    was counted before on this dataset as it is, and kept there otherwise."""
    from occtrain.data.shards import world_key

    path = None if cache_dir is None else Path(cache_dir) / f"{PRIOR_PREFIX}{split}-{world_key(root)}.npz"
    if path is not None and path.is_file():
        with np.load(path, allow_pickle=False) as kept:
            prior = kept["prior"]
        if prior.shape == GRID_SHAPE and prior.dtype == np.uint8:
            return prior
    prior = _count(DatasetIndex.open(root), split)
    if path is not None:
        atomic_write_npz(path, {"prior": prior})
    return prior


def _count(index: DatasetIndex, split: str) -> np.ndarray:
    frames = [(scene, token) for scene in index.splits.get(split, []) for token in index.scenes[scene]]
    if not frames:
        raise DataError(f"{index.root}: its {split} split holds no frame to count the per-voxel prior on")
    # One count per class and voxel: 18 x 200 x 200 x 16 uint32, 46 MB.
    counts = np.zeros((NUM_CLASSES, *GRID_SHAPE), dtype=np.uint32)
    with progress_bar(len(frames), f"the per-voxel prior over {len(frames)} {split} frames, once") as advance:
        for scene, token in frames:
            semantics = index.labels(scene, token)["semantics"]
            for c in np.unique(semantics):
                counts[c] += semantics == c
            advance(1)
    return counts.argmax(0).astype(np.uint8)
