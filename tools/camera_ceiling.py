"""What a camera-reading encoder can reach on a dataset, before any training: its point
budget placed on the truth, and its cameras' pixels lifted to their true depth.

    python tools/camera_ceiling.py data/quickstart --points 4096 --out docs/results/camera-ceiling.md
    python tools/camera_ceiling.py data/quickstart data/quickstart_144x256 --points 4096

For each dataset (synthetic worlds, whose frames carry each pixel's class and depth) and
each frame of its split, the rows are scored in the ``occworld`` convention against the
labels, over the same frames:

- the per-voxel prior of the train split (reads nothing);
- the point budget's oracle: ``--points`` occupied voxel centres with their true classes
  (``--movable-share`` of them movable first, as SparseOccVLA's ground truth is drawn),
  each filling a box of ``--extents`` voxels, over free or over the prior;
- the lifted pixels: every pixel's true class at its true depth, one voxel each, over
  free or over the prior; what a perfect reader of the cameras gets.

An encoder that reads these cameras cannot pass the lifted-pixel rows on the voxels its
cameras do not see; one with this point budget cannot pass the oracle's.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from occtrain.data.frames import frames_batch
from occtrain.data.identity import world_identity
from occtrain.data.layout import DatasetIndex, generator_record
from occtrain.data.voxel_prior import voxel_prior
from occtrain.errors import OcctrainError
from occtrain.formats.io import atomic_write_text
from occtrain.formats.occ3d import CLASS_INDEX, MOVABLE_CLASSES
from occtrain.metrics.occupancy import OccupancyMetric
from occtrain.models.point_sets import lifted_pixels, occupied_points, voxelize
from occtrain.progress import progress_bar
from occtrain.version import code_version

MOVABLE = {"movable": MOVABLE_CLASSES}


def _extent(text: str) -> tuple[int, int, int]:
    parts = text.split(",")
    if len(parts) != 3 or not all(p.strip().isdigit() and int(p) >= 1 for p in parts):
        raise argparse.ArgumentTypeError(f"{text!r}: an extent is x,y,z voxels, each >= 1 (e.g. 3,3,1)")
    x, y, z = (int(p) for p in parts)
    return x, y, z


def ceilings(
    root: Path,
    split: str,
    samples: int,
    points: int,
    movable_share: float,
    extents: list[tuple[int, int, int]],
    cache_dir: Path | None,
) -> dict[str, dict[str, float]]:
    """Row name -> its ``mIoU``, ``IoU`` and ``movable_mIoU`` over the split's frames."""
    index = DatasetIndex.open(root)
    frames = [(s, t) for s in index.splits.get(split, []) for t in index.scenes[s]]
    if samples >= 0:
        frames = frames[:samples]
    if not frames:
        raise OcctrainError(f"{root}: its {split} split holds no frame")
    if "cam_class" not in frames_batch(index, frames[:1], cameras=True, pixel_truth=True):
        raise OcctrainError(f"{root}: its frames have no per-pixel class and depth maps (synthetic ones do)")
    prior = torch.from_numpy(voxel_prior(root, cache_dir)).long()
    keep = tuple(CLASS_INDEX[name] for name in MOVABLE_CLASSES)
    rows: dict[str, OccupancyMetric] = {}

    def score(name: str, pred: torch.Tensor, target: torch.Tensor) -> None:
        rows.setdefault(name, OccupancyMetric(convention="occworld", subsets=MOVABLE)).update(pred[None], target[None])

    rng = np.random.default_rng(0)
    with progress_bar(len(frames), f"{root.name}: {len(frames)} {split} frames") as advance:
        for scene, token in frames:
            batch = frames_batch(index, [(scene, token)], cameras=True, pixel_truth=True)
            target = batch["semantics"][0].long()
            score("the per-voxel prior", prior, target)
            centres, classes, n = occupied_points(target.numpy(), points, rng, keep, movable_share)
            for extent in extents:
                name = f"{points} points, {'x'.join(map(str, extent))} voxels each"
                score(f"{name}, free elsewhere", voxelize(centres[:n], classes[:n], extent), target)
                score(f"{name}, the prior elsewhere", voxelize(centres[:n], classes[:n], extent, prior), target)
            cams = batch["cam_class"], batch["cam_depth"], batch["intrinsics"], batch["cam_to_ego"]
            hw = "x".join(map(str, batch["cam_class"].shape[-2:]))
            score(f"{hw} pixels lifted, free elsewhere", lifted_pixels(*cams)[0], target)
            score(f"{hw} pixels lifted, the prior elsewhere", lifted_pixels(*cams, prior)[0], target)
            advance(1)
    out = {}
    for name, metric in rows.items():
        scores = metric.compute()
        out[name] = {k: float(scores[k]) for k in ("mIoU", "IoU", "movable_mIoU")}
    return out


