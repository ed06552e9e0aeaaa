"""``occtrain data stats``: what a dataset's voxels look like, beside Occ3D-nuScenes.

Any release in the Occ3D layout, real or synthesized, is read the same way: the labels of
a split's frames (all of them, or an evenly spaced subset) are counted, and each figure is
set beside what a real Occ3D-nuScenes frame or its training set shows
(:data:`occtrain.formats.occ3d.OCC3D_FRAME` and :data:`occtrain.formats.occ3d.OCC3D_TRAIN_VOXELS`). It is how
a user sees whether data they train on, ours or their own, looks like what the papers
trained on.

Per-frame shares are averaged over frames (each frame counts once, as the targets are
stated); class shares are of the occupied voxels of all the counted frames together, as the
training-set counts are.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from occtrain.data.identity import world_version
from occtrain.data.layout import DatasetIndex
from occtrain.errors import DataError
from occtrain.formats.occ3d import CLASS_NAMES, FREE, GRID_SHAPE, OCC3D_FRAME, OCC3D_TRAIN_VOXELS
from occtrain.progress import progress_bar

#: The lowest layers, where a real frame's ground lies (ground, kerbs, the feet of things).
LOW_LAYERS = 3

#: The ranges a dataset that looks like Occ3D-nuScenes falls in (means over frames), set
#: around the real frame's figures wide enough for a city's variety: the embedded world
#: is held to them (tests/unit/data/synth/test_synth.py), and any dataset is shown against them.
TARGETS: dict[str, tuple[float, float]] = {
    "occupied": (0.04, 0.10),
    "occupied_columns": (0.25, 0.60),
    "low_layers": (0.30, 0.60),
    "mask_lidar": (0.05, 0.15),
    "mask_camera": (0.04, 0.12),
    "camera_inside_lidar": (1.0, 1.0),
    "occupied_in_camera": (0.30, 0.70),
}
#: Classes whose share of the occupied voxels should lie within a factor of
#: CLASS_FACTOR of the training set's.
TARGET_CLASSES = ("driveable_surface", "vegetation", "manmade", "terrain", "sidewalk", "car")
CLASS_FACTOR = 2.0


def within(key: str, value: float) -> bool | None:
    """Whether a figure lies in its target range (None: the figure has no target)."""
    if key not in TARGETS:
        return None
    lo, hi = TARGETS[key]
    return lo - 1e-9 <= value <= hi + 1e-9


@dataclass(frozen=True)
class DatasetStats:
    """A dataset's voxel statistics (shares in [0, 1]); see the module docstring."""

    root: str
    split: str
    frames: int
    #: The synthetic world's version from ``occtrain/dataset.json`` ("v4"), or "" for data
    #: occtrain did not synthesize.
    world: str
    #: Non-free voxels among all of a frame's voxels.
    occupied: float
    #: x-y columns holding any non-free voxel, and non-free voxels per such column.
    occupied_columns: float
    voxels_per_column: float
    #: Non-free voxels in the lowest :data:`LOW_LAYERS` layers, of all non-free voxels.
    low_layers: float
    #: Per z layer (bottom first): its non-free voxels among the voxels of that layer.
    per_layer: list[float]
    mask_lidar: float
    mask_camera: float
    #: mask_camera voxels that mask_lidar holds too (Occ3D's camera mask lies inside it).
    camera_inside_lidar: float
    #: Non-free voxels among the voxels each mask holds.
    occupied_in_lidar: float
    occupied_in_camera: float
    #: Class name -> its share of all non-free voxels of the counted frames.
    class_shares: dict[str, float]

    def to_json(self) -> dict[str, Any]:
        return {**asdict(self), "reference": reference_json(), "targets": self.targets()}

    def targets(self) -> dict[str, bool]:
        """Figure (or ``class:<name>``, ``all_classes_present``) -> whether it meets its target."""
        met = {key: bool(within(key, getattr(self, key))) for key in TARGETS}
        ref = reference_class_shares()
        for name in TARGET_CLASSES:
            ratio = self.class_shares[name] / ref[name]
            met[f"class:{name}"] = 1 / CLASS_FACTOR <= ratio <= CLASS_FACTOR
        met["all_classes_present"] = all(v > 0 for v in self.class_shares.values())
        return met


