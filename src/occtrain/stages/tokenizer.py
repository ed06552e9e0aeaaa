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
from occtrain.metrics import CodebookUsage, OccupancyMetric
from occtrain.models import count_parameters
from occtrain.occ3d import FREE, MOVABLE_CLASSES
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
        self.recon_occworld = OccupancyMetric(convention="occworld", subsets={"movable": MOVABLE_CLASSES})
        self.recon_occ3d = OccupancyMetric(convention="occ3d")
        #: The trivial baseline: an empty (all free) scene.
        self.baseline_free = OccupancyMetric(convention="occworld")
        self.val_means = ValidationMeans("val/loss")
        #: Code use over the whole val split, per codebook (motion and static for the MS-VAE).
        self.code_usage = torch.nn.ModuleDict(
            {name: CodebookUsage(size) for name, size in zip(self.model.codebook_names, self.model.codebook_sizes)}
        )
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
        codes = out.codes if len(self.code_usage) > 1 else out.codes[:, None]  # (B, codebooks, h, w)
        for i, usage in enumerate(self.code_usage.values()):
            usage.update(codes[:, i])
        self.val_means.update("val/loss", out.losses["loss"], sem.shape[0])

    def on_validation_epoch_end(self) -> None:
        for prefix, metric in (
            ("val/occworld", self.recon_occworld), ("val/occ3d", self.recon_occ3d), ("val/baseline_free_occworld", self.baseline_free),
        ):
            result = metric.compute()
            self.log(f"{prefix}_mIoU", result["mIoU"])
            self.log(f"{prefix}_IoU", result["IoU"])
            if "movable_mIoU" in result:  # where motion separation should show
                self.log(f"{prefix}_movable_mIoU", result["movable_mIoU"].float())
            metric.reset()
        for name, usage in self.code_usage.items():
            result = usage.compute()
            self.log(f"val/{name}_usage", result["usage"])
            self.log(f"val/{name}_perplexity", result["perplexity"])
            usage.reset()
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
