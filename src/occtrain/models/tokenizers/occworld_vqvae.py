"""OccWorld's scene tokenizer (the papers' baseline): a 2D VQ-VAE over the BEV plane with
height in channels. A shared block: OccWorld's family registers it, Occ-LLM's MS-VAE
builds on its body (through the ``voxel_input`` / ``voxel_output`` hooks) and OccVLA
decodes its queries through its decoder."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from occtrain.config.tokenizer import QuantizerFields, latent_hw
from occtrain.formats.occ3d import GRID_SHAPE, NUM_CLASSES
from occtrain.models.tokenizers.base import SceneTokenizer, TokenizerOutput, check_semantics
from occtrain.models.tokenizers.conv import ConvDecoder, ConvEncoder, ConvLayout
from occtrain.models.tokenizers.losses import ce_lovasz, class_balance_weights
from occtrain.models.tokenizers.quantizer import VectorQuantizer


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


class OccWorldVQVAE(SceneTokenizer):
    """Class embedding (E per voxel), the Z axis folded into channels (Z * E), conv encoder,
    VQ, conv decoder back to Z * E channels; a voxel's logits are the dot products of its
    decoded E-vector with the class embeddings (the embedding table is shared both ways).

    Loss: ``ce_weight`` * CE + ``lovasz_weight`` * Lovasz-softmax + ``vq_weight`` * VQ loss.
    """

    def __init__(self, cfg: OccWorldVQVAEConfig):
        super().__init__()
        self.cfg = cfg
        self.latent_hw = latent_hw(cfg)
        depth, e = GRID_SHAPE[2], cfg.class_embed_dim
        self.class_embed = nn.Embedding(NUM_CLASSES, e)
        layout = ConvLayout(ch=cfg.base_channels, channel_mult=list(cfg.channel_mult), strides=list(cfg.strides),
                            num_res_blocks=cfg.num_res_blocks, latent_attention=cfg.latent_attention)  # fmt: skip
        self.encoder = ConvEncoder(in_ch=depth * e, out_ch=cfg.z_channels, **layout)
        self.quant_proj = nn.Conv2d(cfg.z_channels, cfg.code_dim, 1)
        self.quantizer = VectorQuantizer(
            cfg.num_codes, cfg.code_dim, cfg.beta, cfg.ema_decay, cfg.restart_threshold, cfg.usage_decay
        )
        self.post_quant_proj = nn.Conv2d(cfg.code_dim, cfg.z_channels, 1)
        self.decoder = ConvDecoder(in_ch=cfg.z_channels, out_ch=depth * e, **layout)

    def encode_latent(self, semantics: torch.Tensor) -> torch.Tensor:
        b, x, y, z = semantics.shape
        emb = self.voxel_input(self.class_embed(semantics))  # (B, X, Y, Z, E)
        bev = emb.reshape(b, x, y, z * self.cfg.class_embed_dim).permute(0, 3, 1, 2)
        return self.quant_proj(self.encoder(bev))

    def decode_logits(self, z_q: torch.Tensor) -> torch.Tensor:
        feats = self.decoder(self.post_quant_proj(z_q))  # (B, Z * E, X, Y)
        b, _, x, y = feats.shape
        feats = self.voxel_output(feats.view(b, GRID_SHAPE[2], self.cfg.class_embed_dim, x, y))
        # Channels-last in memory, (B, 18, X, Y, Z) as a view: the losses read it per voxel.
        return torch.einsum("bzexy,ce->bxyzc", feats, self.class_embed.weight).permute(0, 4, 1, 2, 3)

    def voxel_input(self, emb: torch.Tensor) -> torch.Tensor:
        """Per-voxel embeddings (B, X, Y, Z, E) before the height is folded; a hook for variants."""
        return emb

    def voxel_output(self, feats: torch.Tensor) -> torch.Tensor:
        """Decoded per-voxel features (B, Z, E, X, Y) before the class dot products; a hook for variants."""
        return feats

    def forward(self, semantics: torch.Tensor) -> TokenizerOutput:
        """Reconstruct (B, 200, 200, 16) labels through the codebook; losses and codebook stats."""
        semantics = check_semantics(semantics)
        vq = self.quantizer(self.encode_latent(semantics))
        logits = self.decode_logits(vq.z_q)
        weights = class_balance_weights(semantics, self.cfg.class_balance)
        ce, lovasz = ce_lovasz(logits, semantics, lovasz_voxels=self.cfg.lovasz_voxels, weights=weights)
        cfg = self.cfg
        total = cfg.ce_weight * ce + cfg.lovasz_weight * lovasz + cfg.vq_weight * vq.loss
        losses = {"loss": total, "ce": ce, "lovasz": lovasz, "vq": vq.loss}
        return TokenizerOutput(logits=logits, losses=losses, stats=vq.stats, codes=vq.codes)
