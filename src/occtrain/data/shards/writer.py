"""Writing shard sets: each split's samples into size-bounded tars, the index last, and
``--rebuild`` as a replacement beside the old set that a kill never half-finishes."""

from __future__ import annotations

import glob
import io
import json
import os
import re
import shlex
import socket
import tempfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import webdataset as wds

from occtrain.data.clips import clip_annotation
from occtrain.data.layout import SPLITS, DatasetIndex
from occtrain.data.shards.entries import INDEX_FILE, KINDS, PACKED_MASKS, pack_mask
from occtrain.data.shards.freshness import clip_shortfall, current_shards, shard_source
from occtrain.errors import DataError
from occtrain.formats.io import atomic_write_json, npz_bytes, remove_inside, write_error
from occtrain.progress import console, progress_bar


class _ShardSink:
    """Writes numbered tar shards atomically (temp name, renamed when closed)."""

    def __init__(self, out_dir: Path, prefix: str, per_shard: int):
        self.out_dir, self.prefix, self.per_shard = out_dir, prefix, per_shard
        self.shards: list[dict] = []
        self._writer: wds.TarWriter | None = None
        self._count = 0

    def write(self, sample: dict) -> None:
        if self._writer is None or self._count >= self.per_shard:
            self._close()
            name = f"{self.prefix}-{len(self.shards):06d}.tar"
            self._tmp = self.out_dir / f".{name}.tmp"
            self._writer = wds.TarWriter(str(self._tmp))
            self.shards.append({"file": name, "samples": 0})
            self._count = 0
        self._writer.write(sample)
        self._count += 1
        self.shards[-1]["samples"] += 1

    def _close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._tmp.replace(self.out_dir / self.shards[-1]["file"])
            # Its size: a shard cut short or gone since is found before a run reads it.
            self.shards[-1]["bytes"] = (self.out_dir / self.shards[-1]["file"]).stat().st_size
            self._writer = None

    def close(self) -> list[dict]:
        self._close()
        return self.shards

    def discard(self) -> None:
        """Remove every file this sink wrote (a failed write leaves nothing behind)."""
        if self._writer is not None:
            try:
                self._writer.close()
            except Exception:
                pass  # the write already failed; the temp file goes below either way
            self._writer = None
            self._tmp.unlink(missing_ok=True)
        for shard in self.shards:
            (self.out_dir / shard["file"]).unlink(missing_ok=True)


def _camera_entries(index: DatasetIndex, scene: str, token: str) -> dict[str, bytes]:
    """A sample's camera files, byte for byte, and its calibration; {} without cameras."""
    if not index.has_cameras:
        return {}
    out: dict[str, bytes] = {}
    records = index.cameras(scene, token)
    for r in records:
        stem, ext = r.name.lower(), r.image.suffix.lower().lstrip(".")
        if ext not in ("png", "jpg", "jpeg"):
            raise DataError(f"{r.image}: camera images must be PNG or JPEG")
        out[f"{stem}.{'jpg' if ext == 'jpeg' else ext}"] = _image_bytes(r.image)
        for part, extra in zip(("class", "depth"), r.maps):
            if extra.is_file():
                out[f"{stem}.{part}.png"] = _image_bytes(extra)
    calib = {
        "intrinsic": [r.intrinsic.tolist() for r in records],
        "cam_to_ego": [r.cam_to_ego.tolist() for r in records],
    }
    out["cams.json"] = json.dumps(calib).encode()
    return out


def _image_bytes(path: Path) -> bytes:
    """An image file's bytes, once its structure checked out (PNG chunk CRCs, JPEG markers):
    a damaged image is refused here, naming it, not met as a decode error mid-training."""
    from PIL import Image

    try:
        data = path.read_bytes()
    except OSError as err:
        raise DataError(
            f"{path}: cannot read it ({err.strerror}); the dataset's camera_sensor records name it"
        ) from None
    try:
        with Image.open(io.BytesIO(data)) as img:
            img.verify()
    except Exception as err:  # PIL raises SyntaxError, OSError, ValueError, struct.error, ...
        raise DataError(
            f"{path}: not a readable image ({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}); "
            "re-create it"
        ) from None
    return data


def _frame_sample(index: DatasetIndex, scene: str, token: str, position: int, split: str) -> dict:
    labels = index.labels(scene, token)
    arrays = {"semantics": labels["semantics"]}
    arrays.update({k: pack_mask(labels[k]) for k in PACKED_MASKS})
    meta = {"scene": scene, "token": token, "index": position, "split": split}
    return {
        "__key__": token,
        "occ.npz": npz_bytes(arrays),
        "meta.json": json.dumps(meta).encode(),
        **_camera_entries(index, scene, token),
    }


