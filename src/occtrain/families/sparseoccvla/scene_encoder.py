"""The trained sparse occupancy encoder as a world model's frozen scene encoder
(``core.protocols.SceneEncoder``): a frame's scene is its N query rows ``[P_L | Q_L]``,
encoded from the cameras once per dataset and decoded back to labels through the last
layer's points."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from occtrain.core.scene_encoders import SCENE_ENCODER_DIR
from occtrain.core.tokenizer_exports import load_tokenizer
from occtrain.data.layout import DatasetIndex
from occtrain.errors import ConfigError
from occtrain.families.sparseoccvla.encoder import SparseOccEncoder

ARCH = "sparseocc"


class SparseSceneEncoder(nn.Module):
    """A frozen :class:`~occtrain.families.sparseoccvla.encoder.SparseOccEncoder` read as scene rows."""

    discrete = False

    def __init__(self, encoder: SparseOccEncoder):
        super().__init__()
        self.encoder = encoder.eval().requires_grad_(False)
        self.export_dir: Path | None = encoder.export_dir

    def train(self, mode: bool = True) -> SparseSceneEncoder:
        super().train(mode)
        self.encoder.eval()
        return self

    @property
    def num_tokens(self) -> int:
        return self.encoder.num_tokens

    def encode(self, semantics: torch.Tensor) -> torch.Tensor:
        raise ValueError("the sparse occupancy encoder reads the cameras: encode samples of a dataset (encode_samples)")

    @torch.no_grad()
    def encode_samples(self, index: DatasetIndex, samples: list[tuple[str, str]]) -> torch.Tensor:
        return self.encoder.encode_samples(index, samples)

    @torch.no_grad()
    def decode(self, rows: torch.Tensor) -> torch.Tensor:
        """Rows (B, N, 3 + D) -> label volumes (B, X, Y, Z): the encoder's own reconstruction."""
        rows = rows.to(self.encoder.queries.device).float()
        return self.encoder.voxelize(*self.encoder.decode_points(rows[..., 3:], rows[..., :3]))


def _sparse(export_dir: Path) -> SparseSceneEncoder:
    encoder = load_tokenizer(export_dir)
    if getattr(encoder, "arch", "") != ARCH:
        raise ConfigError(
            f"{export_dir}: a SparseOccVLA world model reads a '{ARCH}' tokenizer, not "
            f"'{getattr(encoder, 'arch', '?')}'"
        )
    return SparseSceneEncoder(encoder)


def sparse_scene_encoder(exports: dict[str, Path], world_cfg: object = None) -> SparseSceneEncoder:
    """The scene encoder of a pretrain stage: the consumed stage 1's export."""
    if "tokenizer" not in exports:
        raise ConfigError(
            f"a SparseOccVLA pretrain stage consumes its stage 1 (a tokenizer stage with model.arch: {ARCH})"
        )
    return _sparse(exports["tokenizer"])


def load_sparse_scene_encoder(export_dir: Path, config: dict | None = None) -> SparseSceneEncoder:
    """The scene encoder a world-model export holds (its copy of stage 1's export)."""
    return _sparse(Path(export_dir) / SCENE_ENCODER_DIR)
