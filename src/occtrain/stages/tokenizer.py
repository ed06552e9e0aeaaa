"""Stage kind ``tokenizer``: train a scene tokenizer of any registered architecture on single frames.

The architectures (OccWorld's VQ-VAE, OccLLaMA's tokenizer, ...) come from the families'
registrations; ``model.arch`` picks one and ``model.<arch>`` holds its settings. Validation
reports reconstruction mIoU/IoU in both conventions, labelled: OccWorld (what tokenizer
tables report: all voxels) and Occ3D (camera-visible voxels only). The export holds the
weights, the architecture's config and the codebook size, which the pretraining stage
needs to lay out its joint vocabulary.
"""

from __future__ import annotations

from dataclasses import field, make_dataclass
from pathlib import Path
from typing import Any

import torch

from occtrain.config import to_container
from occtrain.errors import ConfigError
from occtrain.families import save_tokenizer, tokenizer_archs, tokenizer_config
from occtrain.metrics.reconstruction import ReconstructionMetrics
from occtrain.models import count_parameters
from occtrain.stages import StageKind, register
from occtrain.stages.base import Stage, StageContext, StageReport
from occtrain.stages.common import ValidationMeans, configure_adamw, freeze_prefixes


def tokenizer_model_schema() -> type:
    """``model:`` of a tokenizer stage: ``arch`` plus one section per registered architecture."""
    archs = tokenizer_archs()
    fields = [("arch", str, field(default="occworld_vqvae"))]
    fields += [(name, arch.config, field(default_factory=arch.config)) for name, arch in archs.items()]
    return make_dataclass("TokenizerModelConfig", fields)


TokenizerModelConfig = tokenizer_model_schema()


class TokenizerStage(Stage):
    """Trains a scene tokenizer with its own losses; validates reconstruction IoU."""

    def __init__(self, ctx: StageContext):
        super().__init__(ctx)
        cfg = ctx.model_cfg
        archs = tokenizer_archs()
        if cfg.arch not in archs:
            raise ConfigError(f"stages '{ctx.spec.name}': model.arch '{cfg.arch}' is not one of {', '.join(archs)}")
        arch_cfg = tokenizer_config(cfg.arch, cfg[cfg.arch], f"stages '{ctx.spec.name}'.model.{cfg.arch}")
        self.arch_cfg = to_container(cfg[cfg.arch])
        self.model = archs[cfg.arch].model(arch_cfg)
        freeze_prefixes(self.model, list(ctx.spec.freeze))
        #: Both conventions, an empty scene as the baseline, code use per codebook (motion and static for the MS-VAE).
        self.recon = ReconstructionMetrics(dict(zip(self.model.codebook_names, self.model.codebook_sizes)))
        self.val_means = ValidationMeans("val/loss")
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
        self.recon.update(pred, sem, batch["mask_camera"], out.codes)
        self.val_means.update("val/loss", out.losses["loss"], sem.shape[0])

    def on_validation_epoch_end(self) -> None:
        self.log_dict({f"val/{k}": v for k, v in self.recon.compute().items()})
        self.recon.reset()
        self.log_dict(self.val_means.pop())

    def configure_optimizers(self) -> dict:
        params = [p for p in self.model.parameters() if p.requires_grad]
        return configure_adamw(params, self.ctx.spec.optim, self.ctx.trainer.max_steps)

    # -- reporting and export
    def report(self) -> StageReport:
        n = count_parameters(self.model)
        scenes = [
            (f"val sample {i}: ground truth vs reconstruction", [("ground truth", gt), ("reconstruction", rec)])
            for i, (gt, rec) in enumerate(self._pictures)
        ]
        return StageReport(f"{self.ctx.model_cfg.arch} {n / 1e6:.2f}M params", {"params": float(n)}, scenes=scenes)

    def export(self, path: Path) -> Path:
        return save_tokenizer(self.model, self.ctx.model_cfg.arch, self.arch_cfg, path)


TOKENIZER = register(
    StageKind(
        name="tokenizer",
        model_schema=TokenizerModelConfig,
        data_kind="frames",
        module=TokenizerStage,
        monitor="val/occworld_mIoU",
        mode="max",
    )
)
