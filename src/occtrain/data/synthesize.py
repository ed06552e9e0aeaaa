"""Write the embedded synthetic world to disk in the Occ3D layout (resumable, deterministic)."""

from __future__ import annotations

import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from occtrain.config.groups import SynthConfig, check_synth_config
from occtrain.data.cameras import nuscenes_rig
from occtrain.data.dataset_writer import DatasetWriter, SceneFiles
from occtrain.data.layout import DatasetIndex
from occtrain.data.schema import QAQuestion
from occtrain.data.synth import generate_scene
from occtrain.data.synth.scene import scene_events
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
    5: "ego_accel from the frame and the one before (the speed now against the last move's), no longer the "
    "acceleration the expert applied after the frame",
    6: "each frame's road (the route ahead, the lead vehicle, the pedestrian in the corridor, the next stop line "
    "and its light, the curvature ahead), the driving command from the route as the closed loop takes it (no "
    "longer from the expert's own future), val scenes drawn until they hold a turn, a red-light stop and a lead",
}
FORMAT_VERSION = max(FORMAT_CHANGES)


#: A val scene's seed is redrawn at most this many times (see ``scene_plan``).
VAL_DRAWS = 32


def _scene_seed(cfg: SynthConfig, i: int, draw: int = 0) -> int:
    words = [cfg.seed, i] if draw == 0 else [cfg.seed, i, draw]
    return int(np.random.SeedSequence(words).generate_state(1)[0])


def _val_seed(cfg: SynthConfig, i: int, taken: set[int]) -> int:
    """The first of scene ``i``'s seeds (``_scene_seed``'s draws, none in ``taken``) whose scene
    holds a turn command, a red-light stop and a lead vehicle (``scene_events``), else the
    first of VAL_DRAWS that holds the most of them, in that order of importance. A draw whose
    ego, driving alone, could not do better than the best so far is not simulated in traffic."""
    best, best_score = -1, (False, False, False)
    for draw in range(VAL_DRAWS):
        seed = _scene_seed(cfg, i, draw)
        if seed in taken:
            continue
        alone = scene_events(seed, cfg.frames_per_scene, traffic=False)
        if best >= 0 and (alone.turns > 0, alone.red_stops > 0, True) <= best_score:
            continue
        events = scene_events(seed, cfg.frames_per_scene)
        score = (events.turns > 0, events.red_stops > 0, events.leads > 0)
        if best < 0 or score > best_score:
            best, best_score = seed, score
        if all(score):
            break
    return best


def scene_plan(cfg: SynthConfig) -> list[tuple[str, str, int]]:
    """(scene name, split, scene seed) for every scene; train and val scenes are disjoint.

    Train scene ``i``'s seed is drawn from (seed, i). A val scene must show open-loop
    scoring what closed loop shows, so its seed is redrawn (deterministically: (seed, i,
    draw)) until its route turns within its frames, the ego stands at a red light and
    follows a lead vehicle (``_val_seed``): the plan is the same on every run, so a resumed
    synthesis writes the scenes an uninterrupted one would have.
    """
    splits = ["train"] * cfg.train_scenes + ["val"] * cfg.val_scenes
    seeds = [_scene_seed(cfg, i) for i in range(cfg.train_scenes)]
    taken = set(seeds)
    for i in range(cfg.train_scenes, len(splits)):
        seeds.append(_val_seed(cfg, i, taken))
        taken.add(seeds[-1])
    return [(f"scene-{i:04d}", split, seed) for i, (split, seed) in enumerate(zip(splits, seeds))]


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


def _write_scene(root: str, name: str, seed: int, cfg: SynthConfig) -> int:
    """Generate one scene and write its frames (labels, cameras, then the sidecar that marks
    it complete); the number of frames. Runs in a worker process or in the caller's."""
    files = SceneFiles(root)
    scene = generate_scene(name=name, seed=seed, num_frames=cfg.frames_per_scene)
    frames = scene.frames
    rig = nuscenes_rig(cfg.camera_height, cfg.camera_width) if cfg.camera_height else []
    for i, frame in enumerate(frames):
        frame["caption"] = caption_for_frame(frame)
        frame["narration"] = narration_for_frame(frame)
        labels = scene.render(i)
        files.write_labels(name, frame["token"], labels)
        if rig:
            views = scene.cameras(i, labels["semantics"], cfg.camera_height, cfg.camera_width)
            files.write_images(frame["token"], [(c.name, v.image, v.classes, v.depth) for c, v in zip(rig, views)])
    files.write_frames(name, frames)
    return len(frames)


def synthesis_workers(frames: int) -> int:
    """Processes for ``frames`` frames still to render: one per core this process may use,
    or this process alone below 100 frames, where starting workers (each imports the
    generator and builds its sensor geometry, a few seconds) costs more than it saves."""
    return 1 if frames < 100 else max(1, len(os.sched_getaffinity(0)))


def synthesize(out: str | Path, cfg: SynthConfig, verbose: bool = True, workers: int | None = None) -> DatasetIndex:
    """Synthesize ``cfg``'s world into ``out``; a complete identical dataset is reused as is.

    Scenes are independent (each from its own seed), so ``workers`` processes (None: see
    :func:`synthesis_workers`) write them side by side; the files are the same whatever
    the number. An interrupted run resumes at the first scene whose sidecar is missing. A
    directory holding a different dataset is refused (DatasetWriter), never overwritten.
    """
    check_synth_config(cfg)
    writer = DatasetWriter(out, _fingerprint(cfg))
    if writer.complete:
        if verbose:
            console.print(f"[green]dataset already complete[/] at {out}")
        return DatasetIndex.open(out)
    cameras = nuscenes_rig(cfg.camera_height, cfg.camera_width) if cfg.camera_height else None
    plan = scene_plan(cfg)
    todo = [(name, seed) for name, _, seed in plan if not writer.scene_done(name)]
    workers = min(workers or synthesis_workers(len(todo) * cfg.frames_per_scene), max(1, len(todo)))
    start = time.perf_counter()
    with progress_bar(len(plan) * cfg.frames_per_scene, f"synthesizing {len(plan)} scenes") as advance:
        advance((len(plan) - len(todo)) * cfg.frames_per_scene)
        if workers == 1:
            for name, seed in todo:
                advance(_write_scene(str(out), name, seed, cfg))
        else:
            # Forked, as torch's DataLoader forks its workers: spawning would re-run the
            # caller's main module in each worker. The workers run numpy only, never
            # torch's thread pools, which a fork copies without their threads.
            context = multiprocessing.get_context("fork")
            with ProcessPoolExecutor(workers, mp_context=context) as pool:
                jobs = [pool.submit(_write_scene, str(out), name, seed, cfg) for name, seed in todo]
                for job in as_completed(jobs):
                    advance(job.result())
    # The dataset's records from the sidecars, in the plan's order, however the scenes were written.
    questions: dict[str, list[QAQuestion]] = {"train": [], "val": []}
    for scene_idx, (name, split, _) in enumerate(plan):
        frames = writer.read_scene(name)
        writer.add_scene_info(name, split, frames, cameras)
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
            f"{len(todo) * cfg.frames_per_scene} frames in {secs:.1f}s ({workers} process"
            f"{'es' if workers > 1 else ''}), {sum(len(q) for q in questions.values())} questions -> {out}"
        )
    return DatasetIndex.open(out)
