"""OccLLaMA's scene-tokenizer config (Sec. III-A) and world-model settings (Sec. III-B);
its task settings are in ``tasks``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from occtrain.config.tokenizer import QuantizerFields, latent_hw
from occtrain.core.ego_steps import SCENE_QUERIES
from occtrain.errors import ConfigError

if TYPE_CHECKING:
    from occtrain.core.lm_world_model import WorldInputs


@dataclass
class OccLLaMATokenizerConfig(QuantizerFields):
    """OccLLaMA's tokenizer: sparse pillar encoder + swin block, VQ, decoupled status/semantics decoder.

    Defaults follow the paper's ``50 x 256 x 2048`` (latent side, feature dimension, codebook
    size) and its loss weights lambda1 = lambda2 = 2, lambda3 = 0.5 (Eq. 9-10).
    """

    num_codes: int = 2048
    code_dim: int = 256
    #: Dimension of the per-point (height, label) embedding inside a pillar.
    class_embed_dim: int = 64
    base_channels: int = 64
    channel_mult: list[int] = field(default_factory=lambda: [1, 2, 4])
    strides: list[int] = field(default_factory=lambda: [2, 2])
    #: ResNet blocks per level of the decoder (it follows OccWorld's decoder).
    num_res_blocks: int = 2
    #: Swin blocks at the latent; they alternate regular and shifted windows.
    swin_depth: int = 2
    swin_heads: int = 8
    #: Side of a square attention window; clipped to the latent side.
    window_size: int = 5
    mlp_ratio: float = 4.0
    #: Per-voxel feature dimension C of the decoded volume, input of the heads h_a and h_n.
    voxel_feature_dim: int = 16
    #: Eq. 9: weight of the semantics reconstruction loss.
    lambda1: float = 2.0
    #: Eq. 9: weight of the occupancy-status reconstruction loss.
    lambda2: float = 2.0
    #: Eq. 10: weight of Lovasz-softmax inside each reconstruction loss.
    lambda3: float = 0.5
    vq_weight: float = 1.0

    def validate(self, where: str) -> None:
        super().validate(where)
        dim = self.base_channels * self.channel_mult[-1]
        if dim % self.swin_heads:
            raise ConfigError(f"{where}.swin_heads: {self.swin_heads} must divide the latent channels {dim}")
        window = min(self.window_size, *latent_hw(self))
        if any(side % window for side in latent_hw(self)):
            raise ConfigError(
                f"{where}.window_size: {self.window_size} must divide the latent side {latent_hw(self)[0]}"
            )


@dataclass
class OccLLaMAWorldConfig:
    """``model.occllama`` of a pretrain stage: OccLLaMA's world model (Sec. III-B)."""

    #: ``learned`` (the paper's): each query is a learnable ``<scene_q_j>`` token.
    #: ``last_scene`` (not the paper's): query j is the code token at cell j of the scene
    #: before it, at the new scene's positions, so keeping a cell's code is the identity;
    #: the model then learns what changes between scenes rather than each scene anew.
    #: ``moved_last_scene`` (not the paper's): the scene before, moved by the ego's step to
    #: the new scene (the waypoint laid out or generated before it) and re-encoded through
    #: the frozen tokenizer, so the ego's own motion, most of what changes between frames,
    #: is in the queries rather than left for the model to learn; unmoved when no waypoint
    #: came between. ``moved_observed_scene`` (not the paper's): the last observed scene
    #: (the prompt's present) moved by the ego's whole move since it (the waypoint before
    #: the new scene), so no forecast step's queries pass through a generated scene: a
    #: coarse tokenizer's decode-encode cycle, repeated step after step, would blur them.
    scene_queries: str = "learned"
    #: How the LLM reads a scene. 0 (the paper's): one token per latent cell (the joint
    #: vocabulary's codes layout). p > 0 (not the paper's): one token per p x p patch of the
    #: latent grid, its cells' codes riding beside the id (the patches layout,
    #: ``core.patch_layout``): a 25 x 25 latent is 625 tokens a scene, or 25 at p = 5.
    patch_size: int = 0
    #: Patches only: where a query carries a scene (``scene_queries`` other than ``learned``),
    #: the patch head adds this learned per-codebook bias (its initial value) to the logit of
    #: the code the query's cell holds, so an untrained model writes its queries back (the
    #: moved present, with ``moved_observed_scene``) and training learns where to differ.
    #: 0: the copy path starts off.
    copy_bias: float = 4.0
    #: Patches only: per-cell feature width of the patch head (``core.patch_layout.PatchHead``).
    cell_dim: int = 64
    #: Patches only, where a query carries a scene: the loss weight of a cell whose target
    #: code differs from the one its query carries, against 1 for a kept one (not the
    #: paper's). What the moved present gets wrong is what the model is for, and a few such
    #: cells among hundreds kept are otherwise a rounding error of the loss. 1: all alike.
    change_weight: float = 1.0
    #: Patches only, where a query carries a scene: the loss weight of a cell where an agent moved (a
    #: movable-class voxel differs between the moved present and the future: where it came
    #: from and went to; ``core.forecast_targets``), against 1 for the rest (not the paper's).
    #: What the moved present cannot say is where the others went. 1: every cell alike.
    mover_weight: float = 1.0

    def validate(self, where: str, inputs: WorldInputs) -> None:
        """One line naming the key when a setting is unknown or cannot work over ``inputs``
        (a ``WorldInputs``)."""
        if self.scene_queries not in SCENE_QUERIES:
            raise ConfigError(f"{where}.scene_queries: '{self.scene_queries}' is not one of {', '.join(SCENE_QUERIES)}")
        latent = tuple(inputs.scene.latent_hw)
        if self.patch_size < 0 or (self.patch_size and (latent[0] % self.patch_size or latent[1] % self.patch_size)):
            raise ConfigError(
                f"{where}.patch_size: {self.patch_size} must be 0 (a token per latent cell) or divide the tokenizer's "
                f"latent grid {latent[0]} x {latent[1]}"
            )
        if not math.isfinite(self.copy_bias):
            raise ConfigError(f"{where}.copy_bias: must be a finite number, got {self.copy_bias}")
        for key in ("change_weight", "mover_weight"):
            if not math.isfinite(getattr(self, key)) or getattr(self, key) < 1:
                raise ConfigError(
                    f"{where}.{key}: must be a number >= 1 (those cells count at least as the rest), got "
                    f"{getattr(self, key)}"
                )
        if self.cell_dim < 1:
            raise ConfigError(f"{where}.cell_dim: must be >= 1, got {self.cell_dim}")
        for key in ("change_weight", "mover_weight"):
            if not self.patch_size and getattr(self, key) != 1:
                # The codes layout's loss is the LLM's own cross-entropy over scene tokens.
                raise ConfigError(
                    f"{where}.{key}: weighs the patch head's cells, but patch_size is 0 (a token per latent cell, "
                    "the LLM's own loss); set patch_size (e.g. 5) or leave the weight at 1"
                )
