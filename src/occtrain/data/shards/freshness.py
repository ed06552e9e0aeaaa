"""Whether the shards in a folder are those a dataset would write now: the dataset's
fingerprint and content key, what a shard set is made from (``shard_source``), and why a
set is not current."""

from __future__ import annotations

import hashlib
import json
import shlex
from collections.abc import Iterable, Iterator
from pathlib import Path

from occtrain.data.camera_records import CLASS_SUFFIX, DEPTH_SUFFIX
from occtrain.data.layout import FRAMES_DIR, SPLITS, DatasetIndex, qa_file
from occtrain.data.shards.entries import DEFAULT_LAYOUT, FINGERPRINT_VERSION, INDEX_FILE, KINDS
from occtrain.data.shards.reader import read_index
from occtrain.errors import DataError


def dataset_fingerprint(index: DatasetIndex, version: int = 2) -> str:
    """A hash of everything shards are made from: annotations.json and the generator record
    by content, every labels file, camera image, sidecar and QA file by size and mtime.

    Editing any of them (a relabelled ``labels.npz``, a re-rendered image) changes it, so
    shards and caches made before the edit are refused, never read. Size and mtime, like
    make: the cost grows with the file count, not with the bytes, which for a real release
    with its camera images are tens of GB (``tools/bench/data.py fingerprint``).

    Version 3 (what shard indexes record) names a missing file (an absent QA sidecar, the
    class and depth maps real images lack) relative to the root, as it names present ones,
    so a dataset moved elsewhere keeps its fingerprint; version 2 named it by its absolute
    path, and stays the default of the caches keyed by it."""
    h = hashlib.sha256((index.root / "annotations.json").read_bytes())
    if index.generator:
        h.update(json.dumps(index.generator, sort_keys=True).encode())
    for path in source_files(index):
        try:
            st = path.stat()
            h.update(f"{path.relative_to(index.root)}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
        except FileNotFoundError:
            h.update(f"{path if version < 3 else path.relative_to(index.root)}\0missing\n".encode())
    return h.hexdigest()[:16]


def world_key(root: str | Path) -> str:
    """Names the dataset at ``root`` as it is now (its resolved path and fingerprint): caches
    and metrics made from a world live under its key, so another world (same folder name,
    another place) or the same one edited since never meets them."""
    index = DatasetIndex.open(root)
    return hashlib.sha256(f"{index.root.resolve()}\0{dataset_fingerprint(index)}".encode()).hexdigest()[:12]


def source_files(index: DatasetIndex) -> Iterator[Path]:
    """Every file a shard of ``index`` may be made from (labels, images and their maps, sidecars)."""
    for scene, token in index.samples():
        yield index.labels_path(scene, token)
        for record in (index.info(scene, token).get("camera_sensor") or {}).values():
            image = index.image_path(record["img_path"])
            yield image
            yield from (image.with_name(f"{image.stem}{suffix}.png") for suffix in (CLASS_SUFFIX, DEPTH_SUFFIX))
    for scene in index.scenes:
        yield index.root / FRAMES_DIR / f"{scene}.json"
    for split in SPLITS:
        yield index.root / qa_file(split)


def current_shards(index: DatasetIndex, out: Path, source: dict) -> dict | None:
    """The index of the shards in ``out`` when they were made from ``source`` (the dataset
    as it is now, this layout); None when ``out`` holds none. Anything else is refused in
    one line that says what is true and what to do, for whichever command met it (`data
    shards`, `run`, `validate`): shards of another dataset, or of this one before it
    changed, are never read."""
    if (out / INDEX_FILE).is_file():
        old = read_index(out)
        made = old.get("source", {})
        if not _same_content(index, made, source):
            raise DataError(_why_not_current(index, out, made, source))
        damaged = _damaged_shard(out, old)
        if damaged:
            raise DataError(f"{damaged}; {_redo(index, out, source)}")
        return old
    if out.exists() and any(p.suffix == ".tar" for p in out.rglob("*.tar")):
        raise DataError(
            f"{out}: holds shards without an {INDEX_FILE} (an interrupted write?); {_redo(index, out, source)}"
        )
    return None


def _damaged_shard(out: Path, index: dict) -> str | None:
    """The first shard ``index`` lists that is gone or not the size it was written at (an
    index of shards from before sizes were recorded: only whether it is there)."""
    for kind, splits in index.get("kinds", {}).items():
        for entries in splits.values():
            for entry in entries:
                path = out / kind / entry["file"]
                if not path.is_file():
                    return f"{path}: a shard {INDEX_FILE} lists is missing"
                size = path.stat().st_size
                if "bytes" in entry and size != entry["bytes"]:
                    return f"{path}: {size} bytes where {INDEX_FILE} recorded {entry['bytes']} (cut short or changed)"
    return None


_CONTENT_KEYS = ("dataset", "fingerprint", "fingerprint_version")


def _layout(source: dict) -> dict:
    return {k: v for k, v in source.items() if k not in _CONTENT_KEYS}


def _same_content(index: DatasetIndex, made: dict, source: dict) -> bool:
    """Whether shards made as ``made`` records are what ``source`` would write now.

    The dataset's path is left out on purpose: a shard holds no path, only what the files
    hold, so shards of a dataset moved or copied with its files' times kept (``mv``,
    ``cp -a``) are byte for byte those this copy would write, and are accepted as they are
    (not re-pointed: `validate` writes nothing, and every copy with this fingerprint may
    read them alike). A plain ``cp -r`` gives every file a new mtime, hence a new
    fingerprint, and cannot be told from an edit without reading every byte (tens of GB
    with images): refused, with the way to rebuild them."""
    if _layout(made) != _layout(source):
        return False
    if made.get("fingerprint_version") == source["fingerprint_version"]:
        return made.get("fingerprint") == source["fingerprint"]
    # Shards of an earlier occtrain (version 2: missing files named by absolute path) stay
    # current where they were made, as long as the dataset there has not changed.
    return (
        made.get("fingerprint_version") == 2
        and made.get("dataset") == source["dataset"]
        and (made.get("fingerprint") == dataset_fingerprint(index, version=2))
    )


def _why_not_current(index: DatasetIndex, out: Path, made: dict, source: dict) -> str:
    """The one line refusing shards that :func:`_same_content` found are not these."""
    redo = _redo(index, out, source)
    if made.get("dataset") == source["dataset"] and "fingerprint_version" not in made:
        return f"{out}: shards of an older occtrain, whose fingerprint saw annotations.json alone; {redo}"
    if _layout(made) != _layout(source):
        differ = "; ".join(
            f"{k} {made[k]} there, {source[k]} here" for k in _layout(source) if k in made and made[k] != source[k]
        )
        return f"{out}: already holds shards of a different dataset or layout{f' ({differ})' if differ else ''}; {redo}"
    if made.get("dataset") == source["dataset"]:
        return (
            f"{out}: its shards were made before {index.root} changed "
            f"(a labels, image, sidecar or annotations file differs); {redo}"
        )
    return (
        f"{out}: its shards were made from {made.get('dataset')}, and {index.root} is not that dataset as it was then "
        f"(another dataset, a copy whose files got new times as `cp -r` gives them, or one edited since); {redo}"
    )


def _redo(index: DatasetIndex, out: Path, source: dict) -> str:
    """What to do about shards that are not current: true for `data shards` (which has
    --out and --rebuild) and for `run` or `validate` (which write them again once gone)."""
    flags = [f"--{k.replace('_', '-')} {source[k]}" for k, default in DEFAULT_LAYOUT.items() if source[k] != default]
    if sorted(source["kinds"]) != sorted(KINDS):
        flags.append(f"--kinds {','.join(source['kinds'])}")
    command = " ".join(
        ["occtrain data shards", shlex.quote(str(index.root)), "--out", shlex.quote(str(out)), *flags, "--rebuild"]
    )
    return f"delete {out} and they are written again, or replace them with `{command}`"


def clip_shortfall(index: DatasetIndex, history: int, future: int) -> str | None:
    """Why no clip of ``history`` + 1 + ``future`` frames fits the train scenes; None when one does."""
    longest = max((len(index.scenes[s]) for s in index.splits["train"]), default=0)
    if longest >= history + 1 + future:
        return None
    return (
        f"{index.root}: its longest train scene has {longest} frames and a clip spans history {history} + 1 + "
        f"future {future} = {history + 1 + future}"
    )


def no_clips_note(shortfall: str) -> str:
    """The line that says shards were (or will be) made without clips, and who cannot train on them."""
    return (
        f"{shortfall}, so no clip fits: frame shards only, which tokenizer stages train on; the world-model "
        "stages (pretrain, instruct, planner, distill) read clips and cannot train on this dataset "
        "(use longer scenes or a shorter history/future)"
    )


def shard_source(
    index: DatasetIndex,
    samples_per_shard: int,
    history: int,
    future: int,
    kinds: Iterable[str] | None = None,
) -> dict:
    """What a shard set of ``index`` with this layout is made from (checked), as its index
    records it. ``kinds`` None: frames, and clips when one fits (see :func:`write_shards`);
    clips asked for by name and fitting no scene are refused."""
    for name, value, least in (
        ("samples_per_shard", samples_per_shard, 1),
        ("history", history, 0),
        ("future", future, 0),
    ):
        if not isinstance(value, int) or isinstance(value, bool) or value < least:
            raise DataError(f"{name} is {value!r}; it must be a whole number of at least {least}")
    shortfall = clip_shortfall(index, history, future)
    if kinds is None:
        kinds = ["frames"] if shortfall else list(KINDS)
    kinds = list(kinds)
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise DataError(f"unknown shard kind '{unknown[0]}'; choose from {', '.join(KINDS)}")
    if "clips" in kinds:
        _check_sidecars(index)
        if shortfall:
            raise DataError(
                f"{shortfall}, so there would be no clip to train on; use longer scenes, a shorter history/future, or "
                "--kinds frames"
            )
    index.has_cameras  # noqa: B018 - refuses a missing camera folder before a shard is written, naming it
    return {
        "dataset": str(index.root.resolve()),
        "fingerprint": dataset_fingerprint(index, FINGERPRINT_VERSION),
        # 2: the fingerprint covers every source file (1, unrecorded: annotations.json alone);
        # 3: it names a missing one relative to the root, so a moved dataset keeps it.
        "fingerprint_version": FINGERPRINT_VERSION,
        "samples_per_shard": samples_per_shard,
        "history": history,
        "future": future,
        "kinds": sorted(kinds),
    }


def _check_sidecars(index: DatasetIndex) -> None:
    """Read every sidecar a clip is made from before the first shard is written: a problem
    (or a scene without a frame sidecar among scenes with one) is a DataError now, not a
    KeyError in training."""
    scenes = [s for split in SPLITS for s in index.splits[split]]
    present = [s for s in scenes if index.has_frame_annotations(s)]
    if present and len(present) < len(scenes):
        lacking = next(s for s in scenes if s not in present)
        path = index.root / FRAMES_DIR / f"{lacking}.json"
        raise DataError(
            f"{path}: missing while {len(present)} other scenes have their frame sidecar; write it or delete them all"
        )
    for scene in present:
        index.frames(scene)
    for split in SPLITS:
        index.questions(split)
