"""What Lightning costs: the tokenizer stage through occtrain's Trainer vs a bare PyTorch loop.

    python tools/bench/overhead.py [--steps 30]

Both train the quickstart's OccWorld VQ-VAE on the same shard stream with the same
optimizer for the same number of steps; the Trainer run includes everything a stage does
(CSV + TensorBoard logging, checkpoints every 10 steps, the progress bar, the resumable
loader). Runs alternate bare, Lightning, bare, Lightning so drift hits both alike; the
printed ratio is Lightning time / bare time (goal: <= 1.05).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")

import lightning as L  # noqa: E402
import torch  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402
from records import Row, record  # noqa: E402

from occtrain.config import DataConfig, TrainerConfig, load_config  # noqa: E402
from occtrain.config.recipe import OptimConfig, StageSpec  # noqa: E402
from occtrain.data.datamodule import ShardDataModule, ensure_data  # noqa: E402
from occtrain.stages import StageContext  # noqa: E402
from occtrain.stages.optim import configure_adamw  # noqa: E402
from occtrain.stages.tokenizer import TOKENIZER, TokenizerStage  # noqa: E402
from occtrain.stages.trainer import build_trainer  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


def context(data: DataConfig, steps: int, stage_dir: Path) -> StageContext:
    raw = OmegaConf.load(REPO / "configs/model/occworld_vqvae_tiny.yaml")
    schema = TokenizerStage.model_schema(TOKENIZER, None, OmegaConf.to_container(raw))  # as the runner builds it
    model_cfg = OmegaConf.merge(OmegaConf.structured(schema), raw)
    trainer = TrainerConfig(
        max_steps=steps, val_check_interval=10_000, limit_val_batches=0, ckpt_every_n_steps=10, log_every_n_steps=5
    )
    spec = StageSpec(name="bench", kind="tokenizer", optim=OptimConfig(lr=1e-3))
    return StageContext(spec, model_cfg, data, trainer, stage_dir, {})


def bare(data: DataConfig, steps: int) -> float:
    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as tmp:
        module = TokenizerStage(context(data, steps, Path(tmp)))
        opt = configure_adamw(module.model.parameters(), OptimConfig(lr=1e-3), steps)
        optimizer, sched = opt["optimizer"], opt["lr_scheduler"]["scheduler"]
        it = iter(ShardDataModule(data, "frames").train_dataloader())
        start = time.perf_counter()
        for _ in range(steps):
            batch = next(it)
            loss = module.model(batch["semantics"].long()).losses["loss"]
            optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(module.model.parameters(), 1.0)
            optimizer.step()
            sched.step()
        return time.perf_counter() - start


def lightning(data: DataConfig, steps: int) -> float:
    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as tmp:
        ctx = context(data, steps, Path(tmp))
        module = TokenizerStage(ctx)
        trainer, _ = build_trainer(ctx.trainer, Path(tmp), monitor=None)
        dm = ShardDataModule(data, "frames")
        start = time.perf_counter()
        trainer.fit(module, datamodule=dm)
        return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=30)
    args = parser.parse_args()
    data = load_config(DataConfig, REPO / "configs/data/quickstart.yaml")
    ensure_data(data, verbose=False)
    L.seed_everything(0, verbose=False)
    times = {"bare": [], "lightning": []}
    for _ in range(2):
        times["bare"].append(bare(data, args.steps))
        times["lightning"].append(lightning(data, args.steps))
    b, lt = min(times["bare"]), min(times["lightning"])
    print(
        f"{args.steps} steps: bare loop {b:.1f} s, occtrain Trainer {lt:.1f} s -> ratio {lt / b:.3f} (best of 2 each)"
    )
    record(
        [
            Row(
                f"the tokenizer stage, {args.steps} steps, through occtrain's Trainer (logging, checkpoints every 10 "
                "steps, the progress bar, the resumable loader) vs a bare PyTorch loop of the same model, data and "
                "optimizer, alternating, best of two each",
                f"{lt:.1f} vs {b:.1f} s: ratio {lt / b:.3f} (goal <= 1.05)",
            )
        ]
    )


if __name__ == "__main__":
    main()
