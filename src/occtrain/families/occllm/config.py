"""Config of Occ-LLM's Motion-Separation VAE (arXiv:2502.06419, Sec. III-A, Table III)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from occtrain.core.ego_steps import SCENE_QUERIES
from occtrain.errors import ConfigError
from occtrain.formats.occ3d import CLASS_INDEX, FREE, MOVABLE_CLASSES, NUM_CLASSES
from occtrain.models.tokenizers.occworld_vqvae import OccWorldVQVAEConfig

if TYPE_CHECKING:
    from occtrain.core.lm_world_model import WorldInputs


@dataclass
class MSVAEConfig(OccWorldVQVAEConfig):
    """OccWorld's 2D VAE (height folded into channels) with Occ-LLM's two additions, each
    switchable for Table III's ablation: a light 3D convolution before the encoder and after
    the decoder, and motion separation (movable and static voxels encoded apart by the shared
    encoder, quantized by two codebooks, decoded by the shared decoder and merged).

    ``num_codes`` is the static codebook's size, ``num_codes_motion`` the movable one's.
    """

    conv3d: bool = True
    # The paper does not list its movable classes: Occ3D's vehicles, cyclists and pedestrians.
    motion_separation: bool = True
    num_codes_motion: int = 512
    movable_classes: list[str] = field(default_factory=lambda: list(MOVABLE_CLASSES))

    def validate(self, where: str) -> None:
        super().validate(where)
        unknown = [c for c in self.movable_classes if c not in CLASS_INDEX or CLASS_INDEX[c] == FREE]
        if unknown:
            raise ConfigError(
                f"{where}.movable_classes: '{unknown[0]}' is not an Occ3D class (0..{NUM_CLASSES - 2} by name)"
            )
        if self.num_codes_motion < 1:
            raise ConfigError(f"{where}.num_codes_motion: must be >= 1, got {self.num_codes_motion}")


@dataclass
class OccLLMWorldConfig:
    """``model.occllm`` of a world-model stage: Occ-LLM's scene tokens (Sec. III-B), each
    switch one of its ablations (Table IV, Table V, frame separation)."""

    #: p: one LLM token per p x p patch of the latent grid (paper: 10 of 50 -> 25 tokens).
    patch_size: int = 2
    #: ``<occ>`` ... ``</occ>`` around every frame (paper: on; off drifts, its Fig. 3).
    frame_separation: bool = True
    #: The ego action gates the latent channels before patchify (Table V).
    pre_fusion: bool = True
    #: Hidden width of the pre-fusion MLP.
    fusion_hidden: int = 64
    #: Per-cell feature width of the patch head (see ``PatchHead``).
    cell_dim: int = 64
    #: What a forecast scene's query block carries (``core.ego_steps.SCENE_QUERIES``; not
    #: the paper's beyond ``learned``, its own). ``moved_observed_scene``: the present moved
    #: by the ego's position at the new frame (the waypoint before it), as OccLLaMA's can,
    #: so a forecast starts from the moved present rather than from nothing.
    scene_queries: str = "learned"
    #: Where a query carries a scene: the copy path's initial per-codebook bias (see
    #: ``core.patch_layout.PatchWorldModel``); unused with ``learned`` queries.
    copy_bias: float = 4.0
    #: The weight of a cell whose target code differs from the code its query carries,
    #: against 1 for one that keeps it (not the paper's): what the moved present gets
    #: wrong (other agents' motion, what the ego's move uncovers) is what the model is
    #: for, and a handful of such cells among hundreds kept is otherwise a rounding error
    #: of the loss. 1: every cell alike.
    change_weight: float = 1.0
    #: Where a query carries a scene: the loss weight of a cell where an agent moved (a
    #: movable-class voxel differs between the moved present and the future: where it came
    #: from and went to; ``core.forecast_targets``), against 1 for the rest (not the paper's).
    #: What the moved present cannot say is where the others went. 1: every cell alike.
    mover_weight: float = 1.0

    def validate(self, where: str, inputs: WorldInputs) -> None:
        """One line naming the key when a setting cannot work over ``inputs`` (a ``WorldInputs``)."""
        if self.scene_queries not in SCENE_QUERIES:
            raise ConfigError(f"{where}.scene_queries: '{self.scene_queries}' is not one of {', '.join(SCENE_QUERIES)}")
        for key in ("copy_bias", "change_weight", "mover_weight"):
            if not math.isfinite(getattr(self, key)):
                raise ConfigError(f"{where}.{key}: must be a finite number, got {getattr(self, key)}")
        for key in ("change_weight", "mover_weight"):
            if getattr(self, key) < 1:
                raise ConfigError(
                    f"{where}.{key}: must be >= 1 (those cells count at least as the rest), got {getattr(self, key)}"
                )
        latent = tuple(inputs.scene.latent_hw)
        if self.patch_size < 1 or latent[0] % self.patch_size or latent[1] % self.patch_size:
            raise ConfigError(
                f"{where}.patch_size: {self.patch_size} must divide the tokenizer's latent grid {latent[0]} x "
                f"{latent[1]}"
            )
        for key in ("fusion_hidden", "cell_dim"):
            if getattr(self, key) < 1:
                raise ConfigError(f"{where}.{key}: must be >= 1, got {getattr(self, key)}")
