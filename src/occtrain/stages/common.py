"""What every stage kind shares: the Trainer, the resumable data position, optimizers, metric names."""

from __future__ import annotations

import logging
import math
import warnings
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback, LearningRateMonitor, ModelCheckpoint, RichProgressBar
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

from occtrain.config.recipe import OptimConfig
from occtrain.config.schema import TrainerConfig
from occtrain.data.datamodule import ResumableLoader
from occtrain.errors import OcctrainError

LAST_CKPT = "last.ckpt"


# ----------------------------------------------------------------------------- callbacks


class _TrackConsumed(Callback):
    """Points the resumable loader at the trainer's step count."""

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        loader = trainer.train_dataloader
        if isinstance(loader, ResumableLoader):
            acc = trainer.accumulate_grad_batches
            loader.consumed = lambda: trainer.global_step * acc


class _RngState(Callback):
    """Saves and restores torch's RNG in checkpoints (Lightning does not)."""

    def state_dict(self) -> dict[str, Any]:
        return {"torch": torch.get_rng_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        torch.set_rng_state(state["torch"])


# ----------------------------------------------------------------------------- trainer


def quiet_lightning() -> None:
    """Keep a run's log readable: Lightning's device banners, tips and a deprecation notice
    of its own internals say nothing a user can act on."""
    logging.getLogger("lightning.pytorch.utilities.rank_zero").setLevel(logging.WARNING)
    logging.getLogger("lightning.pytorch.accelerators.cuda").setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", message=r".*LeafSpec.*")
    warnings.filterwarnings("ignore", message=r".*is_gradient_checkpointing.*")
    # Frozen sub-models (the scene tokenizer, a teacher) are in eval mode on purpose.
    warnings.filterwarnings("ignore", message=r".*module\(s\) in eval mode.*")


def build_trainer(cfg: TrainerConfig, stage_dir: Path, monitor: str | None, mode: str = "max") -> L.Trainer:
    """A Trainer writing ``checkpoints/`` (last.ckpt every N steps, best by ``monitor``) and ``logs/``."""
    quiet_lightning()
    ckpt_dir = stage_dir / "checkpoints"
    callbacks: list[Callback] = [
        ModelCheckpoint(
            dirpath=ckpt_dir, filename="step{step}", every_n_train_steps=cfg.ckpt_every_n_steps,
            save_last=True, save_top_k=0, auto_insert_metric_name=False, enable_version_counter=False,
        ),
        _TrackConsumed(),
        _RngState(),
        LearningRateMonitor(logging_interval="step"),
        RichProgressBar(leave=True),
    ]
    if monitor:
        callbacks.append(
            ModelCheckpoint(
                dirpath=ckpt_dir, filename="best", monitor=monitor, mode=mode, save_top_k=1,
                auto_insert_metric_name=False, enable_version_counter=False,
            )
        )
    logs = stage_dir / "logs"
    loggers = [CSVLogger(logs, name="", version="csv"), TensorBoardLogger(logs, name="", version="tensorboard")]
    return L.Trainer(
        accelerator=cfg.accelerator,
        devices=cfg.devices,
        num_nodes=cfg.num_nodes,
        strategy=cfg.strategy,
        precision=cfg.precision,
        max_steps=cfg.max_steps,
        max_epochs=cfg.max_epochs,
        val_check_interval=cfg.val_check_interval,
        check_val_every_n_epoch=None,
        limit_val_batches=1.0 if cfg.limit_val_batches < 0 else cfg.limit_val_batches,
        log_every_n_steps=cfg.log_every_n_steps,
        gradient_clip_val=cfg.gradient_clip_val or None,
        accumulate_grad_batches=cfg.accumulate_grad_batches,
        deterministic=cfg.deterministic,
        callbacks=callbacks,
        logger=loggers,
        default_root_dir=stage_dir,
        enable_model_summary=False,
        num_sanity_val_steps=0,
    )


def last_checkpoint(stage_dir: Path) -> Path | None:
    path = stage_dir / "checkpoints" / LAST_CKPT
    return path if path.is_file() else None


# ----------------------------------------------------------------------------- optimizer


def configure_adamw(params: Any, cfg: OptimConfig, max_steps: int) -> dict:
    """AdamW with linear warm-up and cosine decay to ``min_lr_ratio`` (or constant), per step."""
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay, betas=tuple(cfg.betas))
    if cfg.schedule not in ("cosine", "constant"):
        raise OcctrainError(f"optim.schedule '{cfg.schedule}' is not one of cosine, constant")

    def factor(step: int) -> float:
        if cfg.warmup_steps and step < cfg.warmup_steps:
            return (step + 1) / cfg.warmup_steps
        if cfg.schedule == "constant" or max_steps <= cfg.warmup_steps:
            return 1.0
        progress = min(1.0, (step - cfg.warmup_steps) / max(1, max_steps - cfg.warmup_steps))
        return cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
    return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}


def freeze_prefixes(module: torch.nn.Module, prefixes: list[str]) -> int:
    """Freeze parameters whose names start with any prefix; returns how many tensors were frozen."""
    n = 0
    for name, p in module.named_parameters():
        if any(name.startswith(pre) for pre in prefixes):
            p.requires_grad_(False)
            n += 1
    if prefixes and n == 0:
        raise OcctrainError(f"freeze: no parameter name starts with {', '.join(prefixes)}")
    return n
