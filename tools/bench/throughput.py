"""Training throughput of one world-model stage: eager vs compiled, padded vs packed, side by
side in one run.

    python tools/bench/throughput.py RECIPE [--stage pretrain] [--run runs/quickstart]
        [--size recipe|1b|8b] [--steps 16] [--warmup 6] [--set KEY=VALUE ...]

The stage is built as ``occtrain run`` builds it (``load_recipe``, its kind's module, the
run's shards and the exports it consumes from ``--run``, which must have trained them) and
trained ``--steps`` optimizer steps under each variant with Lightning, without validation or
checkpoints, in a scratch directory; the run is left as it was. Each variant starts from the
same seed, so all four see the same batches. Reported over the steps after ``--warmup``
(compiling, its recompilation when the sequence length first changes and allocator warm-up
fall inside it): tokens/s, MFU (``stages.callbacks.StepMeter``: model FLOPs per
``models.flops`` over the device's peak; on a CPU a measured fp32 matmul), the padding share
and the step time, and each variant's tokens/s over eager-padded's.

``--size`` replaces the recipe's LLM with a Llama of Llama 3.2 1B's or Llama 3.1 8B's
shape (grouped-query attention aside: occtrain's tiny configs give every head its keys),
randomly initialised: throughput depends on the shape, not the weights. ``--set`` passes
overrides as on ``occtrain run`` (``trainer.accelerator=gpu trainer.precision=bf16-mixed
trainer.strategy=fsdp``, ``stages.pretrain.data.batch_size=8``).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")

from omegaconf import OmegaConf  # noqa: E402
from records import Row, record  # noqa: E402

from occtrain.progress import console  # noqa: E402
from occtrain.run.execution import build_stage  # noqa: E402
from occtrain.run.planning import load_recipe  # noqa: E402
from occtrain.stages.trainer import build_trainer  # noqa: E402

#: LLM shapes by name: Llama 3.2 1B and Llama 3.1 8B (their config.json files).
SIZES = {
    "1b": {"hidden_size": 2048, "num_layers": 16, "num_heads": 32, "intermediate_size": 8192},
    "8b": {"hidden_size": 4096, "num_layers": 32, "num_heads": 32, "intermediate_size": 14336},
}
VARIANTS = (("eager", "padded"), ("eager", "packed"), ("compiled", "padded"), ("compiled", "packed"))


def variant_overrides(stage: str, compiled: bool, packed: bool, size: str) -> list[str]:
    out = [f"trainer.compile={str(compiled).lower()}", f"stages.{stage}.model.pack_sequences={str(packed).lower()}"]
    for key, value in SIZES.get(size, {}).items():
        out.append(f"stages.{stage}.model.llm.{key}={value}")
    return out


def measure(recipe: str, stage_name: str, run_dir: Path, overrides: list[str], steps: int, warmup: int) -> dict:
    """Train the stage ``steps`` steps under ``overrides``; the kept steps' rates."""
    _, planned = load_recipe(recipe, overrides)
    stage = next(p for p in planned if p.spec.name == stage_name)
    inputs = {name: run_dir / name / "export" for name in stage.spec.consumes}
    missing = [str(p) for p in inputs.values() if not p.is_dir()]
    if missing:
        raise SystemExit(f"{missing[0]} does not exist: train the stages {stage_name} consumes in {run_dir} first")
    cfg = OmegaConf.merge(
        stage.trainer,
        {"max_steps": steps, "limit_val_batches": 0, "ckpt_every_n_steps": steps + 1, "loggers": ["csv"]},
    )
    with tempfile.TemporaryDirectory(prefix="occtrain-bench-") as scratch:
        stage_dir = Path(scratch) / stage_name
        module, data = build_stage(dataclasses.replace(stage, trainer=cfg), stage_dir, inputs)
        trainer, meters = build_trainer(cfg, stage_dir, monitor=None)
        trainer.fit(module, datamodule=data)
    meter = meters.steps
    meter.warmup = warmup
    return meter.summary()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recipe")
    parser.add_argument("--stage", default="pretrain")
    parser.add_argument("--run", type=Path, default=None, help="the run whose consumed exports it reads")
    parser.add_argument("--size", default="recipe", choices=["recipe", *SIZES])
    parser.add_argument("--steps", type=int, default=16)
    parser.add_argument("--warmup", type=int, default=6)
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    parser.add_argument("--variants", default=",".join(f"{c}-{p}" for c, p in VARIANTS))
    args = parser.parse_args()
    recipe, _ = load_recipe(args.recipe, args.set)
    run_dir = args.run or Path(recipe.runs_root) / recipe.name  # as occtrain run places it
    rows = []
    for name in args.variants.split(","):
        compiled, packed = name.split("-")
        overrides = [*args.set, *variant_overrides(args.stage, compiled == "compiled", packed == "packed", args.size)]
        console.print(f"[bold]{name}[/]: {args.steps} steps of {args.stage} ({args.size})")
        rows.append((name, measure(args.recipe, args.stage, run_dir, overrides, args.steps, args.warmup)))
    base = rows[0][1].get("train_tokens_per_s")
    print(f"\n{args.stage} of {args.recipe}, LLM {args.size}, {args.steps} steps ({args.warmup} warm-up) per variant")
    print("| variant | tokens/s | x first | MFU % | padding % | step s |")
    print("|---|---|---|---|---|---|")
    shown = []
    for name, m in rows:
        tps = m.get("train_tokens_per_s", float("nan"))
        ratio = tps / base if base else float("nan")
        mfu = 100 * m.get("train_mfu", float("nan"))
        pad = 100 * m.get("train_padding_share", float("nan"))
        step = m.get("train_step_s", float("nan"))
        print(f"| {name} | {tps:,.0f} | {ratio:.2f} | {mfu:.1f} | {pad:.1f} | {step:.3f} |")
        shown.append(f"{name} {tps:,.0f} tokens/s ({ratio:.2f}x, MFU {mfu:.1f} %, padding {pad:.0f} %)")
    peak = rows[0][1].get("train_device_peak_flops_per_s")
    if peak:
        print(f"\npeak the MFU divides by: {peak / 1e12:.3f} TFLOP/s")
    record(
        [
            Row(
                f"training throughput of {args.recipe}'s {args.stage} stage (LLM {args.size}"
                + (", " + " ".join(args.set) if args.set else "")
                + f"), {args.steps} steps after {args.warmup} of warm-up, eager vs compiled x padded vs packed",
                "; ".join(shown) + (f"; the MFU's peak {peak / 1e12:.3f} TFLOP/s" if peak else ""),
            )
        ]
    )


if __name__ == "__main__":
    main()
