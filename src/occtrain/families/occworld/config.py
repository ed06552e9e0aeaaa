"""Config of OccWorld's VQ-VAE, the baseline scene tokenizer; defaults are the released sizes."""

from __future__ import annotations

from dataclasses import dataclass, field

from occtrain.config.tokenizer import QuantizerFields


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
