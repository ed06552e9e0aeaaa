"""Reading shard samples by position, so that each rank and loader worker reads only its own.

A tar shard is uncompressed: once its headers are read (512 bytes a member), the byte range
of every entry is known and a sample can be read alone. :func:`shard_members` lists a
shard's samples that way, and :class:`ShardSamples` reads the samples at the positions a
rank and worker own, and only the entries a stage asked for.

The training order is a function of the seed alone: each epoch visits the shards in a
seeded permutation, and a seeded buffer shuffles the samples across them (:func:`train_order`).
It is computed over sample positions, not bytes, so every process computes the whole order
cheaply and keeps its own part: position ``i`` is in global batch ``i // (world x batch)``,
which rank ``r`` takes the ``r``-th ``batch`` of, and rank-local batches go round-robin to
loader workers (the order a DataLoader collects them in). N ranks of B samples then train on
the batches one process of N x B trains on, each reading about 1/N of the bytes, and a
resumed run starts at a sample position without reading what it skips.
"""

from __future__ import annotations

import bisect
import itertools
import os
import random
import re
import tarfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

from torch.utils.data import IterableDataset, get_worker_info

from occtrain.errors import DataError

#: webdataset's grouping rule: a member ``dir/key.ext.ext`` is entry ``ext.ext`` of sample ``dir/key``.
_MEMBER = re.compile(r"^((?:.*/|)[^.]+)[.]([^/]*)$")

#: Marks a sample that only evens out the batch count of a DDP rank; collate drops it.
PAD_KEY = "__pad__"


@dataclass(frozen=True)
class SampleRef:
    """Where one sample's entries lie in its shard: ``(entry, offset, size)`` each."""

    key: str
    entries: tuple[tuple[str, int, int], ...]


_MEMBERS: dict[tuple[str, int, int], list[SampleRef]] = {}


def shard_members(url: str) -> list[SampleRef]:
    """The samples of one tar shard, in order, with their entries' byte ranges (cached per
    process by path, size and modification time). Reads the headers alone."""
    try:
        st = os.stat(url)
    except OSError as err:
        raise DataError(f"{url}: cannot be read ({err.strerror}); write the shards again") from None
    cache_key = (url, st.st_size, st.st_mtime_ns)
    if cache_key in _MEMBERS:
        return _MEMBERS[cache_key]
    samples: list[SampleRef] = []
    key: str | None = None
    entries: list[tuple[str, int, int]] = []
    try:
        with tarfile.open(url, "r:") as tar:
            for member in tar:
                match = _MEMBER.match(member.name)
                if not member.isfile() or match is None:
                    continue
                if member.offset_data + member.size > st.st_size:
                    raise tarfile.ReadError(f"entry '{member.name}' runs past the end of the file")
                if match.group(1) != key:
                    if key is not None:
                        samples.append(SampleRef(key, tuple(entries)))
                    key, entries = match.group(1), []
                entries.append((match.group(2).lower(), member.offset_data, member.size))
    except (tarfile.TarError, EOFError, OSError) as err:
        raise DataError(
            f"{url}: corrupt or truncated shard ({type(err).__name__}: {err}); write the shards again"
        ) from None
    if key is not None:
        samples.append(SampleRef(key, tuple(entries)))
    _MEMBERS[cache_key] = samples
    return samples


def train_order(counts: list[int], seed: int, shuffle_buffer: int) -> Iterator[tuple[int, int]]:
    """The endless training order over ``(shard, sample)`` positions, the same in every
    process, a function of ``seed`` alone:

    - ``shuffle_buffer < 0``: each epoch is a seeded permutation of every sample. Samples are
      read by position, so this costs no reading beyond the samples themselves;
    - ``0`` or ``1``: each epoch reads the shards whole, in a seeded permutation;
    - larger: that permutation of shards, mixed by a seeded buffer of ``shuffle_buffer``
      samples. Shards written in scene order then give batches from only the few scenes
      the buffer spans (128 samples spanned 3 of the quickstart's 12 train scenes, and its
      planning head ended 0.44 m from the truth instead of 0.19 m).
    """
    if not any(counts):
        raise DataError("the training shards hold no sample")
    if shuffle_buffer < 0:
        yield from _epoch_permutations(counts, seed)
        return

    def epochs() -> Iterator[tuple[int, int]]:
        for epoch in itertools.count():
            shards = list(range(len(counts)))
            random.Random(f"shards:{seed}:{epoch}").shuffle(shards)
            for shard in shards:
                for i in range(counts[shard]):
                    yield shard, i

    if shuffle_buffer <= 1:
        yield from epochs()
        return
    rng = random.Random(f"buffer:{seed}")
    buffer: list[tuple[int, int]] = []
    for item in epochs():
        if len(buffer) < shuffle_buffer:
            buffer.append(item)
            continue
        j = rng.randrange(shuffle_buffer)
        yield buffer[j]
        buffer[j] = item


