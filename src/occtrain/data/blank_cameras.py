"""A dataset's view with every camera image black: what a camera-reading model scores when
its cameras show nothing (``occtrain eval --blank-cameras``).

A model that reads cameras has learned from them only if it scores lower without them; one
that scores the same reads its other inputs (the ego's motion, the past) or a prior. The
view is a dataset directory of its own, so every cache and shard keyed by a dataset (its
resolved path and fingerprint, ``data.shards.world_key``) keeps apart from the real one's:
the camera images are written black at their size and format, the generator record says
``"cameras": "blanked"`` (so the world's identity and name differ, ``data.identity.world_identity``),
and everything else (labels, annotations, sidecars, the synthetic class and depth maps, which
are training targets, not inputs) is a symbolic link to the source. Shards are built anew.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

from occtrain.data.layout import ANNOTATIONS_FILE, DATASET_FILE, DatasetIndex, generator_record
from occtrain.data.releases.files import place
from occtrain.errors import DataError
from occtrain.formats.io import write_error

#: Appended to the source folder's name: the view's folder, and so the eval directory of its scores.
BLANK_SUFFIX = "+blank_cameras"
#: Folders of the source the view does not take: built per dataset (shards) or nothing to read.
NOT_TAKEN = ("shards",)


def camera_images(index: DatasetIndex) -> set[Path]:
    """Every camera image the dataset's samples name (resolved within its root)."""
    return {r.image for scene, token in index.samples() for r in index.cameras(scene, token)}


def blank_camera_view(root: str | Path, into: str | Path) -> Path:
    """The view of the dataset at ``root`` with its cameras blanked, made once under ``into``
    (a folder per source world: the caller keys it) and reused: ``into/<name>+blank_cameras``.
    Made in a temporary folder and renamed into place, so a cut-off build leaves no half view,
    and two builds at once both end with the one view (the first rename wins). A place that
    cannot be written or an image that cannot be read is one line naming it."""
    index = DatasetIndex.open(root)
    source = index.root.resolve()
    if not index.has_cameras:
        raise DataError(f"{root}: the dataset has no camera images to blank")
    into = Path(into)
    view = into / f"{source.name}{BLANK_SUFFIX}"
    if (view / ANNOTATIONS_FILE).is_file():
        return view
    images = camera_images(index)
    outside = sorted(str(p) for p in images if source not in p.resolve().parents)
    if outside:
        raise DataError(
            f"{outside[0]}: a camera image outside the dataset root {source}; a blanked view mirrors the root"
        )
    try:
        into.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=into, prefix=".blank."))
    except OSError as err:
        raise write_error(view, err) from None
    try:
        _mirror(source, tmp, {p.resolve() for p in images}, (source / DATASET_FILE).resolve(), top=True)
        record = {**(generator_record(source) or {}), "cameras": "blanked"}
        (tmp / DATASET_FILE).parent.mkdir(parents=True, exist_ok=True)
        (tmp / DATASET_FILE).write_text(json.dumps(record, indent=2))
        try:
            tmp.rename(view)
        except OSError:
            if not (view / ANNOTATIONS_FILE).is_file():
                raise
            shutil.rmtree(tmp, ignore_errors=True)  # another build of the same view renamed first
    except BaseException as err:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(err, OSError):
            raise write_error(view, err) from None
        raise
    return view


def _mirror(src: Path, dst: Path, images: set[Path], record: Path, top: bool = False) -> None:
    """``dst`` as ``src`` with ``images`` written black and ``record`` left out (the caller
    writes its own); every other file the same bytes under a hard link (a copy where the
    filesystem has none): a dataset's files lie inside its root, and a symbolic link out of
    it is refused where it is read."""
    dst.mkdir(exist_ok=True)
    for entry in sorted(src.iterdir()):
        if top and entry.name in NOT_TAKEN:
            continue
        target, path = dst / entry.name, entry.resolve()
        if path == record:
            continue
        if path in images:
            _write_black(path, target)
        elif entry.is_dir():
            _mirror(entry, target, images, record)
        else:
            place(path, target)


def _write_black(image: Path, target: Path) -> None:
    """A black image of ``image``'s size, mode and format at ``target``."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(image) as img:
            img.load()  # a truncated file opens; its pixels do not
            size, mode, fmt = img.size, img.mode, img.format
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as err:
        raise DataError(
            f"{image}: unreadable camera image ({err}); re-create or re-download the dataset's images"
        ) from None
    Image.new(mode, size, 0).save(target, format=fmt)