def reference_class_shares() -> dict[str, float]:
    """Occ3D-nuScenes' training-set share of each class among the occupied voxels."""
    counts = np.asarray(OCC3D_TRAIN_VOXELS[:FREE], dtype=np.float64)
    return {name: float(c) for name, c in zip(CLASS_NAMES[:FREE], counts / counts.sum())}


def reference_json() -> dict[str, Any]:
    return {"frame": dict(OCC3D_FRAME), "train_class_shares": reference_class_shares()}


def pick_frames(index: DatasetIndex, split: str, frames: int) -> list[tuple[str, str]]:
    """``frames`` samples of ``split`` spread evenly over it in scene order (-1: every one)."""
    samples = list(index.samples(split))
    if not samples:
        raise DataError(f"{index.root}: split '{split}' has no frames; choose another --split")
    if frames == -1 or frames >= len(samples):
        return samples
    if frames < 1:
        raise DataError(f"--frames {frames}: count at least 1 frame, or -1 for every frame of the split")
    return [samples[i] for i in np.linspace(0, len(samples) - 1, frames).round().astype(int)]


class _Counts:
    """Running sums over frames: per-frame shares to average, class voxels to pool."""

    def __init__(self) -> None:
        self.frames = 0
        self.sums: dict[str, float] = {}
        self.layers = np.zeros(GRID_SHAPE[2])
        self.classes = np.zeros(FREE, dtype=np.int64)

    def add(self, labels: dict[str, np.ndarray]) -> None:
        occ = labels["semantics"] != FREE
        lidar, camera = labels["mask_lidar"].astype(bool), labels["mask_camera"].astype(bool)
        columns = occ.any(axis=2)
        n_occ = int(occ.sum())
        shares = {
            "occupied": occ.mean(),
            "occupied_columns": columns.mean(),
            "voxels_per_column": n_occ / max(int(columns.sum()), 1),
            "low_layers": occ[..., :LOW_LAYERS].sum() / max(n_occ, 1),
            "mask_lidar": lidar.mean(),
            "mask_camera": camera.mean(),
            "camera_inside_lidar": (camera & lidar).sum() / max(int(camera.sum()), 1),
            "occupied_in_lidar": (occ & lidar).sum() / max(int(lidar.sum()), 1),
            "occupied_in_camera": (occ & camera).sum() / max(int(camera.sum()), 1),
        }
        for key, value in shares.items():
            self.sums[key] = self.sums.get(key, 0.0) + float(value)
        self.layers += occ.mean(axis=(0, 1))
        self.classes += np.bincount(labels["semantics"][occ].ravel(), minlength=FREE)[:FREE]
        self.frames += 1

    def result(self, root: Path, split: str, world: str = "") -> DatasetStats:
        n = max(self.frames, 1)
        total = max(int(self.classes.sum()), 1)
        return DatasetStats(
            root=str(root),
            split=split,
            frames=self.frames,
            world=world,
            **{key: value / n for key, value in self.sums.items()},
            per_layer=[float(v) / n for v in self.layers],
            class_shares={name: float(c) / total for name, c in zip(CLASS_NAMES[:FREE], self.classes)},
        )


def dataset_stats(root: str | Path, split: str = "val", frames: int = 100, progress: bool = True) -> DatasetStats:
    """Count ``frames`` frames of ``split`` of the dataset at ``root`` (-1: all of them),
    with a progress bar unless ``progress`` is off (a command whose output is not the count)."""
    index = DatasetIndex.open(root)
    picked = pick_frames(index, split, frames)
    counts = _Counts()
    bar = progress_bar(len(picked), f"counting the voxels of {len(picked)} {split} frames")
    with bar if progress else nullcontext(lambda n: None) as advance:
        for scene, token in picked:
            counts.add(index.labels(scene, token))
            advance(1)
    return counts.result(index.root, split, world_version(index.root))


# ----------------------------------------------------------------------------- what a person reads


