"""``occtrain data shards``: a dataset's frames and clips written as webdataset shards."""

from __future__ import annotations

from pathlib import Path


def shards(
    dataset: str | Path,
    out: str | Path,
    samples_per_shard: int,
    history: int,
    future: int,
    kinds: list[str] | None,
    rebuild: bool,
) -> None:
    """Write the shards and list what each split holds."""
    from occtrain.data.shards import no_clips_note, write_shards
    from occtrain.formats.io import check_output
    from occtrain.progress import console

    check_output(out, "--out", kind="dir")  # an unwritable --out fails now, not after minutes of sharding
    index = write_shards(dataset, out, samples_per_shard, history, future, kinds, rebuild=rebuild)
    if "clips" in index.get("missing", {}):
        console.print(f"note: {no_clips_note(index['missing']['clips'])}", markup=False)
    for kind, splits in index["kinds"].items():
        for split, entries in splits.items():
            n = sum(e["samples"] for e in entries)
            console.print(f"{kind:6s} {split:5s}: {n:5d} samples in {len(entries)} shards")
    console.print(f"shards -> {out}")