def world_name(root: Path) -> str:
    """A world as its results pages name it (``data.identity``), not by where it lies on
    this machine, with its cameras' size: the worlds compared here differ in nothing else."""
    record = generator_record(root) or {}
    size = (record.get("camera_height"), record.get("camera_width"))
    name = world_identity(root).name
    return f"{name}, {size[0]}x{size[1]} cameras" if all(size) else name


def table(results: dict[str, dict[str, dict[str, float]]]) -> str:
    lines = [
        "| world | row | mIoU | IoU | movable-class mIoU |",
        "|---|---|---|---|---|",
    ]
    for dataset, rows in results.items():
        for name, s in rows.items():
            lines.append(f"| {dataset} | {name} | {s['mIoU']:.1f} | {s['IoU']:.1f} | {s['movable_mIoU']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("roots", nargs="+", type=Path, help="synthetic dataset roots")
    parser.add_argument("--split", default="val")
    parser.add_argument("--samples", type=int, default=-1, help="the first N frames of the split (-1: all)")
    parser.add_argument("--points", type=int, default=4096, help="the encoder's point budget")
    parser.add_argument("--movable-share", type=float, default=0.15)
    parser.add_argument("--extents", type=_extent, nargs="+", default=[(3, 3, 2), (3, 3, 1)])
    parser.add_argument("--cache-dir", type=Path, default=None, help="where the per-voxel prior is kept")
    parser.add_argument("--out", type=Path, default=None, help="write the table here (markdown)")
    args = parser.parse_args(argv)
    try:
        for root in args.roots:
            if not root.is_dir():
                raise OcctrainError(f"{root}: no such dataset; give a synthetic world's root (occtrain data synth)")
        results = {
            world_name(root): ceilings(
                root, args.split, args.samples, args.points, args.movable_share, args.extents, args.cache_dir
            )
            for root in args.roots
        }
    except OcctrainError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    text = table(results)
    if args.out is not None:
        atomic_write_text(args.out, page(text, args))
    print(text, end="")
    return 0


def page(text: str, args: argparse.Namespace) -> str:
    """The table as a docs page: what each row is, and the command and code that wrote it."""
    extents = " ".join(",".join(map(str, e)) for e in args.extents)
    frames = "every frame" if args.samples < 0 else f"the first {args.samples} frames"
    return (
        "# What a camera-reading encoder can reach\n\n"
        f"Scored in the `occworld` convention over {frames} of each world's {args.split} split, before any "
        "training. The per-voxel prior reads nothing; the point budget's rows place "
        f"{args.points} points on occupied voxels with their true classes ({args.movable_share:.0%} movable "
        "first, as SparseOccVLA's ground truth is drawn), each filling a box of that many voxels; the lifted "
        "pixels are every camera pixel's true class at its true depth, one voxel each. An encoder with this "
        "point budget cannot pass the budget's rows; one that reads these cameras cannot pass the lifted "
        "pixels' on the voxels they do not show.\n\n"
        f"Written by `python tools/camera_ceiling.py <worlds> --points {args.points} --extents {extents}` "
        f"at code {code_version()}.\n\n" + text
    )


if __name__ == "__main__":
    sys.exit(main())