#: (figure, label, reference key in OCC3D_FRAME) in the order a person reads them.
FIGURES = (
    ("occupied", "occupied share of all voxels", "occupied"),
    ("occupied_columns", "columns holding an occupied voxel", "occupied_columns"),
    ("voxels_per_column", "occupied voxels per occupied column", "voxels_per_column"),
    ("low_layers", f"occupied voxels in the lowest {LOW_LAYERS} layers", "low_layers"),
    ("mask_lidar", "mask_lidar share of all voxels", "mask_lidar"),
    ("mask_camera", "mask_camera share of all voxels", "mask_camera"),
    ("camera_inside_lidar", "mask_camera voxels inside mask_lidar", "camera_inside_lidar"),
    ("occupied_in_camera", "occupied share inside mask_camera", "occupied_in_camera"),
)


def rows(stats: DatasetStats) -> list[tuple[str, str, str, str, str]]:
    """(figure, this dataset, Occ3D-nuScenes, target, met) as text: shares in %, counts as they are."""

    def text(key: str, value: float | None) -> str:
        if value is None:
            return "–"
        return f"{value:.2f}" if key == "voxels_per_column" else f"{100 * value:.1f} %"

    def target(key: str) -> str:
        if key not in TARGETS:
            return ""
        lo, hi = TARGETS[key]
        return f"{100 * lo:.0f} %" if lo == hi else f"{100 * lo:.0f}-{100 * hi:.0f} %"

    def met(key: str) -> str:
        ok = within(key, getattr(stats, key))
        return "" if ok is None else ("yes" if ok else "no")

    return [
        (label, text(key, getattr(stats, key)), text(key, OCC3D_FRAME.get(ref)), target(key), met(key))
        for key, label, ref in FIGURES
    ]


def class_rows(stats: DatasetStats) -> list[tuple[str, str, str, str, str]]:
    """(class, this dataset, Occ3D-nuScenes training set, ratio, met) as text, commonest in
    the reference first; "met" is filled for the TARGET_CLASSES."""
    ref = reference_class_shares()
    met = stats.targets()
    out = []
    for name in sorted(ref, key=ref.__getitem__, reverse=True):
        ours = stats.class_shares[name]
        ok = met.get(f"class:{name}")
        out.append(
            (
                name,
                f"{100 * ours:.2f} %",
                f"{100 * ref[name]:.2f} %",
                f"{ours / ref[name]:.2f}x",
                "" if ok is None else ("yes" if ok else "no"),
            )
        )
    return out


def class_chart(stats: DatasetStats, width: int = 720) -> np.ndarray:
    """A bar chart (H, W, 3) uint8: each class's share of the occupied voxels, this dataset
    (its Occ3D colour) above the Occ3D-nuScenes training set (grey), on one scale."""
    from PIL import Image, ImageDraw

    from occtrain.formats.occ3d import CLASS_COLORS

    ref = reference_class_shares()
    names = sorted(ref, key=ref.__getitem__, reverse=True)
    top = max(max(ref.values()), max(stats.class_shares.values()), 1e-9)
    row, label_w, pad = 22, 150, 8
    img = Image.new("RGB", (width, pad * 2 + row * len(names) + 20), "white")
    draw = ImageDraw.Draw(img)
    bar_w = width - label_w - pad * 2 - 60
    draw.text(
        (pad, pad),
        f"class shares of occupied voxels: {Path(stats.root).name} ({stats.split}, {stats.frames} frames) "
        "above, Occ3D-nuScenes train below",
        fill="black",
    )
    for i, name in enumerate(names):
        y = pad + 20 + i * row
        draw.text((pad, y + 4), name, fill="black")
        colour = tuple(int(c) for c in CLASS_COLORS[CLASS_NAMES.index(name)])
        for j, (share, fill) in enumerate(((stats.class_shares[name], colour), (ref[name], (150, 150, 150)))):
            x1 = label_w + int(bar_w * share / top)
            draw.rectangle((label_w, y + j * 9, max(x1, label_w + 1), y + j * 9 + 8), fill=fill, outline=(60, 60, 60))
            if j == 0:
                draw.text((x1 + 4, y), f"{100 * share:.1f} %", fill="black")
    return np.asarray(img)
