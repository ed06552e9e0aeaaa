"""OccVLA's skip-occupancy inference (its App. B, Table 8), side by side in one run.

    python tools/bench/occvla.py [--stage runs/occvla/stage2] [--samples 32] [--repeats 2]

On the same val clips with the same model, each sample's meta-action chain of thought is
generated two ways, alternating (so machine noise falls on both alike): Setting 2, the
images then the text (what evaluation does), and Setting 1's cost, the occupancy query
block run after the images and decoded to voxels by the frozen OccWorld decoder before
the text. It prints seconds per sample both ways and their ratio (the paper: 21.94 vs
17.95 s/it, 1.22x), whether the generated texts are identical (they must be: text never
sees the queries), and the query branch's occupancy mIoU/IoU in the ``occ3d`` (camera
mask) and ``occworld`` (every voxel) conventions on those samples.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")

import torch  # noqa: E402
from records import Row, record  # noqa: E402

from occtrain.config import load_config  # noqa: E402
from occtrain.config.recipe import RecipeConfig  # noqa: E402
from occtrain.data.clips import frame_clips  # noqa: E402
from occtrain.data.layout import DatasetIndex  # noqa: E402
from occtrain.engine import load_world_model  # noqa: E402
from occtrain.formats.occ3d import FUTURE_STEPS  # noqa: E402
from occtrain.metrics import OccupancyMetric  # noqa: E402
from occtrain.stages.stage import shared_cache_dir  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stage", default="runs/occvla/stage2", help="RUN_DIR/STAGE of an OccVLA world-model stage")
    parser.add_argument("--samples", type=int, default=32, help="val clips (-1: all)")
    parser.add_argument("--repeats", type=int, default=2, help="timed passes over the samples, each way")
    args = parser.parse_args()
    stage = Path(args.stage)
    recipe = load_config(RecipeConfig, stage.parent / "pipeline.yaml")
    engine = load_world_model(stage / "export").eval()
    if engine.vision is None:
        raise SystemExit(f"{stage}: not an OccVLA stage (its world model reads no cameras)")
    engine.prepare_inputs(
        recipe.data.root, stage / "cache", shared_cache_dir(stage)
    )  # time generation, not camera encoding
    index = DatasetIndex.open(recipe.data.root)
    clips = list(frame_clips(index, "val", engine.tasks.context_frames, FUTURE_STEPS, partial_history=False))
    clips = clips if args.samples < 0 else clips[: args.samples]
    prompts = []
    for clip in clips:
        items = engine.task_items("meta_action", clip)
        if items:
            prompts.append((clip.anchor["token"], *engine.prompt_and_plan(items[0], {})))
    metrics = {c: OccupancyMetric(c) for c in ("occ3d", "occworld")}
    times = {False: 0.0, True: 0.0}
    same = 0
    torch.manual_seed(0)
    with torch.no_grad():
        engine.world.generate_with_occupancy(prompts[0][1], prompts[0][2], occupancy=True)  # warm-up
        for rep in range(args.repeats):
            for token, prompt, plan in prompts:
                outs = {}
                for occupancy in (False, True) if rep % 2 == 0 else (True, False):
                    start = time.perf_counter()
                    outs[occupancy] = engine.world.generate_with_occupancy(prompt, plan, occupancy=occupancy)
                    times[occupancy] += time.perf_counter() - start
                same += outs[False][0] == outs[True][0]
                if rep == 0:
                    pred = outs[True][1].argmax(1)
                    labels = index.labels(index.scene_of(token), token)
                    target = torch.from_numpy(labels["semantics"]).long()[None]
                    metrics["occ3d"].update(pred, target, torch.from_numpy(labels["mask_camera"].astype(bool))[None])
                    metrics["occworld"].update(pred, target)
    n = len(prompts) * args.repeats
    skip, full = times[False] / n, times[True] / n
    print(f"{stage}: {len(prompts)} val samples x {args.repeats} passes, meta-action chain of thought")
    print(f"  with the occupancy block (Setting 1 cost): {full:.3f} s/sample")
    print(f"  skipping it (Setting 2):                   {skip:.3f} s/sample")
    print(f"  -> skipping is {full / skip:.2f}x faster (paper, Table 8: 21.94 / 17.95 = 1.22x)")
    print(f"  identical generated text: {same}/{n}")
    for conv, metric in metrics.items():
        r = metric.compute()
        print(f"  query-branch occupancy, {conv}: mIoU {float(r['mIoU']):.2f}, IoU {float(r['IoU']):.2f}")
    record(
        [
            Row(
                f"OccVLA's meta-action chain of thought on {len(prompts)} val clips, {args.repeats} passes "
                "alternating: the occupancy query block run and decoded (Setting 1) vs skipped (Setting 2)",
                f"{full:.3f} vs {skip:.3f} s a sample: skipping is {full / skip:.2f}x faster (the paper's Table 8: "
                f"1.22x); identical text {same}/{n}",
            )
        ]
    )


if __name__ == "__main__":
    main()
