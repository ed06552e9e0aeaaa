"""Write the embedded synthetic world to disk in the Occ3D layout (resumable, deterministic)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from occtrain.config.groups import SynthConfig, check_synth_config
from occtrain.data.cameras import nuscenes_rig
from occtrain.data.layout import DatasetIndex, DatasetWriter
from occtrain.data.schema import QAQuestion
from occtrain.data.synth import generate_scene
from occtrain.data.synth.text import caption_for_frame, narration_for_frame, questions_for_frame
from occtrain.progress import console, progress_bar

#: What each version of the world changed; the last is the current one. The version is the
#: world's name in every table measured on it ("world v4").
FORMAT_CHANGES = {
    2: "six cameras (images, per-pixel class and depth, camera_sensor records), signal poles at "
    "crossings, mask_camera cast from the camera rays",
    3: "camera_sensor records in the released files' form (keyed by channel, intrinsics, img_path)",
    4: "surfaces instead of solids, labels only where the scene's lidar sweeps saw a surface, "
    "mask_lidar from 32 beams that return, mask_camera inside it, street-like class areas",
}
FORMAT_VERSION = max(FORMAT_CHANGES)


def scene_plan(cfg: SynthConfig) -> list[tuple[str, str, int]]:
    """(scene name, split, scene seed) for every scene; train and val scenes are disjoint."""
    plan = []
    total = cfg.train_scenes + cfg.val_scenes
    for i in range(total):
        seed = int(np.random.SeedSequence([cfg.seed, i]).generate_state(1)[0])
        plan.append((f"scene-{i:04d}", "train" if i < cfg.train_scenes else "val", seed))
    return plan


def _fingerprint(cfg: SynthConfig) -> dict:
    return {
        "generator": "occtrain.synth",
        "format_version": FORMAT_VERSION,
        "seed": cfg.seed,
        "train_scenes": cfg.train_scenes,
        "val_scenes": cfg.val_scenes,
        "frames_per_scene": cfg.frames_per_scene,
        "camera_height": cfg.camera_height,
        "camera_width": cfg.camera_width,
    }


def synthesize(out: str | Path, cfg: SynthConfig, verbose: bool = True) -> DatasetIndex:
    """Synthesize ``cfg``'s world into ``out``; a complete identical dataset is reused as is.

    An interrupted run resumes at the first scene whose sidecar is missing. A directory
    holding a different dataset is refused (DatasetWriter), never overwritten.
    """
    check_synth_config(cfg)
    writer = DatasetWriter(out, _fingerprint(cfg))
    if writer.complete:
        if verbose:
            console.print(f"[green]dataset already complete[/] at {out}")
        return DatasetIndex.open(out)
    cameras = nuscenes_rig(cfg.camera_height, cfg.camera_width) if cfg.camera_height else None
    plan = scene_plan(cfg)
    questions: dict[str, list[QAQuestion]] = {"train": [], "val": []}
    start = time.perf_counter()
    rendered = 0
    with progress_bar(len(plan) * cfg.frames_per_scene, f"synthesizing {len(plan)} scenes") as advance:
        for scene_idx, (name, split, seed) in enumerate(plan):
            if writer.scene_done(name):
                frames = writer.read_scene(name)
                advance(len(frames))
            else:
                scene = generate_scene(name=name, seed=seed, num_frames=cfg.frames_per_scene)
                frames = scene.frames
                for i, frame in enumerate(frames):
                    frame["caption"] = caption_for_frame(frame)
                    frame["narration"] = narration_for_frame(frame)
                    labels = scene.render(i)
                    writer.write_labels(name, frame["token"], labels)
                    if cameras:
                        views = scene.cameras(i, labels["semantics"], cfg.camera_height, cfg.camera_width)
                        writer.write_images(
                            frame["token"], [(c.name, v.image, v.classes, v.depth) for c, v in zip(cameras, views)]
                        )
                    rendered += 1
                    advance(1)
            writer.write_scene(name, split, frames, cameras)
            # Questions depend only on the frames and a per-scene seed, so a resumed run
            # regenerates exactly the questions an uninterrupted one would have written.
            rng = np.random.default_rng([cfg.seed, scene_idx, 7])
            for frame in frames:
                questions[split].extend(questions_for_frame(frame, rng))
    writer.finalize(questions)
    if verbose:
        secs = time.perf_counter() - start
        console.print(
            f"wrote {len(plan)} scenes ({cfg.train_scenes} train, {cfg.val_scenes} val), "
            f"{rendered} frames in {secs:.1f}s, "
            f"{sum(len(q) for q in questions.values())} questions -> {out}"
        )
    return DatasetIndex.open(out)