def _clip_samples(index: DatasetIndex, scene: str, split: str, history: int, future: int, qa: dict) -> Iterator[dict]:
    tokens = index.scenes[scene]
    frames = index.frames(scene) if index.has_frame_annotations(scene) else None
    cache: dict[str, dict[str, np.ndarray]] = {}
    for anchor in range(history, len(tokens) - future):
        ann = clip_annotation(index, scene, anchor, history, future, split, frames)
        window = ann["tokens"]
        for tok in list(cache):
            if tok not in window:
                del cache[tok]
        for tok in window:
            if tok not in cache:
                cache[tok] = index.labels(scene, tok)
        sem = np.stack([cache[t]["semantics"] for t in window])
        cam = np.stack([pack_mask(cache[t]["mask_camera"]) for t in window])
        yield {
            "__key__": tokens[anchor],
            "occ.npz": npz_bytes({"semantics": sem, "mask_camera": cam}),
            "ann.json": json.dumps(ann).encode(),
            "qa.json": json.dumps(qa.get(tokens[anchor], [])).encode(),
            "caption.txt": ann["anchor"].get("caption", "").encode(),
            "narration.txt": ann["anchor"].get("narration", "").encode(),
            **_camera_entries(index, scene, tokens[anchor]),
        }


def write_shards(
    dataset: str | Path,
    out: str | Path,
    samples_per_shard: int = 64,
    history: int = 4,
    future: int = 6,
    kinds: Iterable[str] | None = None,
    progress: Callable[[int], None] | None = None,
    rebuild: bool = False,
) -> dict:
    """Write frame and/or clip shards for both splits; returns the index written to ``out/index.json``.

    ``kinds`` None: frames, and clips when a train scene is long enough for one (the index
    then records why clips are ``missing``). An ``out`` that already holds shards of a
    different dataset or layout is refused; one that holds exactly these shards is left as
    it is. ``rebuild`` replaces whatever shards ``out`` holds, the old ones usable until the
    new ones are complete.
    """
    index = DatasetIndex.open(dataset)
    out = Path(out)
    source = shard_source(index, samples_per_shard, history, future, kinds)
    if rebuild:
        _check_rebuildable(out)
        _remove_killed_rebuilds(out)
    else:
        old = current_shards(index, out, source)
        _remove_killed_rebuilds(out)
        if old is not None:
            return old
    # Without kinds named, clips are left out only when none fits: the shortfall says why.
    shortfall = None if kinds is not None or "clips" in source["kinds"] else clip_shortfall(index, history, future)
    missing = {} if shortfall is None else {"clips": shortfall}
    written = [k for k in KINDS if k in source["kinds"]]

    def write(into: Path, advance: Callable[[int], None]) -> dict:
        return _write_shards(index, into, samples_per_shard, history, future, written, source, advance, missing)

    def write_all(advance: Callable[[int], None]) -> dict:
        if rebuild and out.is_dir() and any(out.iterdir()):
            return _replace_shards(out, lambda staging: write(staging, advance))
        return write(out, advance)

    if progress is None:  # no caller's bar: show one, so a log sees minutes of sharding move
        frames = sum(len(index.scenes[scene]) for split in SPLITS for scene in index.splits.get(split, []))
        with progress_bar(
            frames * len(written), f"writing {' and '.join(written)} shards of {frames} frames"
        ) as advance:
            return write_all(advance)
    return write_all(progress)


def _write_shards(
    index: DatasetIndex,
    out: Path,
    samples_per_shard: int,
    history: int,
    future: int,
    kinds: list[str],
    source: dict,
    progress: Callable[[int], None],
    missing: dict[str, str],
) -> dict:
    """:func:`write_shards` once the shards are known to be missing."""
    result: dict[str, Any] = {"source": source, "kinds": {}, **({"missing": missing} if missing else {})}
    new_dirs = [d for d in (out, *(out / k for k in kinds)) if not d.exists()]
    sinks: list[_ShardSink] = []
    try:
        for kind in kinds:
            (out / kind).mkdir(parents=True, exist_ok=True)
            result["kinds"][kind] = {}
            for split in SPLITS:
                sink = _ShardSink(out / kind, split, samples_per_shard)
                sinks.append(sink)
                _write_split(sink, index, kind, split, history, future, progress)
                result["kinds"][kind][split] = sink.close()
    except BaseException:
        # A bad label (or ^C) halfway: remove what this call wrote, so the next call does
        # not find shards without an index. `out` held no shards before (checked above).
        for sink in sinks:
            sink.discard()
        for d in reversed(new_dirs):
            if d.is_dir() and not any(d.iterdir()):
                d.rmdir()
        raise
    atomic_write_json(out / INDEX_FILE, result)
    return result


#: What a shard directory holds; --rebuild replaces nothing else.
_SHARD_ENTRIES = frozenset((INDEX_FILE, *KINDS))


def _check_rebuildable(out: Path) -> None:
    """--rebuild swaps the whole of ``out``: refuse it when ``out`` holds anything that is
    not a shard (a dataset, someone's files), which the swap would delete."""
    if not out.is_dir():
        return
    for entry in sorted(out.iterdir()):
        leftover = entry.name.startswith(".") and entry.name.endswith(".tmp")  # an interrupted atomic write
        if entry.name not in _SHARD_ENTRIES and not leftover:
            raise DataError(
                f"{out}: holds {entry.name}, which is not a shard file; --rebuild replaces the whole directory, "
                "so move it away first or choose another --out"
            )


