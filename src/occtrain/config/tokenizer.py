"""Structured configs of the two scene tokenizers; the defaults are the published sizes.

Both tokenizers shrink the 200 x 200 BEV plane by a list of per-stage strides, so the
latent side is ``200 / prod(strides)`` (paper: 50, quickstart: 10). Use
:func:`latent_hw` on a dataclass or an omegaconf DictConfig alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from occtrain.errors import ConfigError
from occtrain.occ3d import GRID_SHAPE


@dataclass
class QuantizerFields:
    """Codebook settings shared by both tokenizers."""

    #: K, the number of codebook entries (= occupancy tokens of the world model).
    num_codes: int = 512
    #: Dimension of one code vector.
    code_dim: int = 128
    #: Weight of the commitment term ||z - sg(e)||^2.
    beta: float = 1.0
    #: EMA decay of the codebook; 0 learns the codebook by the codebook loss instead.
    ema_decay: float = 0.0
    #: Restart a code whose running assignment count per batch falls below this (0: never).
    restart_threshold: float = 0.0
    #: Decay of that running assignment count.
    usage_decay: float = 0.99
    #: Voxels per batch the Lovasz-softmax term is evaluated on (0: all, the exact loss; a
    #: CPU recipe samples, since the exact loss sorts every voxel for every class).
    lovasz_voxels: int = 0


@dataclass
class OccWorldVQVAEConfig(QuantizerFields):
    """OccWorld's VQ-VAE: class embedding, height folded into channels, 2D ResNet encoder/decoder.

    Defaults match the released model (embedding 8, channels 64 x (1, 2, 4), two ResNet blocks per
    level, attention at the 50 x 50 latent, 512 codes of dimension 128): about 14.2 M parameters.
    """

    class_embed_dim: int = 8
    base_channels: int = 64
    #: Channel multiplier of each resolution level; one more entry than ``strides``.
    channel_mult: list[int] = field(default_factory=lambda: [1, 2, 4])
    #: Downsampling stride between consecutive levels; their product must divide 200.
    strides: list[int] = field(default_factory=lambda: [2, 2])
    num_res_blocks: int = 2
    #: Self-attention blocks at the latent resolution (OccWorld: yes, at 50 x 50).
    latent_attention: bool = True
    #: Channels of the encoder output before the 1x1 projection to ``code_dim``.
    z_channels: int = 128
    ce_weight: float = 10.0
    lovasz_weight: float = 1.0
    vq_weight: float = 1.0

    @property
    def latent_hw(self) -> tuple[int, int]:
        return latent_hw(self)


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

    @property
    def latent_hw(self) -> tuple[int, int]:
        return latent_hw(self)


def latent_hw(cfg: Any) -> tuple[int, int]:
    """(h, w) of the token grid: the 200 x 200 plane divided by the product of ``strides``."""
    r = math.prod(int(s) for s in cfg.strides)
    return GRID_SHAPE[0] // r, GRID_SHAPE[1] // r


def validate_tokenizer_config(cfg: OccWorldVQVAEConfig | OccLLaMATokenizerConfig, where: str) -> None:
    """Raise a one-line ConfigError naming ``<where>.<key>`` for settings no model can be built from."""
    strides = list(cfg.strides)
    if not strides or any(s < 1 for s in strides):
        raise ConfigError(f"{where}.strides: {strides} must be a non-empty list of positive integers")
    r = math.prod(strides)
    if GRID_SHAPE[0] % r or GRID_SHAPE[1] % r:
        raise ConfigError(f"{where}.strides: their product {r} must divide {GRID_SHAPE[0]} (e.g. [2, 2] -> 50, [4, 5] -> 10)")
    if len(cfg.channel_mult) != len(strides) + 1:
        raise ConfigError(
            f"{where}.channel_mult: needs one entry per level, i.e. len(strides) + 1 = {len(strides) + 1}, got {len(cfg.channel_mult)}"
        )
    for key in ("num_codes", "code_dim", "base_channels", "class_embed_dim"):
        if getattr(cfg, key) < 1:
            raise ConfigError(f"{where}.{key}: must be >= 1, got {getattr(cfg, key)}")
    if not 0.0 <= cfg.ema_decay < 1.0:
        raise ConfigError(f"{where}.ema_decay: {cfg.ema_decay} must be in [0, 1) (0 turns EMA off)")
    if not 0.0 < cfg.usage_decay < 1.0:
        raise ConfigError(f"{where}.usage_decay: {cfg.usage_decay} must be in (0, 1)")
    if isinstance(cfg, OccLLaMATokenizerConfig):
        dim = cfg.base_channels * cfg.channel_mult[-1]
        if dim % cfg.swin_heads:
            raise ConfigError(f"{where}.swin_heads: {cfg.swin_heads} must divide the latent channels {dim}")
        window = min(cfg.window_size, *latent_hw(cfg))
        if any(side % window for side in latent_hw(cfg)):
            raise ConfigError(f"{where}.window_size: {cfg.window_size} must divide the latent side {latent_hw(cfg)[0]}")
