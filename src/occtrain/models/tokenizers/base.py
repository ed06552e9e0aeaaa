"""What every scene tokenizer shares: its output record, the codebook API, input checking."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import torch
from torch import nn

from occtrain.errors import DataError
from occtrain.formats.occ3d import GRID_SHAPE, NUM_CLASSES
from occtrain.models.tokenizers.quantizer import VectorQuantizer


@dataclass
class TokenizerOutput:
    """One forward pass of a tokenizer.

    logits: (B, 18, 200, 200, 16) class scores whose argmax is the reconstruction;
    losses: ``loss`` (the total that is optimised) and its weighted-in parts;
    stats: scalar tensors to log (codebook usage fraction, perplexity);
    codes: (B, h, w) token ids (None for a continuous encoder);
    labels: the reconstruction (B, 200, 200, 16) itself, when it is not the argmax of
    ``logits`` (a point-set encoder voxelizes its points);
    oracles: in evaluation, reconstructions that bound what the encoder can reach, by name
    (``TokenizerModel.oracles``): the best its point budget allows placed on occupied voxels,
    or what a perfect reader of its cameras' pixels lifts into the grid.
    """

    logits: torch.Tensor | None
    losses: dict[str, torch.Tensor]
    stats: dict[str, torch.Tensor]
    codes: torch.Tensor | None
    labels: torch.Tensor | None = None
    oracles: dict[str, torch.Tensor] = field(default_factory=dict)

    def prediction(self) -> torch.Tensor:
        """The reconstructed label volumes (B, 200, 200, 16)."""
        if self.labels is not None:
            return self.labels
        assert self.logits is not None, "an output without labels has logits"
        return self.logits.argmax(1)


class TokenizerModel(nn.Module):
    """What a tokenizer stage trains and exports, whatever it encodes scenes into: codes from
    codebooks (:class:`SceneTokenizer`) or continuous rows (a camera encoder's queries). Its
    capabilities are declared here, with their defaults, for the stage and the export to
    read."""

    #: Scenes become codes of codebooks; False: continuous rows (``num_tokens`` x ``token_dim``).
    discrete: ClassVar[bool] = True
    #: The oracles its evaluation reports beside it (``TokenizerOutput.oracles``' names).
    oracles: ClassVar[tuple[str, ...]] = ()
    #: The export it was loaded from (``core.tokenizer_exports.load_tokenizer``), which a world-model
    #: export copies; None for one built in this process.
    export_dir: Path | None = None

    def export_state_dict(self) -> dict[str, torch.Tensor]:
        """The weights an export keeps: all of them, unless a training-only branch is left out."""
        return self.state_dict()

    def set_voxel_prior(self, prior: torch.Tensor) -> None:
        """The training split's per-voxel prior (X, Y, Z), given before training: a model
        that decodes voxels it has no evidence for keeps it (and exports it) to fill them.
        A dense decoder, which labels every voxel itself, ignores it."""

    @property
    def num_tokens(self) -> int:
        """The rows a scene becomes, for a continuous model (a discrete one's is its latent grid)."""
        raise NotImplementedError(f"{type(self).__name__} encodes scenes to codes; see its latent_hw")

    @property
    def token_dim(self) -> int:
        """The width of those rows, for a continuous model."""
        raise NotImplementedError(f"{type(self).__name__} encodes scenes to codes; see its codebooks")


class SceneTokenizer(TokenizerModel):
    """Base of the tokenizers: ``encode`` scenes to codes, ``decode`` codes to class logits.

    Subclasses provide ``encode_latent`` (semantics -> continuous latent (B, D, h, w)),
    ``decode_logits`` (quantized latent -> logits) and ``forward``.
    """

    quantizer: VectorQuantizer
    latent_hw: tuple[int, int]

    @property
    def num_codes(self) -> int:
        return self.quantizer.num_codes

    @property
    def codebook(self) -> torch.Tensor:
        """(K, code_dim) current code vectors, e.g. to initialise occupancy-token embeddings."""
        return self.quantizer.codebook

    @property
    def codebooks(self) -> list[torch.Tensor]:
        """Every codebook, in the order of ``encode``'s code grids (one here)."""
        return [self.codebook]

    @property
    def codebook_sizes(self) -> list[int]:
        return [int(c.shape[0]) for c in self.codebooks]

    @property
    def num_codebooks(self) -> int:
        return len(self.codebooks)

    @property
    def codebook_names(self) -> list[str]:
        """Names of the codebooks in metrics (``val/<name>_usage``)."""
        return ["codebook"] if self.num_codebooks == 1 else [f"codebook{i}" for i in range(self.num_codebooks)]

    def compiled_blocks(self) -> list[nn.Module]:
        """What ``trainer.compile`` compiles for training: the dense encoder and decoder
        (fixed shapes: one graph each). The quantizer stays eager: its nearest-code search
        and in-place codebook updates gain nothing compiled."""
        return [m for m in (getattr(self, "encoder", None), getattr(self, "decoder", None)) if isinstance(m, nn.Module)]

    def encode_latent(self, semantics: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def decode_logits(self, z_q: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def encode(self, semantics: torch.Tensor) -> torch.Tensor:
        """Token ids (B, h, w) of label volumes (B, 200, 200, 16); never updates the codebook."""
        return self.quantizer.nearest(self.encode_latent(check_semantics(semantics)))

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """Class logits (B, 18, 200, 200, 16) of token ids (B, h, w)."""
        return self.decode_logits(self.quantized(codes))

    def decode_labels(self, codes: torch.Tensor) -> torch.Tensor:
        """The reconstruction (B, 200, 200, 16) of token ids: the argmax of :meth:`decode`.

        What forecasting and evaluation call; a tokenizer whose argmax has a cheaper closed
        form than its full logits overrides it."""
        return self.decode(codes).argmax(1)

    def quantized(self, codes: torch.Tensor) -> torch.Tensor:
        """The quantized latent (B, code_dim, h, w) of token ids (B, h, w), after checking their grid."""
        if tuple(codes.shape[1:]) != tuple(self.latent_hw):
            raise DataError(
                f"codes of shape {tuple(codes.shape)}: this tokenizer decodes (B, {self.latent_hw[0]}, "
                f"{self.latent_hw[1]}) grids"
            )
        return self.quantizer.lookup(codes.long())


def check_semantics(semantics: torch.Tensor) -> torch.Tensor:
    """The label volume as long, after checking its (B, 200, 200, 16) shape and integer dtype."""
    if semantics.dim() != 4 or tuple(semantics.shape[1:]) != GRID_SHAPE:
        raise DataError(
            f"semantics of shape {tuple(semantics.shape)}: tokenizers take (B, {', '.join(map(str, GRID_SHAPE))}) "
            "Occ3D label volumes"
        )
    if semantics.is_floating_point():
        raise DataError(f"semantics of dtype {semantics.dtype}: pass integer class labels in [0, {NUM_CLASSES})")
    return semantics.long()
