"""``occtrain data show``: a bird's-eye picture of a dataset frame (or several) as PNG."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from occtrain.data.cameras import CAMERA_NAMES
from occtrain.data.clips import pose_anchor
from occtrain.data.labels import load_labels
from occtrain.data.layout import DatasetIndex
from occtrain.data.render import render_bev, strip, surround
from occtrain.errors import DataError
from occtrain.formats.occ3d import FRAME_DT, FREE
from occtrain.progress import console


def show(
    path: str | Path,
    out: str | Path,
    scene: str | None = None,
    index: int = 0,
    frames: int = 1,
    scale: int = 3,
    overwrite: bool = False,
) -> Path:
    """Render ``frames`` consecutive frames starting at ``index`` of ``scene`` (default: the
    first val scene, named on the console); returns the PNG path. An existing ``out`` is
    replaced only with ``overwrite``.

    ``path`` is a dataset root (the ego's future trajectory is drawn when the sidecar has it,
    the six camera views around each frame when the dataset has them) or a single ``labels.npz``.
    """
    path, out = Path(path), Path(out)
    chosen = ""  # the scene show picked, said once the picture exists
    if scale < 1:
        raise DataError(f"--scale {scale}: must be at least 1 pixel per voxel")
    if frames < 1:
        raise DataError(f"--frames {frames}: draw at least 1 frame")
    if out.is_dir():
        raise DataError(f"{out}: is a directory; --out takes a .png file name")
    if out.exists() and not overwrite:
        raise DataError(f"{out}: exists; pass --overwrite to replace it, or choose another --out")
    if path.suffix == ".npz":
        labels = load_labels(path, require_masks=False)
        pictures = [render_bev(labels["semantics"], labels.get("mask_camera"), scale=scale, title=path.parent.name)]
        classes = np.unique(labels["semantics"]).tolist()
    else:
        pictures, classes, chosen = _dataset_pictures(path, scene, index, frames, scale)
    image = strip(pictures, [int(c) for c in classes if c != FREE])
    tmp = out.with_name(f".{out.name}.tmp.png")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        image.save(tmp)
        tmp.replace(out)
    except OSError as err:
        if tmp.parent.is_dir():  # a parent that is a file is why it failed; nothing to clean then
            tmp.unlink(missing_ok=True)
        raise DataError(f"{out}: cannot write the picture ({err.strerror or err}); choose another --out") from None
    if chosen:  # said once the picture exists: a failed call prints its one error line alone
        console.print(chosen)
    return out


def _dataset_pictures(
    path: Path, scene: str | None, index: int, frames: int, scale: int
) -> tuple[list, list[int], str]:
    """The frames' pictures, the classes they show, and which scene was chosen for the user
    ("" when they named one)."""
    chosen = ""
    ds = DatasetIndex.open(path)
    if not ds.scenes:
        raise DataError(f"{path}: the dataset has no scenes")
    if scene is None:
        scene = next(iter(ds.splits["val"] or ds.scenes))
        chosen = f"scene {scene} (the first {'val ' if ds.splits['val'] else ''}scene; --scene picks another)"
    if scene not in ds.scenes:
        raise DataError(f"{path}: no scene '{scene}'; scenes are {', '.join(list(ds.scenes)[:8])}...")
    tokens = ds.scenes[scene]
    if not 0 <= index < len(tokens):
        raise DataError(f"{path}: scene '{scene}' has frames 0..{len(tokens) - 1}, not {index}")
    annotated = ds.frames(scene) if ds.has_frame_annotations(scene) else None
    pictures, seen = [], set()
    for i in range(index, min(index + frames, len(tokens))):
        labels = ds.labels(scene, tokens[i])
        ann = annotated[i] if annotated else pose_anchor(ds, scene, i)  # without the sidecar the poses give the path
        bev = render_bev(
            labels["semantics"],
            labels["mask_camera"],
            trajectory=ann["ego_future"],
            trajectory_mask=ann["ego_future_mask"],
            scale=scale,
            title=f"{scene} #{i}  t={i * FRAME_DT:.1f}s" + (f"  {ann['command']}" if "command" in ann else ""),
        )
        if ds.has_cameras:
            views = dict(zip(CAMERA_NAMES, ds.images(scene, tokens[i])))
            bev = surround(views, bev)
        pictures.append(bev)
        seen.update(np.unique(labels["semantics"]).tolist())
    classes = sorted(seen)
    return pictures, classes, chosen