def _replace_shards(out: Path, write: Callable[[Path], dict]) -> dict:
    """Write a new shard set beside ``out`` and swap it in only once complete (index.json
    written last): a failure or ^C halfway leaves the old shards as they were, usable.

    Writing over them in place would not: a new ``train-000000.tar`` under the old index
    is a shard set whose counts lie. The swap is two renames on one file system; the old
    set is deleted after them."""
    out = out.resolve()  # a link to the shards stays a link, to the new ones
    parent = out.parent
    try:
        staging = Path(tempfile.mkdtemp(dir=parent, prefix=_rebuild_prefix(out)))
        os.chmod(staging, out.stat().st_mode & 0o7777)  # mkdtemp's 0700 would replace the directory's own mode
    except OSError as err:
        raise write_error(out, err) from None
    try:
        result = write(staging)
    except BaseException:
        remove_inside(staging, parent)
        raise
    retired = staging.with_name(staging.name.replace(".rebuild-", ".replaced-"))
    out.rename(retired)
    try:
        staging.rename(out)
    except OSError as err:
        retired.rename(out)  # the old shards back where they were
        remove_inside(staging, parent)
        raise write_error(out, err) from None
    remove_inside(retired, parent)
    return result


def _rebuild_prefix(out: Path) -> str:
    """``.OUT.rebuild-PID.HOST-``: a staging folder's name says whose it is, so that once a
    kill -9 left it behind, a later command can tell it from one a live rebuild is writing."""
    return f".{out.name}.rebuild-{os.getpid()}.{socket.gethostname()}-"


#: A staging folder (or the old shards between the swap's two renames) and its owner.
_REBUILD_NAME = re.compile(r"\.(?P<out>.+)\.(?:rebuild|replaced)-(?:(?P<pid>\d+)\.(?P<host>.+)-)?[^-]+")


@dataclass(frozen=True)
class LeftoverRebuild:
    """A folder beside a shard directory that a ``--rebuild`` of it wrote and did not finish."""

    path: Path
    out: Path
    #: Its process and machine; None for a folder named before they were recorded.
    pid: int | None
    host: str | None

    @property
    def stopped(self) -> bool:
        """Its process is gone: nothing will finish or remove the folder."""
        return self.pid is not None and self.host == socket.gethostname() and not _alive(self.pid)

    @property
    def running(self) -> bool:
        """Its process, on this machine, is still there (writing it, or about to remove it)."""
        return self.pid is not None and self.host == socket.gethostname() and _alive(self.pid)

    def problem(self) -> str:
        what = f"{self.path}: left by an `occtrain data shards --rebuild` of {self.out} that"
        remove = f"remove it with `rm -r {shlex.quote(str(self.path))}`"
        if self.stopped:
            return (
                f"{what} was stopped (pid {self.pid} on {self.host} is gone); {remove} (the next `occtrain data "
                f"shards` of {self.out} removes it too)"
            )
        by = f" (pid {self.pid} on {self.host})" if self.pid is not None else ""
        return f"{what} has not finished; unless that rebuild{by} is still running, {remove}"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    except (OverflowError, ValueError):  # no process can have such a number
        return False
    return True


def leftover_rebuilds(folder: str | Path, out: str | None = None) -> list[LeftoverRebuild]:
    """The folders unfinished ``--rebuild`` runs left in ``folder`` (of the shard directory
    ``folder/out`` alone, when given), stopped or still running, each with its owner."""
    folder = Path(folder).resolve()
    if not folder.is_dir():
        return []
    found = []
    for path in sorted(folder.glob(f".{glob.escape(out) if out else '*'}.re*-*")):
        named = _REBUILD_NAME.fullmatch(path.name)
        if named and (out is None or named["out"] == out) and path.is_dir() and not path.is_symlink():
            pid = int(named["pid"]) if named["pid"] else None
            found.append(LeftoverRebuild(path, folder / named["out"], pid, named["host"]))
    return found


def _remove_killed_rebuilds(out: Path) -> None:
    """Remove what rebuilds of ``out`` killed on this machine left beside it (a live one's
    folder, or another machine's, stays), each with a note."""
    out = out.resolve()  # as _replace_shards names its folders
    for leftover in leftover_rebuilds(out.parent, out.name):
        if leftover.stopped and remove_inside(leftover.path, leftover.path.parent):
            console.print(
                f"note: removed {leftover.path}, left by a `--rebuild` of {out} that was stopped (pid {leftover.pid})",
                markup=False,
            )


def _write_split(
    sink: _ShardSink,
    index: DatasetIndex,
    kind: str,
    split: str,
    history: int,
    future: int,
    progress: Callable[[int], None] | None,
) -> None:
    """Every sample of one kind and split, into ``sink``."""
    if kind == "frames":
        for scene, token in index.samples(split):
            sink.write(_frame_sample(index, scene, token, index.scenes[scene].index(token), split))
            if progress:
                progress(1)
        return
    qa = index.questions_by_sample(split)
    for scene in index.splits[split]:
        for sample in _clip_samples(index, scene, split, history, future, qa):
            sink.write(sample)
        if progress:
            progress(len(index.scenes[scene]))
