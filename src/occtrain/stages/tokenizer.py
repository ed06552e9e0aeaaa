"""Stage kind ``tokenizer``: train a scene tokenizer of any registered architecture on single frames.

The architectures (OccWorld's VQ-VAE, OccLLaMA's tokenizer, SparseOccVLA's camera-reading
sparse occupancy encoder, ...) come from the families' registrations; ``model.arch`` picks
one and ``model.<arch>`` holds its settings. An architecture that reads the cameras gets the
frames' images and may consume a vision stage, whose frozen encoder is its distillation
teacher. Validation reports reconstruction mIoU/IoU in both conventions, labelled: OccWorld
(what tokenizer tables report: all voxels) and Occ3D (camera-visible voxels only). The
export holds the weights, the architecture's config and the layout (codebooks, or tokens
and their width) that the pretraining stage lays its joint vocabulary out from.
"""

from __future__ import annotations

from dataclasses import dataclass, field, make_dataclass
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.utilities.types import OptimizerLRSchedulerConfig
from omegaconf import MISSING

from occtrain.config import to_container
from occtrain.core.registry import TokenizerArch, tokenizer_archs, tokenizer_family
from occtrain.core.tokenizer_exports import load_tokenizer, save_tokenizer, tokenizer_config
from occtrain.data.frames import frames_batch
from occtrain.data.layout import DatasetIndex
from occtrain.data.voxel_prior import voxel_prior
from occtrain.errors import ConfigError
from occtrain.metrics.reconstruction import ReconstructionMetrics
from occtrain.models import count_parameters
from occtrain.models.camera_encoder import load_vision_encoder
from occtrain.models.tokenizers.base import SceneTokenizer, TokenizerModel, TokenizerOutput
from occtrain.progress import progress_bar
from occtrain.stages import StageKind, register
from occtrain.stages.common import ValidationMeans
from occtrain.stages.optim import configure_adamw, freeze_prefixes
from occtrain.stages.stage import EvalRequest, EvalResult, Stage, StageContext, StageReport


@dataclass
class TokenizerModelConfig:
    """``model:`` of a tokenizer stage: ``arch`` (a registered architecture) and ``model.<arch>``."""

    arch: str = MISSING


def _arch_of(model: Any) -> TokenizerArch | None:
    return tokenizer_archs().get(str(model["arch"] if isinstance(model, dict) else getattr(model, "arch", "")))


def reconstruction_metrics(model: TokenizerModel, root: str | Path, cache_dir: Path | None) -> ReconstructionMetrics:
    """Both conventions, an empty scene and the per-voxel prior of ``root``'s train split
    (kept in ``cache_dir``) as the baselines, the model's oracles, code use per codebook
    (motion and static for the MS-VAE; none for a continuous encoder)."""
    prior = torch.from_numpy(voxel_prior(root, cache_dir))
    if not isinstance(model, SceneTokenizer):
        return ReconstructionMetrics({}, oracles=model.oracles, prior=prior)
    return ReconstructionMetrics(dict(zip(model.codebook_names, model.codebook_sizes)), prior=prior)


