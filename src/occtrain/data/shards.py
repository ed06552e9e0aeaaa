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
"""

from __future__ import annotations

import glob
import hashlib
import io
import json
import os
import re
import shlex
import socket
import tarfile
import tempfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NotRequired, TypedDict

import numpy as np
import webdataset as wds

from occtrain.data.clips import clip_annotation
from occtrain.data.layout import CLASS_SUFFIX, DEPTH_SUFFIX, FRAMES_DIR, SPLITS, DatasetIndex, qa_file, read_npz
from occtrain.data.reading import PAD_KEY, ShardSamples
from occtrain.data.validate import first_problem
from occtrain.errors import DataError
from occtrain.formats.io import atomic_write_json, npz_bytes, parse_json, rank_world, remove_inside, write_error
from occtrain.formats.occ3d import GRID_SHAPE
from occtrain.progress import console, progress_bar

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


# ----------------------------------------------------------------------------- writing


def _pack(mask: np.ndarray) -> np.ndarray:
    return np.packbits(mask.astype(bool), axis=-1)


def unpack_mask(packed: np.ndarray) -> np.ndarray:
    """Inverse of the bit-packing applied to masks in shards: uint8 0/1 of grid shape."""
    return np.unpackbits(packed, axis=-1, count=GRID_SHAPE[-1])


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


class ShardEntry(TypedDict):
    file: str  # a file name inside SHARDS/<kind>/
    samples: int


class ShardIndex(TypedDict):
    """``SHARDS/index.json``: what the shards were made from, and the shards of each kind and split."""

    source: dict[str, Any]
    kinds: dict[str, dict[str, list[ShardEntry]]]
    #: Kinds left out although asked for by default, and why (clips no scene is long enough for).
    missing: NotRequired[dict[str, str]]


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
    arrays.update({k: _pack(labels[k]) for k in PACKED_MASKS})
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
        cam = np.stack([_pack(cache[t]["mask_camera"]) for t in window])
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
    missing = (
        {} if kinds is not None or "clips" in source["kinds"] else {"clips": clip_shortfall(index, history, future)}
    )
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


# ----------------------------------------------------------------------------- --rebuild

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


# ----------------------------------------------------------------------------- which shards are current


def current_shards(index: DatasetIndex, out: Path, source: dict) -> dict | None:
    """The index of the shards in ``out`` when they were made from ``source`` (the dataset
    as it is now, this layout); None when ``out`` holds none. Anything else is refused in
    one line that says what is true and what to do, for whichever command met it (`data
    shards`, `run`, `validate`): shards of another dataset, or of this one before it
    changed, are never read."""
    if (out / INDEX_FILE).is_file():
        old = read_index(out)
        made = old.get("source", {})
        if _same_content(index, made, source):
            return old
        raise DataError(_why_not_current(index, out, made, source))
    if out.exists() and any(p.suffix == ".tar" for p in out.rglob("*.tar")):
        raise DataError(
            f"{out}: holds shards without an {INDEX_FILE} (an interrupted write?); {_redo(index, out, source)}"
        )
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


# ----------------------------------------------------------------------------- what shards are made of


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


# ----------------------------------------------------------------------------- reading


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
    :mod:`occtrain.data.reading`).

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


__all__ = [
    "ALLOWED_EXTENSIONS",
    "KINDS",
    "PAD_KEY",
    "LeftoverRebuild",
    "decode_sample",
    "leftover_rebuilds",
    "make_pipeline",
    "read_index",
    "read_npz",
    "shard_urls",
    "unpack_mask",
    "write_shards",
]
