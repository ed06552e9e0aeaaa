"""OccLLaMA's scene-tokenizer config (Sec. III-A) and world-model settings (Sec. III-B);
its task settings are in ``tasks``."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from occtrain.config.tokenizer import QuantizerFields, latent_hw
from occtrain.errors import ConfigError


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


#: What a scene's query block is made of ("next_scene" mode): the paper's learnable
#: ``<scene_q_j>`` tokens, the code tokens of the scene before it, those of the scene
#: before it moved by the ego's step, or those of the observed present moved by the ego's
#: move since it.
SCENE_QUERIES = ("learned", "last_scene", "moved_last_scene", "moved_observed_scene")


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

    def validate(self, where: str, inputs: Any) -> None:
        """One line naming the key when a setting is unknown."""
        if self.scene_queries not in SCENE_QUERIES:
            raise ConfigError(f"{where}.scene_queries: '{self.scene_queries}' is not one of {', '.join(SCENE_QUERIES)}")