class TokenizerStage(Stage):
    """Trains a scene tokenizer with its own losses; validates reconstruction IoU."""

    count_flops = True
    evaluable = True
    #: A vision stage: the distillation teacher of an architecture that takes one.
    consumes_kinds = ("vision",)
    consumes_count = (0, 1)
    frozen_prefixes = ("teacher.",)

    @classmethod
    def family_of(cls, model: dict, consumed: dict[str, Any]) -> str | None:
        """The family that registered ``model.arch``."""
        return tokenizer_family(str(model["arch"])) if model.get("arch") else None

    @classmethod
    def model_schema(cls, kind: StageKind, family: str | None, model: dict | None = None) -> type:
        """``arch`` and that architecture's section only: another architecture's defaults are no part of the hash."""
        arch = (model or {}).get("arch")
        archs = tokenizer_archs()
        if arch not in archs:
            return kind.model_schema
        return make_dataclass(
            f"TokenizerModelConfig_{arch}",
            [(arch, archs[arch].config, field(default_factory=archs[arch].config))],
            bases=(kind.model_schema,),
        )

    @classmethod
    def check_family(cls, family: str | None, consumed: dict[str, Any], where: str) -> None:
        if family is None:
            raise ConfigError(
                f"{where}: model.arch is missing; tokenizer architectures are {', '.join(tokenizer_archs())}"
            )

    @classmethod
    def check_model(cls, model: Any, key: str) -> None:
        """The architecture's own checks (heads dividing channels, windows the latent grid)."""
        tokenizer_config(model.arch, model[model.arch], f"{key}.{model.arch}")

    @classmethod
    def camera_input(cls, model: Any) -> bool:
        arch = _arch_of(model)
        return bool(arch is not None and arch.reads_cameras)

    def __init__(self, ctx: StageContext):
        super().__init__(ctx)
        cfg = ctx.model_cfg
        archs = tokenizer_archs()
        if cfg.arch not in archs:
            raise ConfigError(f"stages '{ctx.spec.name}': model.arch '{cfg.arch}' is not one of {', '.join(archs)}")
        arch_cfg = tokenizer_config(cfg.arch, cfg[cfg.arch], f"stages '{ctx.spec.name}'.model.{cfg.arch}")
        self.arch = archs[cfg.arch]
        self.arch_cfg = to_container(cfg[cfg.arch])
        self.model = self.arch.model(arch_cfg)
        freeze_prefixes(self.model, list(ctx.spec.freeze))
        self.teacher = self._teacher(ctx)
        if self.teacher is not None:
            self.model.attach_teacher(self.teacher.hidden_size)
        self.index = DatasetIndex.open(ctx.data.root) if self.arch.reads_cameras else None
        self.recon = reconstruction_metrics(self.model, ctx.data.root, ctx.shared_cache_dir)
        if self.recon.prior is not None:
            self.model.set_voxel_prior(self.recon.prior)
        self.val_means = ValidationMeans("val/loss")
        self._pictures: list[tuple] = []

    def _teacher(self, ctx: StageContext) -> torch.nn.Module | None:
        """The frozen encoder of the consumed vision stage (a distillation teacher), or None."""
        where = f"stages '{ctx.spec.name}'"
        if not ctx.inputs:
            return None
        if "vision" not in self.arch.teachers:
            raise ConfigError(f"{where}: a {ctx.model_cfg.arch} tokenizer takes no teacher; remove its consumes")
        return load_vision_encoder(next(iter(ctx.inputs.values())))

    def forward(self, batch: dict[str, Any]) -> TokenizerOutput:
        """One pass of the tokenizer over a frames batch: the labels, or for an architecture
        that reads the cameras the whole batch with the dataset and the teacher."""
        if self.arch.reads_cameras:
            return self.model(batch, self.index, self.teacher)
        return self.model(batch["semantics"].long())

    def train(self, mode: bool = True) -> TokenizerStage:
        super().train(mode)
        if self.teacher is not None:
            self.teacher.eval()  # frozen
        return self

    # -- training
    def compiled_blocks(self) -> list[torch.nn.Module]:
        return self.model.compiled_blocks()

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        out = self({**batch, "seed": self.step_seed(self.global_step)})
        bs = batch["semantics"].shape[0]
        for name, value in out.losses.items():
            self.log(f"train/{name}", value, batch_size=bs, prog_bar=name == "loss")
        for name, value in out.stats.items():
            self.log(f"train/{name}", value, batch_size=bs)
        return out.losses["loss"]

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        sem = batch["semantics"].long()
        out = self({**batch, "seed": self.ctx.data.seed})
        pred = out.prediction()
        if batch_idx == 0:  # kept for the dashboard's ground truth vs reconstruction pictures
            self._pictures = [
                (sem[i].to(torch.uint8).cpu().numpy(), pred[i].to(torch.uint8).cpu().numpy())
                for i in range(min(2, len(sem)))
            ]
        self.recon.update(pred, sem, batch["mask_camera"], out.codes, out.oracles)
        self.val_means.update("val/loss", out.losses["loss"], sem.shape[0])

    def on_validation_epoch_end(self) -> None:
        self.log_dict({f"val/{k}": v for k, v in self.recon.compute().items()})
        self.recon.reset()
        self.log_dict(self.val_means.pop())

    def configure_optimizers(self) -> OptimizerLRSchedulerConfig:
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

    @classmethod
    @torch.no_grad()
    def evaluate_export(cls, request: EvalRequest) -> EvalResult:
        """Reconstruction of every frame of the split (or the first ``samples``): IoU/mIoU in
        the ``occworld`` and ``occ3d`` conventions, beside an empty scene, and each
        codebook's usage and perplexity over the split."""
        model = load_tokenizer(request.export)
        arch = tokenizer_archs()[model.arch]
        index = DatasetIndex.open(request.data_root)
        every = [(scene, token) for scene in index.splits.get(request.split, []) for token in index.scenes[scene]]
        frames = every if request.samples < 0 else every[: request.samples]
        recon = reconstruction_metrics(model, request.data_root, request.shared_cache_dir)
        size = request.batch_size
        with progress_bar(len(frames), f"reconstructing {len(frames)} {request.split} frames") as advance:
            for i in range(0, len(frames), size):
                batch = frames_batch(index, frames[i : i + size], arch.reads_cameras, pixel_truth=bool(model.oracles))
                sem = batch["semantics"].long()
                if arch.reads_cameras:
                    out = model(batch, index, None)
                    recon.update(out.prediction(), sem, batch["mask_camera"], oracles=out.oracles)
                else:
                    codes = model.encode(sem)
                    recon.update(model.decode_labels(codes), sem, batch["mask_camera"], codes)
                advance(len(frames[i : i + size]))
        return EvalResult.on_items(
            {"frames": float(len(frames)), **recon.compute()}, "frames", [t for _, t in frames], [t for _, t in every]
        )


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
