"""Stage kind ``vision``: pretrain the camera encoder on dense targets the renderer provides.

The multi-view encoder (a SigLIP/CLIP vision tower + per-camera embeddings) and a dense
head predict each pixel's class (the 18 Occ3D labels, 17 = sky/no surface) and depth.
Losses: cross-entropy over all pixels and L1 on log depth over pixels with a surface.
Validation scores the whole val split against a trivial baseline fitted on the train split
at the start of fit: each camera pixel's most frequent class and geometric mean depth. The export is
the tower as a standard Hugging Face directory plus occtrain's parts, which later stages
load with :func:`occtrain.models.camera_encoder.load_vision_encoder`, frozen or fine-tuned.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.utilities.types import OptimizerLRSchedulerConfig

from occtrain.errors import ConfigError, DataError
from occtrain.metrics import DepthAbsRelMetric, PixelSegmentationMetric
from occtrain.models import count_parameters
from occtrain.models.camera_encoder import (
    DenseHead,
    MultiViewEncoder,
    PixelPrior,
    VisionConfig,
    export_vision,
    pixel_losses,
)
from occtrain.models.llm import checkpoint_layers
from occtrain.stages import StageKind, register
from occtrain.stages.common import ValidationMeans
from occtrain.stages.optim import configure_adamw, freeze_prefixes
from occtrain.stages.stage import Stage, StageContext, StageReport

TOWER_PREFIX = "encoder.tower."
#: What a batch must carry: the camera images and the renderer's dense targets.
CAMERA_KEYS = ("images", "cam_class", "cam_depth")


@dataclass
class VisionModelConfig:
    """``model:`` of a vision stage."""

    vision: VisionConfig = field(default_factory=VisionConfig)
    #: Weight of the per-pixel class cross-entropy.
    class_weight: float = 1.0
    #: Weight of the L1 loss on log depth (pixels with a surface only).
    depth_weight: float = 1.0
    #: Train only the camera embedding and the dense head (a probe of a loaded tower).
    freeze_tower: bool = False
    #: Train batches (per process) the per-pixel prior baseline is counted over; 0: no baseline.
    prior_batches: int = 16
    #: Recompute the tower's layer activations in backward instead of keeping them.
    gradient_checkpointing: bool = False


class VisionStage(Stage):
    """Trains the multi-view encoder with a dense class + depth head; validates per-pixel mIoU and AbsRel."""

    reads_cameras = True

    def __init__(self, ctx: StageContext):
        super().__init__(ctx)
        cfg = ctx.model_cfg
        where = f"stages '{ctx.spec.name}'.model"
        for key in ("class_weight", "depth_weight"):
            if getattr(cfg, key) < 0:
                raise ConfigError(f"{where}.{key}: {getattr(cfg, key)} must not be negative")
        if cfg.prior_batches < 0:
            raise ConfigError(f"{where}.prior_batches: {cfg.prior_batches} must not be negative (0: no baseline)")
        v = cfg.vision
        self.encoder = MultiViewEncoder(v)
        self.head = DenseHead(self.encoder.hidden_size, self.encoder.patch_size)
        if cfg.freeze_tower:
            self.encoder.tower.requires_grad_(False)
            if v.path:  # the frozen tower comes back from its directory; checkpoints need not hold it
                self.frozen_prefixes = (TOWER_PREFIX,)
        freeze_prefixes(self, list(ctx.spec.freeze))
        if cfg.gradient_checkpointing:
            checkpoint_layers(self.encoder.tower)
        self.image_hw = (v.image_height, v.image_width)
        self.prior = PixelPrior(v.num_cameras, v.image_height, v.image_width)
        self.pixel = PixelSegmentationMetric()
        self.depth = DepthAbsRelMetric()
        self.prior_pixel = PixelSegmentationMetric()
        self.prior_depth = DepthAbsRelMetric()
        self.val_means = ValidationMeans("val/loss", "val/class_loss", "val/depth_loss")
        self._last: dict[str, float] = {}

    # -- model
    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """uint8 images (B, N, H, W, 3) -> class logits (B, N, C, H, W), log-depth (B, N, H, W)."""
        tokens, grid = self.encoder(images)
        return self.head(tokens, grid, images.shape[1], self.image_hw)

    def losses(self, batch: dict[str, Any]) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
        """The weighted loss and its parts, with the predictions they came from."""
        cfg = self.ctx.model_cfg
        missing = [k for k in CAMERA_KEYS if k not in batch]
        if missing:
            raise DataError(
                f"{self.ctx.data.root}: frames carry no {', '.join(missing)}; a vision stage trains on camera images "
                "with the per-pixel class and depth the synthetic renderer writes"
            )
        logits, log_depth = self(batch["images"])
        class_loss, depth_loss = pixel_losses(logits, log_depth, batch["cam_class"], batch["cam_depth"])
        loss = cfg.class_weight * class_loss + cfg.depth_weight * depth_loss
        return {"loss": loss, "class_loss": class_loss, "depth_loss": depth_loss}, logits, log_depth

    # -- training
    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        losses, _, _ = self.losses(batch)
        bs = batch["images"].shape[0]
        for name, value in losses.items():
            self.log(f"train/{name}", value, batch_size=bs, prog_bar=name == "loss")
        return losses["loss"]

    def configure_optimizers(self) -> OptimizerLRSchedulerConfig:
        params = [p for p in self.parameters() if p.requires_grad]
        return configure_adamw(params, self.ctx.spec.optim, self.ctx.trainer.max_steps)

    # -- the trivial baseline
    def fit_prior(self, batches: Iterable[dict[str, Any]]) -> None:
        """Count the per-pixel prior over ``batches`` (a train stream), replacing any earlier one."""
        self.prior.reset()
        for batch in batches:
            if "cam_class" not in batch or "cam_depth" not in batch:
                raise DataError(
                    f"{self.ctx.data.root}: frames carry no cam_class/cam_depth; the per-pixel prior needs the "
                    "renderer's targets"
                )
            self.prior.update(batch["cam_class"], batch["cam_depth"])

    def on_fit_start(self) -> None:
        n = self.ctx.model_cfg.prior_batches
        datamodule = getattr(self.trainer, "datamodule", None)  # set by Lightning when fit has one
        if not n or datamodule is None:
            return
        # Each rank counts its share of the train stream; the sums are added over ranks, so
        # every rank scores the same prior. A fresh loader and a forked RNG leave training's
        # data position and random draws as they would be without the baseline.
        with torch.random.fork_rng(devices=[]):
            self.fit_prior(itertools.islice(datamodule.train_dataloader(), math.ceil(n / self.trainer.world_size)))
        self.prior.reduce(lambda t: self.trainer.strategy.reduce(t, reduce_op="sum"))

    # -- validation
    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        losses, logits, log_depth = self.losses(batch)
        target, depth = batch["cam_class"].long(), batch["cam_depth"].float()
        self.pixel.update(logits.argmax(2), target)
        self.depth.update(log_depth.exp(), depth)
        if self.prior.fitted:
            prior_class, prior_depth = self.prior.predict(target.shape[0])
            self.prior_pixel.update(prior_class, target)
            self.prior_depth.update(prior_depth, depth)
        for name, value in losses.items():
            self.val_means.update(f"val/{name}", value, target.shape[0])

    def validation_results(self) -> dict[str, float]:
        """This validation's metrics (every rank must call it), then reset."""
        out = self.val_means.pop()
        seg = self.pixel.compute()
        out["val/pixel_mIoU"] = float(seg["mIoU"])
        out.update({f"val/pixel_IoU_{name}": float(v) for name, v in seg["per_class"].items()})
        out["val/depth_absrel"] = float(self.depth.compute())
        if self.prior.fitted:
            out["val/baseline_prior_pixel_mIoU"] = float(self.prior_pixel.compute()["mIoU"])
            out["val/baseline_prior_depth_absrel"] = float(self.prior_depth.compute())
        for metric in (self.pixel, self.depth, self.prior_pixel, self.prior_depth):
            metric.reset()
        return out

    def on_validation_epoch_end(self) -> None:
        self._last = self.validation_results()
        self.log_dict(self._last)

    # -- reporting and export
    def report(self) -> StageReport:
        tower, total = count_parameters(self.encoder.tower), count_parameters(self)
        summary = (
            f"{self.encoder.tower.config.model_type} tower {tower / 1e6:.2f}M + {(total - tower) / 1e3:.0f}K params"
        )
        m = self._last
        if "val/pixel_mIoU" in m:
            summary += f"; pixel mIoU {m['val/pixel_mIoU']:.1f}"
            if "val/baseline_prior_pixel_mIoU" in m:
                summary += f" (prior {m['val/baseline_prior_pixel_mIoU']:.1f})"
            summary += f", depth AbsRel {m['val/depth_absrel']:.3f}"
            if "val/baseline_prior_depth_absrel" in m:
                summary += f" (prior {m['val/baseline_prior_depth_absrel']:.3f})"
        return StageReport(summary, {"params": float(total), "params_tower": float(tower)})

    def export(self, path: Path) -> Path:
        return export_vision(path, self.encoder, self.head, {"stage": self.ctx.spec.name})


VISION = register(
    StageKind(
        name="vision",
        model_schema=VisionModelConfig,
        data_kind="frames",
        module=VisionStage,
        monitor="val/pixel_mIoU",
        mode="max",
    )
)
