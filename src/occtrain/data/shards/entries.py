"""What a shard holds: its kinds, the entry formats it may carry, how masks are packed,
and the index that lists a shard set."""

from __future__ import annotations

from typing import Any, NotRequired, TypedDict

import numpy as np

from occtrain.formats.occ3d import GRID_SHAPE

INDEX_FILE = "index.json"


KINDS = ("frames", "clips")


#: The only entry formats a shard may hold; anything else is refused, never unpickled.
ALLOWED_EXTENSIONS = ("npy", "npz", "json", "txt", "png", "jpg")


#: Entries holding camera data start with this (``cam_front.png``, ``cams.json``).
CAMERA_ENTRY_PREFIX = "cam"


PACKED_MASKS = ("mask_lidar", "mask_camera")


#: The fingerprint a new shard index records (see :func:`dataset_fingerprint`).
FINGERPRINT_VERSION = 3


#: What `occtrain data shards` writes unless told otherwise (see :func:`shard_source`).
DEFAULT_LAYOUT = {"samples_per_shard": 64, "history": 4, "future": 6}


def pack_mask(mask: np.ndarray) -> np.ndarray:
    return np.packbits(mask.astype(bool), axis=-1)


def unpack_mask(packed: np.ndarray) -> np.ndarray:
    """Inverse of the bit-packing applied to masks in shards: uint8 0/1 of grid shape."""
    return np.unpackbits(packed, axis=-1, count=GRID_SHAPE[-1])


class ShardEntry(TypedDict):
    file: str  # a file name inside SHARDS/<kind>/
    samples: int


class ShardIndex(TypedDict):
    """``SHARDS/index.json``: what the shards were made from, and the shards of each kind and split."""

    source: dict[str, Any]
    kinds: dict[str, dict[str, list[ShardEntry]]]
    #: Kinds left out although asked for by default, and why (clips no scene is long enough for).
    missing: NotRequired[dict[str, str]]
