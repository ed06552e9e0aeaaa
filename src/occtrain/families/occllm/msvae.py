"""Occ-LLM's Motion-Separation VAE: one encoder and decoder, two codebooks.

Eq. 5-7 of the paper, as implemented here: the movable grid keeps the movable voxels and
sets every other voxel free (Eq. 5 as printed has the indicator inverted; read as a typo),
the static grid keeps the rest with the movable voxels set free. Both go through the
shared encoder; the movable latent is quantized by the motion codebook, the static one by
the static codebook; the shared decoder decodes each, and the reconstruction takes the
motion branch wherever it predicts a non-free class, the static branch elsewhere (Eq. 7).
Loss (Eq. 8, whose printed sign is a slip: the negative log-likelihood is minimised):
cross-entropy (+ Lovasz, as OccWorld's) of each separated grid plus each codebook's
commitment term.
"""

from __future__ import annotations

import torch
from torch import nn

from occtrain.families.occllm.config import MSVAEConfig
from occtrain.formats.occ3d import CLASS_INDEX, FREE
from occtrain.models.tokenizers.base import TokenizerOutput, check_semantics
from occtrain.models.tokenizers.losses import ce_lovasz, class_balance_weights
from occtrain.models.tokenizers.occworld_vqvae import OccWorldVQVAE
from occtrain.models.tokenizers.quantizer import VectorQuantizer


def separate(semantics: torch.Tensor, movable: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(movable grid, static grid) of label volumes: each keeps its own voxels, the rest free."""
    is_movable = movable[semantics]
    free = torch.full_like(semantics, FREE)
    return torch.where(is_movable, semantics, free), torch.where(is_movable, free, semantics)


def merge(logits_motion: torch.Tensor, logits_static: torch.Tensor) -> torch.Tensor:
    """Logits (B, 18, X, Y, Z) taking the motion branch where it predicts non-free (Eq. 7)."""
    take = (logits_motion.argmax(1) != FREE).unsqueeze(1)
    return torch.where(take, logits_motion, logits_static)


class MSVAE(OccWorldVQVAE):
    """OccWorld's VQ-VAE plus a 3D convolution on each side and motion separation.

    Without motion separation it is a one-codebook VAE (Table III's baselines); codes then
    have one grid per scene, else two: (B, 2, h, w), motion first.
    """

    #: (18,) bool: which classes the motion grid keeps.
    movable: torch.Tensor

    def __init__(self, cfg: MSVAEConfig):
        super().__init__(cfg)
        e = cfg.class_embed_dim
        # Light: one 3x3x3 convolution at the class-embedding width on each side.
        self.pre3d = nn.Conv3d(e, e, 3, padding=1) if cfg.conv3d else None
        self.post3d = nn.Conv3d(e, e, 3, padding=1) if cfg.conv3d else None
        self.quantizer_motion = (
            VectorQuantizer(
                cfg.num_codes_motion, cfg.code_dim, cfg.beta, cfg.ema_decay, cfg.restart_threshold, cfg.usage_decay
            )
            if cfg.motion_separation
            else None
        )
        movable = torch.zeros(FREE + 1, dtype=torch.bool)
        movable[[CLASS_INDEX[c] for c in cfg.movable_classes]] = True
        self.register_buffer("movable", movable, persistent=False)

    @property
    def codebook_names(self) -> list[str]:
        return ["motion", "static"] if self.quantizer_motion is not None else ["codebook"]

    @property
    def codebooks(self) -> list[torch.Tensor]:
        """(motion, static) with motion separation, else the one codebook."""
        if self.quantizer_motion is None:
            return [self.codebook]
        return [self.quantizer_motion.codebook, self.codebook]

    def voxel_input(self, emb: torch.Tensor) -> torch.Tensor:
        if self.pre3d is None:
            return emb
        return self.pre3d(emb.permute(0, 4, 1, 2, 3)).permute(0, 2, 3, 4, 1)

    def voxel_output(self, feats: torch.Tensor) -> torch.Tensor:
        if self.post3d is None:
            return feats
        return self.post3d(feats.permute(0, 2, 3, 4, 1)).permute(0, 4, 1, 2, 3)  # (B, Z, E, X, Y) <-> (B, E, X, Y, Z)

    def forward(self, semantics: torch.Tensor) -> TokenizerOutput:
        """Reconstruct (B, 200, 200, 16) labels; losses and per-codebook usage statistics."""
        semantics = check_semantics(semantics)
        cfg = self.cfg
        if self.quantizer_motion is None:
            return super().forward(semantics)
        moving, static = separate(semantics, self.movable)
        # One pass of the shared encoder and decoder over both grids, stacked on the batch axis.
        latent_m, latent_s = self.encode_latent(torch.cat([moving, static])).chunk(2)
        vq_m, vq_s = self.quantizer_motion(latent_m), self.quantizer(latent_s)
        logits_m, logits_s = self.decode_logits(torch.cat([vq_m.z_q, vq_s.z_q])).chunk(2)
        ce_m, lov_m = ce_lovasz(
            logits_m, moving, lovasz_voxels=cfg.lovasz_voxels, weights=class_balance_weights(moving, cfg.class_balance)
        )
        ce_s, lov_s = ce_lovasz(
            logits_s, static, lovasz_voxels=cfg.lovasz_voxels, weights=class_balance_weights(static, cfg.class_balance)
        )
        total = (
            cfg.ce_weight * (ce_m + ce_s)
            + cfg.lovasz_weight * (lov_m + lov_s)
            + cfg.vq_weight * (vq_m.loss + vq_s.loss)
        )
        losses = {"loss": total, "ce_motion": ce_m, "ce_static": ce_s, "lovasz_motion": lov_m, "lovasz_static": lov_s,
                  "vq_motion": vq_m.loss, "vq_static": vq_s.loss}  # fmt: skip
        stats = {f"motion_{k}": v for k, v in vq_m.stats.items()} | {f"static_{k}": v for k, v in vq_s.stats.items()}
        return TokenizerOutput(merge(logits_m, logits_s), losses, stats, torch.stack([vq_m.codes, vq_s.codes], 1))

    def encode(self, semantics: torch.Tensor) -> torch.Tensor:
        """Token ids: (B, h, w) with one codebook, (B, 2, h, w) (motion, static) with two."""
        semantics = check_semantics(semantics)
        if self.quantizer_motion is None:
            return super().encode(semantics)
        latent_m, latent_s = self.encode_latent(torch.cat(separate(semantics, self.movable))).chunk(2)
        return torch.stack([self.quantizer_motion.nearest(latent_m), self.quantizer.nearest(latent_s)], 1)

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """Merged class logits (B, 18, 200, 200, 16) of ``encode``'s codes."""
        if self.quantizer_motion is None:
            return super().decode(codes)
        codes = codes.long()
        z_q = torch.cat([self.quantizer_motion.lookup(codes[:, 0]), self.quantizer.lookup(codes[:, 1])])
        return merge(*self.decode_logits(z_q).chunk(2))
