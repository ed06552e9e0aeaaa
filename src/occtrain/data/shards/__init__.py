"""Webdataset tar shards made from an Occ3D-layout dataset, and their safe reading.

Two kinds of sample, each in its own shard set under ``SHARDS/<kind>/<split>-NNNNNN.tar``:

``frames`` (tokenizer stages): one frame.
    ``__key__``  sample token
    ``occ.npz``  ``semantics`` uint8 (200,200,16); ``mask_lidar``, ``mask_camera`` bit-packed uint8
    ``meta.json`` ``{"scene", "token", "index", "split"}``

``clips`` (world-model stages): ``history`` past frames, the anchor frame and ``future`` frames.
    ``__key__``  anchor sample token
    ``occ.npz``  ``semantics`` uint8 (T,200,200,16); ``mask_camera`` bit-packed, T = history+1+future
    ``ann.json`` ``{"anchor": FrameAnnotation, "tokens": [...], "ego_poses": [[x, y, yaw], ...],
                   "history": h, "future": f, "split"}``
    ``qa.json``  the anchor's NuScenes-QA questions (a list, possibly empty)
    ``caption.txt``, ``narration.txt``  the anchor's text

Both kinds carry the (anchor) frame's six camera views when the dataset has them:
    ``cam_front.png`` ... (or ``.jpg``, the release's files as they are), ``cam_front.class.png``
    and ``cam_front.depth.png`` beside synthetic images, and ``cams.json`` ``{"intrinsic":
    [6 x 3 x 3], "cam_to_ego": [6 x 4 x 4]}``. A stage that does not read cameras drops
    these entries before anything is decoded.

``SHARDS/index.json`` lists the shards and their sample counts and is written last, so a
shard set without it is incomplete. Reading decodes only an allow-list of formats
(npy/npz without pickle, json, txt, png); anything else in a shard is refused.

The package: ``entries`` (what a shard holds), ``freshness`` (whether a set is current),
``writer``, ``reader`` and ``positions`` (which samples a rank and loader worker read,
and reading them alone).
"""

from __future__ import annotations

from occtrain.data.shards.entries import ALLOWED_EXTENSIONS, INDEX_FILE, KINDS, unpack_mask
from occtrain.data.shards.freshness import (
    clip_shortfall,
    current_shards,
    dataset_fingerprint,
    no_clips_note,
    shard_source,
    source_files,
    world_key,
)
from occtrain.data.shards.reader import decode_sample, iter_raw, make_pipeline, read_index, shard_urls
from occtrain.data.shards.writer import LeftoverRebuild, leftover_rebuilds, write_shards

__all__ = [
    "ALLOWED_EXTENSIONS",
    "clip_shortfall",
    "current_shards",
    "dataset_fingerprint",
    "decode_sample",
    "INDEX_FILE",
    "iter_raw",
    "KINDS",
    "leftover_rebuilds",
    "LeftoverRebuild",
    "make_pipeline",
    "no_clips_note",
    "read_index",
    "resolve",
    "shard_source",
    "shard_urls",
    "source_files",
    "unpack_mask",
    "world_key",
    "write_shards",
]
