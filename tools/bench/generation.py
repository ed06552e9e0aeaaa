"""Batched vs one-at-a-time greedy generation, side by side in one run, on a trained export.

    python tools/bench/generation.py [--stage runs/quickstart/instruct] [--batch-size 16] [--batches 2]

Both paths roll out the same tasks on the same val clips with the same model
(``WorldModelEngine.rollouts(..., batched=True/False)``); the script prints sequences per
second of each, the ratio, and how many generated answers are identical (they should all be).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")

import torch  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402
from records import Row, record  # noqa: E402

from occtrain.config import load_config  # noqa: E402
from occtrain.config.recipe import RecipeConfig  # noqa: E402
from occtrain.data.clips import clips_from_batch  # noqa: E402
from occtrain.data.datamodule import ShardDataModule  # noqa: E402
from occtrain.engine import load_world_model  # noqa: E402
from occtrain.stages.stage import shared_cache_dir  # noqa: E402


def timed(engine, task, batches, batched: bool) -> tuple[float, list]:
    outputs = []
    start = time.perf_counter()
    for batch in batches:
        for _, _, generated, _ in engine.rollouts(task, clips_from_batch(batch), batch, batched=batched):
            outputs.append(generated)
    return time.perf_counter() - start, outputs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stage", default="runs/quickstart/instruct", help="RUN_DIR/STAGE of a world-model stage")
    parser.add_argument("--tasks", default="qa,cot_planning")
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--batches", type=int, default=2)
    args = parser.parse_args()
    stage = Path(args.stage)
    recipe = load_config(RecipeConfig, stage.parent / "pipeline.yaml")
    data = ShardDataModule(OmegaConf.merge(recipe.data, {"batch_size": args.batch_size}), "clips")
    data.prepare_data()
    batches = [b for _, b in zip(range(args.batches), data.loader("val", train=False))]
    engine = load_world_model(stage / "export").eval()
    engine.prepare_inputs(
        recipe.data.root, stage / "cache", shared_cache_dir(stage)
    )  # time generation, not the frozen encoders
    torch.manual_seed(0)
    rows = []
    for task in args.tasks.split(","):
        timed(engine, task, batches[:1], True)  # warm-up
        t_one, one = timed(engine, task, batches, batched=False)
        t_batch, many = timed(engine, task, batches, batched=True)
        same = sum(a == b for a, b in zip(one, many))
        n = len(one)
        print(
            f"{task}: {n} sequences, one at a time {n / t_one:.2f} seq/s, batched ({args.batch_size}) "
            f"{n / t_batch:.2f} seq/s "
            f"-> {t_one / t_batch:.1f}x; identical answers {same}/{n}"
        )
        rows.append(
            Row(
                f"greedy generation of `{task}` on {n} val prompts of a trained instruct export: one prompt at a "
                f"time vs a batch's {args.batch_size} together",
                f"{n / t_one:.2f} vs {n / t_batch:.2f} sequences/s ({t_one / t_batch:.1f}x); identical answers "
                f"{same}/{n}",
            )
        )
    record(rows)


if __name__ == "__main__":
    main()
