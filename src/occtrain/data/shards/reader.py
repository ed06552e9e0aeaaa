"""Reading shard sets safely: the index, the shard URLs of a split, an allow-list decoder
(never unpickled) and the webdataset pipeline a datamodule iterates."""

from __future__ import annotations

import io
import re
import tarfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import webdataset as wds

from occtrain.data.shards.entries import (
    ALLOWED_EXTENSIONS,
    CAMERA_ENTRY_PREFIX,
    INDEX_FILE,
    PACKED_MASKS,
    ShardIndex,
    unpack_mask,
)
from occtrain.data.shards.positions import PAD_KEY, ShardSamples
from occtrain.data.validate import first_problem
from occtrain.errors import DataError
from occtrain.formats.io import parse_json
from occtrain.formats.occ3d import GRID_SHAPE
from occtrain.ranks import rank_world


def read_index(shards: str | Path) -> dict:
    """The index of a shard directory; a missing or bad one is a one-line DataError."""
    path = Path(shards) / INDEX_FILE
    if not path.is_file():
        raise DataError(f"{path}: not found; write shards with `occtrain data shards DATASET --out {Path(shards)}`")
    try:
        idx = parse_json(path.read_text())
    except ValueError as err:
        raise DataError(f"{path}: not valid JSON ({err}); write the shards again") from None
    problem = first_problem(idx, ShardIndex)
    if problem:
        raise DataError(f"{path}: {problem}; write the shards again")
    for kind, splits in idx["kinds"].items():
        for split, entries in splits.items():
            for i, entry in enumerate(entries):
                name = entry["file"]
                if Path(name).name != name or name in (
                    "",
                    ".",
                    "..",
                ):  # a shard never lies outside its kind's directory
                    raise DataError(
                        f"{path}: kinds.{kind}.{split}[{i}].file '{name}' is not a file name; write the shards again"
                    )
    return idx


def shard_urls(shards: str | Path, kind: str, split: str) -> tuple[list[str], int]:
    """Paths of one kind/split's shards and their total sample count."""
    idx = read_index(shards)
    if kind not in idx["kinds"]:
        why = idx.get("missing", {}).get(kind)
        if why:  # left out by default because no scene is long enough: --kinds would be refused alike
            raise DataError(
                f"{Path(shards) / INDEX_FILE}: has no '{kind}' shards: {why}, so no clip fits; use longer scenes or a "
                "shorter history/future"
            )
        raise DataError(f"{Path(shards) / INDEX_FILE}: has no '{kind}' shards; write them with --kinds {kind}")
    entries = idx["kinds"][kind].get(split, [])
    return [str(Path(shards) / kind / e["file"]) for e in entries], sum(e["samples"] for e in entries)


def _decode_entry(name: str, data: bytes, where: str) -> Any:
    ext = name.rsplit(".", 1)[-1].lower()
    if ext not in ALLOWED_EXTENSIONS:
        raise DataError(
            f"{where}: entry '{name}' is not an allowed format ({', '.join(ALLOWED_EXTENSIONS)}); "
            "refusing to decode it (pickled payloads are never loaded)"
        )
    try:
        if ext == "npy":
            return np.load(io.BytesIO(data), allow_pickle=False)
        if ext == "npz":
            with np.load(io.BytesIO(data), allow_pickle=False) as npz:
                return {k: npz[k] for k in npz.files}
        if ext == "json":
            return parse_json(data)
        if ext == "txt":
            return data.decode("utf-8")
        from PIL import Image

        return np.asarray(Image.open(io.BytesIO(data)))
    except ValueError as err:
        if "allow_pickle" in str(err):
            raise DataError(f"{where}: entry '{name}' holds a pickled object array; refusing to load it") from None
        raise DataError(f"{where}: entry '{name}' cannot be decoded ({err})") from None
    except Exception as err:  # zlib, zip, unicode and image errors all mean a corrupt entry
        raise DataError(f"{where}: entry '{name}' is corrupt ({type(err).__name__}: {err})") from None


