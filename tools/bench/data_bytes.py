"""Bytes each rank reads from the training shards at 1, 2 and 4 processes.

    python tools/bench/data_bytes.py [--shards data/quickstart/shards] [--global-batch 8] [--epochs 1]

Each setting starts N fresh processes (rank r of N, no process group needed: the reader
takes its rank and world as arguments, as a stage's does from the process group) and
reads the same global training order: ``--epochs`` epochs of the split in global batches
of ``--global-batch``, each rank its ``global-batch / N`` share of every batch through a
DataLoader. Two counts per rank, side by side in one run:

- ``rchar``: bytes the process read through read() syscalls while iterating
  (``/proc/self/io``): tar headers, entries, everything, as the kernel saw it;
- ``entries``: the entry bytes the reader returned (``ShardSamples.bytes_read``).

Until issue 28 every rank read every tar of the stream and kept its share (``N x`` the
bytes of its samples); now each reads the byte ranges of its own samples. Expected: per
rank about 1/N of one process, for both shard kinds (frames feed the tokenizer stages,
clips the world-model stages; clips are read here with every entry, as a stage without
cached scene codes does).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch.multiprocessing as mp  # noqa: E402
from records import Row, record  # noqa: E402
from torch.utils.data import DataLoader  # noqa: E402

from occtrain.data.shards import make_pipeline, shard_urls  # noqa: E402


def _rchar() -> int:
    with open("/proc/self/io") as fh:
        return int(next(line for line in fh if line.startswith("rchar:")).split()[1])


def _rank(rank: int, world: int, urls: list[str], total: int, batch: int, steps: int, out: dict) -> None:
    pipeline = make_pipeline(
        urls, train=True, total=total, batch_size=batch, rank_and_world=(rank, world), seed=0, shuffle_buffer=1
    )
    loader = DataLoader(pipeline, batch_size=batch, num_workers=0, collate_fn=len)
    iterator = iter(loader)
    next(iterator)  # imports and the header scan of the first batch are set-up, not reading
    before, entries = _rchar(), pipeline.pipeline[0].bytes_read
    seen = 1
    for _ in range(steps - 1):
        next(iterator)
        seen += 1
    out[rank] = (_rchar() - before, pipeline.pipeline[0].bytes_read - entries, seen * batch)


def measure(urls: list[str], total: int, world: int, global_batch: int, steps: int) -> list[tuple[int, int, int]]:
    """(rchar, entry bytes, samples) of each of ``world`` fresh processes."""
    ctx = mp.get_context("spawn")
    with ctx.Manager() as manager:
        out = manager.dict()
        procs = [
            ctx.Process(target=_rank, args=(r, world, urls, total, global_batch // world, steps, out))
            for r in range(world)
        ]
        for p in procs:
            p.start()
        for p in procs:
            p.join()
            if p.exitcode != 0:
                raise SystemExit(f"rank process exited with {p.exitcode}")
        return [out[r] for r in range(world)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shards", default="data/quickstart/shards")
    parser.add_argument("--global-batch", type=int, default=8)
    parser.add_argument("--epochs", type=float, default=1.0)
    args = parser.parse_args()
    if not (Path(args.shards) / "index.json").is_file():
        raise SystemExit(
            f"{args.shards}: no shards; run `occtrain run recipes/quickstart.yaml` (or `occtrain data shards`) first"
        )
    print(f"training shards of {args.shards}, global batch {args.global_batch}, {args.epochs:g} epoch(s); MiB per rank")
    print(f"{'kind':<7} {'processes':>9} {'rchar/rank':>11} {'entries/rank':>13} {'vs 1 process':>13} {'1/N':>6}")
    shares: dict[str, list[str]] = {}
    for kind in ("frames", "clips"):
        urls, total = shard_urls(args.shards, kind, "train")
        steps = max(2, int(total * args.epochs) // args.global_batch)
        one = None
        for world in (1, 2, 4):
            ranks = measure(urls, total, world, args.global_batch, steps)
            rchar = sum(r for r, _, _ in ranks) / world
            entries = sum(e for _, e, _ in ranks) / world
            assert all(n == steps * args.global_batch // world for _, _, n in ranks)
            one = one or rchar
            print(
                f"{kind:<7} {world:>9} {rchar / 2**20:>11.1f} {entries / 2**20:>13.1f} {rchar / one:>13.3f} "
                f"{1 / world:>6.3f}"
            )
            shares.setdefault(kind, []).append(f"{rchar / 2**20:.1f}")
    record(
        [
            Row(
                f"bytes each rank reads (`/proc/self/io` rchar) of {args.epochs:g} epoch of the training shards, "
                f"global batch {args.global_batch}, at 1 / 2 / 4 fresh processes",
                "; ".join(f"{kind} {' / '.join(mib)} MiB a rank" for kind, mib in shares.items()),
            )
        ]
    )


if __name__ == "__main__":
    main()
