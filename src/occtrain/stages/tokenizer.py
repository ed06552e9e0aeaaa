"""Stage kind ``tokenizer``: train a scene tokenizer (OccWorld VQ-VAE or OccLLaMA's) on single frames.

Validation reports reconstruction mIoU/IoU in both conventions, labelled: OccWorld (what
tokenizer tables report: all voxels) and Occ3D (camera-visible voxels only). The export
holds the weights, the model config and the codebook size, which the pretraining stage
needs to lay out its joint vocabulary.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lightning as L
import torch
from omegaconf import OmegaConf

from occtrain.config import to_container
from occtrain.config.tokenizer import OccLLaMATokenizerConfig, OccWorldVQVAEConfig, validate_tokenizer_config
from occtrain.errors import ConfigError
from occtrain.metrics import OccupancyMetric
from occtrain.models import build_tokenizer, count_parameters
from occtrain.occ3d import FREE
from occtrain.stages import StageContext, StageKind, register
from occtrain.stages.common import configure_adamw, freeze_prefixes, read_export, write_export

ARCHS = ("occworld_vqvae", "occllama_tokenizer")


@dataclass
class TokenizerModelConfig:
    """``model:`` of a tokenizer stage: which architecture, and the settings of each."""

    arch: str = "occworld_vqvae"
    occworld_vqvae: OccWorldVQVAEConfig = field(default_factory=OccWorldVQVAEConfig)
    occllama_tokenizer: OccLLaMATokenizerConfig = field(default_factory=OccLLaMATokenizerConfig)


class TokenizerStage(L.LightningModule):
    """Trains a scene tokenizer with its own losses; validates reconstruction IoU."""

    def __init__(self, ctx: StageContext):
        super().__init__()
        cfg = ctx.model_cfg
        if cfg.arch not in ARCHS:
            raise ConfigError(f"stages '{ctx.spec.name}': model.arch '{cfg.arch}' is not one of {', '.join(ARCHS)}")
        validate_tokenizer_config(cfg[cfg.arch], f"stages '{ctx.spec.name}'.model.{cfg.arch}")
        self.ctx = ctx
        self.arch_cfg = to_container(cfg[cfg.arch])
        self.model = build_tokenizer(cfg.arch, cfg[cfg.arch])
        freeze_prefixes(self.model, list(ctx.spec.freeze))
        self.recon_occworld = OccupancyMetric(convention="occworld")
        self.recon_occ3d = OccupancyMetric(convention="occ3d")
        #: The trivial baseline: an empty (all free) scene.
        self.baseline_free = OccupancyMetric(convention="occworld")
        self._pictures: list[tuple] = []

    # -- training
    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        sem = batch["semantics"].long()
        out = self.model(sem)
        bs = sem.shape[0]
        for name, value in out.losses.items():
            self.log(f"train/{name}", value, batch_size=bs, prog_bar=name == "loss")
        for name, value in out.stats.items():
            self.log(f"train/{name}", value, batch_size=bs)
        return out.losses["loss"]

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        sem = batch["semantics"].long()
        out = self.model(sem)
        pred = out.logits.argmax(1)
        if batch_idx == 0:  # kept for the dashboard's ground truth vs reconstruction pictures
            self._pictures = [(sem[i].to(torch.uint8).cpu().numpy(), pred[i].to(torch.uint8).cpu().numpy()) for i in range(min(2, len(sem)))]
        self.recon_occworld.update(pred, sem)
        self.baseline_free.update(torch.full_like(sem, FREE), sem)
        self.recon_occ3d.update(pred, sem, batch["mask_camera"])
        self.log("val/loss", out.losses["loss"], batch_size=sem.shape[0], sync_dist=True)

    def on_validation_epoch_end(self) -> None:
        for prefix, metric in (
            ("val/occworld", self.recon_occworld), ("val/occ3d", self.recon_occ3d), ("val/baseline_free_occworld", self.baseline_free),
        ):
            result = metric.compute()
            self.log(f"{prefix}_mIoU", result["mIoU"])
            self.log(f"{prefix}_IoU", result["IoU"])
            metric.reset()

    def configure_optimizers(self) -> dict:
        params = [p for p in self.model.parameters() if p.requires_grad]
        return configure_adamw(params, self.ctx.spec.optim, self.ctx.trainer.max_steps)

    # -- reporting and export
    def summary(self) -> str:
        return f"{self.ctx.model_cfg.arch} {count_parameters(self.model) / 1e6:.2f}M params"

    def sample_scenes(self) -> list[tuple[str, list[tuple[str, Any]]]]:
        """(caption, [(panel label, semantics)]) for the dashboard's bird's-eye pictures."""
        return [
            (f"val sample {i}: ground truth vs reconstruction", [("ground truth", gt), ("reconstruction", rec)])
            for i, (gt, rec) in enumerate(self._pictures)
        ]

    def summary_metrics(self) -> dict[str, float]:
        return {"params": float(count_parameters(self.model))}

    def export(self, path: Path) -> Path:
        config = {
            "stage_kind": "tokenizer",
            "arch": self.ctx.model_cfg.arch,
            "config": self.arch_cfg,
            "num_codes": int(self.model.num_codes),
            "latent_hw": list(self.model.latent_hw),
            "params": count_parameters(self.model),
            "label_convention": "occ3d",
        }
        return write_export(path, self.model.state_dict(), config)


def load_tokenizer(export_dir: Path) -> torch.nn.Module:
    """Rebuild a tokenizer from a tokenizer stage's export (frozen, eval mode)."""
    state, config = read_export(export_dir)
    if config.get("stage_kind") != "tokenizer":
        raise ConfigError(f"{export_dir}: not a tokenizer export (stage kind '{config.get('stage_kind')}'); consume the tokenizer stage")
    schema = {"occworld_vqvae": OccWorldVQVAEConfig, "occllama_tokenizer": OccLLaMATokenizerConfig}[config["arch"]]
    cfg = OmegaConf.merge(OmegaConf.structured(schema), config["config"])
    model = build_tokenizer(config["arch"], cfg)
    model.load_state_dict(state)
    model.export_dir = Path(export_dir)  # a world-model export copies it from here
    return model.eval().requires_grad_(False)


TOKENIZER = register(
    StageKind(
        name="tokenizer",
        model_schema=TokenizerModelConfig,
        data_kind="frames",
        build=TokenizerStage,
        monitor="val/occworld_mIoU",
        mode="max",
    )
)
