"""Scene encoders: a tokenizer stage's VQ model as the :class:`~occtrain.core.protocols.SceneEncoder`
of the world models that read discrete codes, and where a world-model export keeps it."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from occtrain.core.tokenizer_exports import load_tokenizer
from occtrain.errors import ConfigError
from occtrain.models.tokenizers.base import SceneTokenizer

#: Where a world-model export keeps a copy of its scene encoder's own export.
SCENE_ENCODER_DIR = "scene_tokenizer"


class VQSceneEncoder(nn.Module):
    """A frozen VQ scene tokenizer as a scene encoder: a scene is its codes, flat and
    codebook-major (``num_codebooks * h * w``), decoded through the tokenizer's decoder."""

    discrete = True

    tokenizer: SceneTokenizer

    def __init__(self, tokenizer: SceneTokenizer):
        super().__init__()
        self.tokenizer = tokenizer.eval().requires_grad_(False)
        self.export_dir: Path | None = tokenizer.export_dir

    def train(self, mode: bool = True) -> VQSceneEncoder:
        super().train(mode)
        self.tokenizer.eval()  # frozen: no dropout, no codebook updates
        return self

    @property
    def device(self) -> torch.device:
        return self.tokenizer.codebook.device

    @property
    def latent_hw(self) -> tuple[int, int]:
        h, w = self.tokenizer.latent_hw
        return h, w

    @property
    def codebooks(self) -> list[torch.Tensor]:
        return self.tokenizer.codebooks

    @property
    def codebook_sizes(self) -> list[int]:
        return self.tokenizer.codebook_sizes

    @torch.no_grad()
    def encode(self, semantics: torch.Tensor) -> torch.Tensor:
        return self.tokenizer.encode(semantics.to(self.device)).flatten(1)

    @torch.no_grad()
    def decode(self, scenes: torch.Tensor) -> torch.Tensor:
        h, w = self.latent_hw
        k = self.tokenizer.num_codebooks
        grids = scenes.view(-1, h, w) if k == 1 else scenes.view(-1, k, h, w)
        return self.tokenizer.decode_labels(grids.long().to(self.device))


def vq_scene_encoder(exports: dict[str, Path], world_cfg: object = None) -> VQSceneEncoder:
    """The scene encoder of a pretrain stage: the consumed tokenizer stage's export."""
    if "tokenizer" not in exports:
        raise ConfigError("a pretrain stage of this family consumes a tokenizer stage; add one to consumes")
    return VQSceneEncoder(load_tokenizer(exports["tokenizer"]))


def load_vq_scene_encoder(export_dir: Path, config: dict | None = None) -> VQSceneEncoder:
    """The scene encoder a world-model export holds (its copy of the tokenizer export)."""
    return VQSceneEncoder(load_tokenizer(Path(export_dir) / SCENE_ENCODER_DIR))