def _epoch_permutations(counts: list[int], seed: int) -> Iterator[tuple[int, int]]:
    starts = list(itertools.accumulate(counts, initial=0))
    for epoch in itertools.count():
        order = list(range(starts[-1]))
        random.Random(f"samples:{seed}:{epoch}").shuffle(order)
        for n in order:
            # The last shard starting at or before n: empty shards share a start and are skipped.
            shard = bisect.bisect_right(starts, n) - 1
            yield shard, n - starts[shard]


def own_train_positions(
    order: Iterable[tuple[int, int]],
    start: int,
    rank: int,
    world: int,
    batch_size: int,
    worker: int,
    workers: int,
) -> Iterator[tuple[int, int]]:
    """The positions of ``order`` from sample ``start`` on that are this rank's and worker's:
    rank ``r`` takes the ``r``-th ``batch_size`` samples of each global batch of
    ``world x batch_size``, and its batches go round-robin to ``workers``."""
    per_step = world * batch_size
    for i, item in enumerate(itertools.islice(order, start, None)):
        step, within = divmod(i, per_step)
        if within // batch_size == rank and step % workers == worker:
            yield item


def own_val_positions(total: int, rank: int, world: int, worker: int, workers: int) -> list[int | None]:
    """Every ``world``-th of ``total`` validation samples from ``rank`` on, split over loader
    workers; ``None`` marks one padding sample (see :class:`ShardSamples`)."""
    mine: list[int | None] = list(range(rank, total, world))
    if len(mine) < -(-total // world):
        mine.insert(0, None)
    return mine[worker::workers]


class ShardSamples(IterableDataset):
    """Raw samples (``{"__key__", "__url__", entry: bytes}``, as webdataset gives them) of
    shards read by position.

    ``train``: the endless order of :func:`train_order` from sample ``start`` on, this rank's
    and worker's part of it. Otherwise every sample once, strided over ranks and workers.
    DDP needs every rank to run the same number of validation batches (each forward is a
    collective), so a rank with one sample fewer than the others starts with a padding
    sample (a copy of its first, marked :data:`PAD_KEY`) that collate drops.

    ``wanted(entry)`` says which entries to read; the others' bytes are never read.
    ``bytes_read`` counts what this object read (headers excluded), for benchmarks.
    """

    def __init__(
        self,
        urls: list[str],
        total: int | None,
        train: bool,
        rank: int,
        world: int,
        batch_size: int = 1,
        seed: int = 0,
        shuffle_buffer: int = 0,
        wanted: Callable[[str], bool] | None = None,
    ):
        super().__init__()
        if not urls:
            raise DataError("no shards to read; write them with `occtrain data shards`")
        self.urls, self.total, self.train = list(urls), total, train
        self.rank, self.world, self.batch_size = rank, world, batch_size
        self.seed, self.shuffle_buffer = seed, shuffle_buffer
        self.wanted = wanted
        #: The first sample position of the training order to read (set to resume).
        self.start = 0
        self.bytes_read = 0

    def members(self) -> list[list[SampleRef]]:
        """Every shard's samples; their count must be what the shard index says."""
        members = [shard_members(url) for url in self.urls]
        found = sum(len(m) for m in members)
        if self.total is not None and found != self.total:
            # A shard cut at a member boundary reads as a shorter valid tar: only the count tells.
            url = next((u for u, m in zip(self.urls, members) if not m), self.urls[-1])
            raise DataError(
                f"{url}: its split holds {found} samples, index.json says {self.total} (a truncated or replaced "
                "shard); write the shards again"
            )
        return members

    def __iter__(self) -> Iterator[dict]:
        info = get_worker_info()
        worker, workers = (info.id, info.num_workers) if info is not None else (0, 1)
        members = self.members()
        if self.train:
            order = train_order([len(m) for m in members], self.seed, self.shuffle_buffer)
            for shard, i in own_train_positions(
                order, self.start, self.rank, self.world, self.batch_size, worker, workers
            ):
                yield self.read(shard, members[shard][i])
            return
        flat = [(s, ref) for s, refs in enumerate(members) for ref in refs]
        positions = own_val_positions(len(flat), self.rank, self.world, worker, workers)
        for p in positions:
            if p is None:  # the padding sample, only ever first: a copy of the rank's first sample
                yield {**self.read(*flat[self.rank]), PAD_KEY: True}
            else:
                yield self.read(*flat[p])

    def read(self, shard: int, ref: SampleRef) -> dict:
        """One sample's wanted entries, as bytes."""
        url = self.urls[shard]
        sample: dict = {"__key__": ref.key, "__url__": url}
        with open(url, "rb") as f:
            for name, offset, size in ref.entries:
                if self.wanted is not None and not self.wanted(name):
                    continue
                f.seek(offset)
                data = f.read(size)
                if len(data) != size:
                    raise DataError(
                        f"{url}: corrupt or truncated shard (entry '{ref.key}.{name}' is cut short); write the shards "
                        "again"
                    )
                sample[name] = data
                self.bytes_read += size
        return sample


__all__ = [
    "PAD_KEY",
    "SampleRef",
    "ShardSamples",
    "own_train_positions",
    "own_val_positions",
    "shard_members",
    "train_order",
]
