"""Data throughput: world synthesis frames/s (one core) and shard reading samples/s.

    python tools/bench/data.py [--frames 40] [--read-seconds 8]
    python tools/bench/data.py fingerprint [--root data/quickstart]
    python tools/bench/data.py transfer [--root data/quickstart]

``fingerprint`` times what every stage start pays to know its shards and caches are of the
dataset as it is: the size-and-mtime fingerprint occtrain uses against hashing the same
files' bytes, interleaved three times each (the page cache warm for both after the first).
``transfer`` times handing a clip batch of the dataset's shards (made by a run of it) to the
device: Lightning's default walk of the whole batch against ``ShardDataModule.transfer_batch_to_device``,
which leaves the per-sample records alone, alternating over the same batches.

Everything is measured in one run, side by side, on the same machine state:
synthesis (scene generation with its lidar sweeps, labels with both masks, annotation and
text, no disk) without and with the six cameras (ray cast and shaded at the default
72 x 128), synthesis of a 4-scene world including the labels.npz and image writes in one
process and in one worker process per core (``synthesize(workers=...)``), and reading single-frame
shards with decoding through a DataLoader at num_workers 0 and 2.
Goals: synthesis with both masks and the cameras >= 15 frames/s (world v4 issue), cameras
costing no more than 3x synthesis without them (cameras issue), reading >= 200 samples/s.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
from records import Row, record  # noqa: E402

from occtrain.config import DataConfig, SynthConfig  # noqa: E402
from occtrain.data.datamodule import ShardDataModule  # noqa: E402
from occtrain.data.shards import write_shards  # noqa: E402
from occtrain.data.synth import generate_scene, prepare_sensors  # noqa: E402
from occtrain.data.synth.text import caption_for_frame, narration_for_frame  # noqa: E402
from occtrain.data.synthesize import synthesize  # noqa: E402


def bench_synthesis(frames: int, cameras: bool) -> float:
    prepare_sensors((72, 128))  # per-process set-up, not throughput
    start = time.perf_counter()
    scene = generate_scene(name="scene-bench", seed=11, num_frames=frames)
    for i, frame in enumerate(scene.frames):
        frame["caption"] = caption_for_frame(frame)
        frame["narration"] = narration_for_frame(frame)
        labels = scene.render(i)
        if cameras:
            scene.cameras(i, labels["semantics"], 72, 128)
    return frames / (time.perf_counter() - start)


def bench_read(cfg: DataConfig, workers: int, seconds: float) -> float:
    cfg.num_workers = workers
    loader = ShardDataModule(cfg, "frames").train_dataloader()
    it = iter(loader)
    next(it)  # worker start-up is not throughput
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        n += len(next(it)["token"])
    rate = n / (time.perf_counter() - start)
    del it
    return rate


def bench_fingerprint(root: Path) -> None:
    import hashlib

    from occtrain.data.layout import DatasetIndex
    from occtrain.data.shards import dataset_fingerprint, source_files

    index = DatasetIndex.open(root)
    files = [f for f in source_files(index) if f.is_file()]
    size = sum(f.stat().st_size for f in files)

    def by_content() -> None:
        h = hashlib.sha256()
        for f in files:
            h.update(f.read_bytes())

    stat_s, hash_s = [], []
    for _ in range(3):
        for fn, out in ((lambda: dataset_fingerprint(index), stat_s), (by_content, hash_s)):
            start = time.perf_counter()
            fn()
            out.append(time.perf_counter() - start)
    print(f"{root}: {len(files)} source files, {size / 1e6:.0f} MB")
    print(f"fingerprint by size + mtime: {' / '.join(f'{t:.2f}' for t in stat_s)} s")
    print(
        f"sha256 of every byte       : {' / '.join(f'{t:.2f}' for t in hash_s)} s   "
        f"({min(hash_s) / min(stat_s):.1f}x the fingerprint, best of three)"
    )
    record(
        [
            Row(
                f"what every stage start pays to know its shards and caches are of the dataset as it is "
                f"({len(files):,} source files, {size / 1e6:.0f} MB): occtrain's size + mtime fingerprint vs a "
                "sha256 of every byte, three interleaved runs",
                f"{min(stat_s):.2f}-{max(stat_s):.2f} s vs {min(hash_s):.2f}-{max(hash_s):.2f} s (the first hash "
                "reads cold files; later ones from the page cache)",
            )
        ]
    )


def bench_transfer(root: Path, batches: int = 20) -> None:
    from lightning.fabric.utilities.apply_func import move_data_to_device

    data = DataConfig(root=str(root))
    module = ShardDataModule(data, "clips")
    held = [batch for batch, _ in zip(module.train_dataloader(), range(batches))]
    cpu = torch.device("cpu")
    walk_s, ours_s = [], []
    for batch in held:
        for move, out in (
            (lambda b: move_data_to_device(b, cpu), walk_s),
            (lambda b: module.transfer_batch_to_device(b, cpu, 0), ours_s),
        ):
            start = time.perf_counter()
            move(batch)
            out.append(time.perf_counter() - start)
    walk, ours = 1e3 * sum(walk_s) / len(held), 1e3 * sum(ours_s) / len(held)
    print(f"{root}: {len(held)} clip batches of {data.batch_size}")
    print(f"Lightning's walk of the whole batch : {walk:7.2f} ms a batch")
    print(f"ShardDataModule's transfer          : {ours:7.2f} ms a batch   ({walk / ours:.0f}x faster)")
    record(
        [
            Row(
                f"handing a clip batch (batch {data.batch_size}, {len(held)} batches of the training shards) to the "
                "device: Lightning's walk of the whole batch vs `ShardDataModule.transfer_batch_to_device`, which "
                "leaves the per-sample records alone, alternating per batch",
                f"{walk:.2f} vs {ours:.2f} ms a batch ({walk / ours:.0f}x)",
            )
        ]
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", nargs="?", choices=("throughput", "fingerprint", "transfer"), default="throughput")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--read-seconds", type=float, default=8.0)
    ap.add_argument(
        "--root", type=Path, default=Path("data/quickstart"), help="the dataset `fingerprint` and `transfer` read"
    )
    args = ap.parse_args()
    if args.what == "fingerprint":
        bench_fingerprint(args.root)
        return
    if args.what == "transfer":
        bench_transfer(args.root)
        return
    torch.set_num_threads(1)

    plain = bench_synthesis(args.frames, cameras=False)
    with_cams = bench_synthesis(args.frames, cameras=True)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = SynthConfig(train_scenes=3, val_scenes=1, frames_per_scene=args.frames, seed=5)
        cores = len(os.sched_getaffinity(0))
        disk_fps = {}
        for workers in (1, cores):
            root = Path(tmp) / f"world-{workers}"
            start = time.perf_counter()
            synthesize(root, cfg, verbose=False, workers=workers)
            disk_fps[workers] = 4 * args.frames / (time.perf_counter() - start)
        write_shards(root, Path(tmp) / "shards", kinds=["frames"])
        data = DataConfig(root=str(root), shards=str(Path(tmp) / "shards"), batch_size=8, shuffle_buffer=64)
        read0 = bench_read(data, 0, args.read_seconds)
        read2 = bench_read(data, 2, args.read_seconds)

    print(f"synthesis, in memory      : {plain:7.1f} frames/s   (labels and both masks)")
    print(
        f"  with the six cameras    : {with_cams:7.1f} frames/s   (goal >= 15; {plain / with_cams:.2f}x the time, goal "
        "<= 3x)"
    )
    print(f"synthesis, written to disk: {disk_fps[1]:7.1f} frames/s   (labels, six images with class and depth maps)")
    print(
        f"  in {cores} worker processes  : {disk_fps[cores]:7.1f} frames/s   ({disk_fps[cores] / disk_fps[1]:.2f}x one "
        "process)"
    )
    print(f"shard read, num_workers=0 : {read0:7.1f} samples/s  (goal >= 200)")
    print(f"shard read, num_workers=2 : {read2:7.1f} samples/s  ({read2 / read0:.2f}x workers=0)")
    record(
        [
            Row(
                f"world synthesis in memory, one core ({args.frames} frames: scenes, lidar, labels with both masks, "
                "annotation, text): without vs with the six cameras (72 x 128, class and depth maps)",
                f"{plain:.1f} vs {with_cams:.1f} frames/s: the cameras cost {plain / with_cams:.2f}x the time "
                "(goal <= 3x); goal >= 15 frames/s with the cameras",
            ),
            Row(
                f"a 4-scene world written to disk (labels, six images and twelve maps a frame) by one process vs "
                f"one worker process per core ({cores})",
                f"{disk_fps[1]:.1f} vs {disk_fps[cores]:.1f} frames/s ({disk_fps[cores] / disk_fps[1]:.2f}x)",
            ),
            Row(
                "reading frame shards with decoding through a DataLoader, num_workers 0 vs 2",
                f"{read0:.0f} vs {read2:.0f} samples/s (goal >= 200)",
            ),
        ]
    )


if __name__ == "__main__":
    main()
