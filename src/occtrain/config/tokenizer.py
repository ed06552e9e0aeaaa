"""What every scene tokenizer's config shares: the codebook fields, the latent grid, validation.

Each architecture's own config lives in its family (``occtrain.families.<family>``) and
derives from :class:`QuantizerFields`. Tokenizers shrink the 200 x 200 BEV plane by a list
of per-stage strides, so the latent side is ``200 / prod(strides)`` (paper: 50,
quickstart: 10). Use :func:`latent_hw` on a dataclass or an omegaconf DictConfig alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from occtrain.errors import ConfigError
from occtrain.formats.occ3d import GRID_SHAPE


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
    #: Cross-entropy weight of an occupied voxel: its class's frequency among the batch's
    #: occupied voxels to the power ``-class_balance``, the occupied keeping their total;
    #: free voxels weigh 1 (``tokenizers.losses.class_balance_weights``). 0 is the papers'
    #: unweighted loss, under which a small tokenizer reconstructs no moving object: cars,
    #: buses and pedestrians are 1.6 % of the voxels (docs/families/occllama.md, "Switches beyond the papers").
    class_balance: float = 0.0

    @property
    def latent_hw(self) -> tuple[int, int]:
        return latent_hw(self)

    def validate(self, where: str) -> None:
        """Raise a one-line ConfigError naming ``<where>.<key>``; subclasses add their checks."""
        validate_common(self, where)


def latent_hw(cfg: Any) -> tuple[int, int]:
    """(h, w) of the token grid: the 200 x 200 plane divided by the product of ``strides``."""
    r = math.prod(int(s) for s in cfg.strides)
    return GRID_SHAPE[0] // r, GRID_SHAPE[1] // r


def validate_common(cfg: Any, where: str) -> None:
    """Checks every convolutional tokenizer needs (strides, channel multipliers, codebook)."""
    strides = list(cfg.strides)
    if not strides or any(s < 1 for s in strides):
        raise ConfigError(f"{where}.strides: {strides} must be a non-empty list of positive integers")
    r = math.prod(strides)
    if GRID_SHAPE[0] % r or GRID_SHAPE[1] % r:
        raise ConfigError(
            f"{where}.strides: their product {r} must divide {GRID_SHAPE[0]} (e.g. [2, 2] -> 50, [4, 5] -> 10)"
        )
    if len(cfg.channel_mult) != len(strides) + 1:
        raise ConfigError(
            f"{where}.channel_mult: needs one entry per level, i.e. len(strides) + 1 = {len(strides) + 1}, got "
            f"{len(cfg.channel_mult)}"
        )
    for key in ("num_codes", "code_dim", "base_channels", "class_embed_dim"):
        if getattr(cfg, key) < 1:
            raise ConfigError(f"{where}.{key}: must be >= 1, got {getattr(cfg, key)}")
    if not 0.0 <= cfg.ema_decay < 1.0:
        raise ConfigError(f"{where}.ema_decay: {cfg.ema_decay} must be in [0, 1) (0 turns EMA off)")
    if not 0.0 <= cfg.class_balance <= 1.0:
        raise ConfigError(
            f"{where}.class_balance: {cfg.class_balance} must lie in [0, 1] (0: the papers' unweighted loss)"
        )
    if not 0.0 < cfg.usage_decay < 1.0:
        raise ConfigError(f"{where}.usage_decay: {cfg.usage_decay} must be in (0, 1)")
