"""A stage's validation samples for the dashboard: BEV pictures and generated texts with references.

Layout (written by :func:`write_samples`, read by :func:`read_samples`)::

    <stage>/samples/index.json   {"images": [{"file": "bev_val_0.png", "caption": "..."}],
                                  "texts":  [{"task": "qa", "prompt": "...", "prediction": "...",
                                              "reference": "..."}]}
    <stage>/samples/*.png        the pictures index.json names, RGB
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from occtrain.data.render import render_bev, strip
from occtrain.errors import DataError
from occtrain.formats.io import atomic_write_bytes, atomic_write_json, parse_json, png_bytes, remove_inside
from occtrain.formats.occ3d import FREE, GRID_SHAPE

SAMPLES_DIR = "samples"
INDEX_FILE = "index.json"
TEXT_KEYS = ("task", "prompt", "prediction", "reference")
_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*\.png$")


def write_samples(stage_dir: Path, images: Sequence[tuple[str, np.ndarray]], texts: Sequence[dict[str, Any]]) -> Path:
    """Replace ``stage_dir/samples`` with these pictures and texts; returns the index path.

    ``images``: (caption, (H, W, 3) uint8 array) pairs, saved as ``sample_<i>.png``;
    ``texts``: dicts with ``task``, ``prompt``, ``prediction`` and ``reference`` strings.
    Every file is written atomically and the index last, so a reader sees the old set or the new one.
    """
    out = Path(stage_dir) / SAMPLES_DIR
    entries, clean_texts = [], []
    for i, (caption, image) in enumerate(images):
        name = f"sample_{i}.png"
        if np.asarray(image).ndim != 3:
            raise ValueError(f"a sample image must be (H, W, 3) uint8, got {np.asarray(image).shape}")
        atomic_write_bytes(out / name, png_bytes(image, optimize=True))
        entries.append({"file": name, "caption": str(caption)})
    for i, t in enumerate(texts):
        missing = [k for k in TEXT_KEYS if k not in t]
        if missing:
            raise ValueError(f"sample text {i} lacks {', '.join(missing)}; each needs {', '.join(TEXT_KEYS)}")
        clean_texts.append({k: str(t[k]) for k in TEXT_KEYS})
    index = atomic_write_json(out / INDEX_FILE, {"images": entries, "texts": clean_texts})
    listed = {e["file"] for e in entries}
    for stale in out.glob("*.png"):
        if stale.name not in listed:
            remove_inside(stale, out)
    return index


def read_samples(stage_dir: Path) -> tuple[list[tuple[str, bytes]], list[dict[str, str]]]:
    """(caption, PNG bytes) pairs and text records of a stage; empty when it wrote none.

    Raises :class:`DataError` naming the file when the index or a picture it names is unreadable.
    """
    path = Path(stage_dir) / SAMPLES_DIR / INDEX_FILE
    if not path.is_file():
        return [], []
    try:
        raw = parse_json(path.read_text())
        image_entries, text_entries = list(raw.get("images", [])), list(raw.get("texts", []))
        texts = [{k: str(t.get(k, "")) for k in TEXT_KEYS} for t in text_entries]
        names = [(str(e["file"]), str(e.get("caption", ""))) for e in image_entries]
    except (ValueError, AttributeError, KeyError, TypeError) as err:
        raise DataError(
            f"{path}: unreadable samples index ({err}); re-run the stage's validation to rewrite it"
        ) from None
    images = []
    for name, caption in names:
        png = path.parent / name
        if not _SAFE_NAME.match(name) or not png.is_file():
            raise DataError(f"{path}: names picture '{name}', which is not a PNG beside it")
        data = png.read_bytes()
        if not data.startswith(b"\x89PNG\r\n\x1a\n"):
            raise DataError(f"{png}: not a PNG file; re-run the stage's validation to rewrite it")
        images.append((caption, data))
    return images, texts


def bev_comparison(rows: Sequence[tuple], scale: int | None = None) -> np.ndarray:
    """Labelled bird's-eye panels side by side (e.g. ground truth, reconstruction, forecast).

    ``rows``: (label, semantics (200, 200, 16) class ids) pairs, or (label, semantics,
    {"truth": (N, 2), "plan": (M, 2)}) to draw trajectories (ego frame, metres); returns an
    (H, W, 3) uint8 picture with a legend of the classes that appear. Panels are drawn at
    2 px per voxel, 1 px when there are more than three (the picture stays page-wide).
    """
    if not rows:
        raise ValueError("bev_comparison needs at least one (label, semantics) panel")
    scale = scale or (2 if len(rows) <= 3 else 1)
    panels, present = [], set()
    for label, sem, *extra in rows:
        sem = np.asarray(sem)
        if sem.shape != GRID_SHAPE:
            raise ValueError(f"panel '{label}': semantics shape {sem.shape}, expected {GRID_SHAPE}")
        paths = extra[0] if extra else {}
        panels.append(render_bev(sem, scale=scale, title=label, trajectory=paths.get("truth"), plan=paths.get("plan")))
        present.update(np.unique(sem).tolist())
    classes = sorted(c for c in present if c != FREE)
    return np.asarray(strip(panels, classes or None))