def decode_sample(sample: dict) -> dict:
    """Decode one raw webdataset sample through the allow-list; masks are unpacked."""
    where = f"{sample.get('__url__', '?')} sample '{sample.get('__key__', '?')}'"
    out: dict[str, Any] = {"__key__": sample.get("__key__")}
    if sample.get(PAD_KEY):
        out[PAD_KEY] = True
    for name, value in sample.items():
        if name.startswith("__"):
            continue
        out[name] = _decode_entry(name, value, where)
    occ = out.get("occ.npz")
    if isinstance(occ, dict):
        for key in PACKED_MASKS:
            if key in occ:
                occ[key] = unpack_mask(occ[key])
        sem = occ.get("semantics")
        if sem is None or sem.shape[-3:] != GRID_SHAPE or sem.dtype != np.uint8:
            shape = None if sem is None else sem.shape
            raise DataError(f"{where}: 'occ.npz' semantics has shape {shape}, expected (..., {GRID_SHAPE}) uint8")
    return out


def _shard_error_detail(exn: BaseException) -> str:
    """The message of a tar error, without the stream objects webdataset appends to it."""
    first = exn.args[0] if exn.args else exn
    while isinstance(first, BaseException) and first.args:
        first = first.args[0]
    if isinstance(first, tuple) and first:
        first = first[0]
    return re.split(r"\s*@\s*<|'?\)?,\s*<", str(first))[0].strip("(\"' ")


def _raise_shard_error(exn: Exception) -> bool:
    """webdataset error handler: turn tar/IO failures into one-line DataErrors naming the shard."""
    if isinstance(exn, DataError):
        # webdataset appends its stream and url to the args of what passes through it
        # (which would print as a tuple): raise the message alone, once more.
        raise DataError(exn.args[0]) from None
    url = next((a for a in exn.args[1:] if isinstance(a, str)), None) if exn.args else None
    where = url or "shard"
    if isinstance(exn, (tarfile.TarError, EOFError, OSError, ValueError)):
        detail = _shard_error_detail(exn)
        raise DataError(
            f"{where}: corrupt or truncated shard ({type(exn).__name__}: {detail}); write the shards again"
        ) from None
    raise exn


def make_pipeline(
    urls: list[str],
    train: bool,
    total: int | None = None,
    shuffle_buffer: int = -1,
    seed: int = 0,
    transform: Callable[[dict], Any] | None = None,
    entries: Iterable[str] | None = None,
    batch_size: int = 1,
    cameras: bool = False,
    rank_and_world: tuple[int, int] | None = None,
) -> wds.DataPipeline:
    """Decoded samples of shards, each rank and loader worker reading only its own (see
    :mod:`occtrain.data.shards.positions`).

    ``train=True``: the endless seeded training order, this rank's batches of
    ``batch_size``. ``train=False``: every sample once, in order, strided over ranks and
    workers. ``entries`` keeps only those entries of each sample, never read otherwise (a
    stage that needs only annotations never reads the occupancy arrays); camera entries are
    read only with ``cameras``. ``rank_and_world`` defaults to the process group's. The
    pipeline's first stage (``pipeline.pipeline[0]``) is the :class:`ShardSamples` reader.
    """
    keep = frozenset(entries) if entries is not None else None

    def wanted(name: str) -> bool:
        if name.startswith(CAMERA_ENTRY_PREFIX):
            return cameras
        return keep is None or name in keep

    rank, world = rank_and_world or rank_world()
    source = ShardSamples(
        urls,
        total,
        train,
        rank,
        world,
        batch_size=batch_size,
        seed=seed,
        shuffle_buffer=shuffle_buffer,
        wanted=wanted,
    )
    stages: list[Any] = [source, wds.map(decode_sample, handler=_raise_shard_error)]
    if transform is not None:
        stages.append(wds.map(transform, handler=_raise_shard_error))
    return wds.DataPipeline(*stages)


def iter_raw(url: str) -> Iterator[dict]:
    """Raw samples of one shard (for checking), errors as DataError naming the shard.

    webdataset names the shard in some of the errors it passes on and not in others (a
    tar cut inside a member's header arrives without it): the one shard read here is
    named whenever the error does not.
    """
    try:
        yield from wds.DataPipeline(wds.SimpleShardList([url]), wds.tarfile_to_samples(handler=_raise_shard_error))
    except DataError as err:
        message = str(err)
        if message.startswith("shard: "):
            raise DataError(f"{url}: {message[len('shard: ') :]}") from None
        raise
