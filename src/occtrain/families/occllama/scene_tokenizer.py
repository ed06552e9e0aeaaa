"""OccLLaMA's scene tokenizer: sparse pillar encoder, VQ codebook, decoupled status/semantics decoder.

Decoupled combination (paper Eq. 8): x^ = x^_a * not M(x^_a) + x^_n * M(x^_a), i.e. a voxel is
free where the status head h_a says free, and takes the semantics head h_n's class where it
says occupied. :func:`combine_decoupled` writes this as 18-class scores whose argmax is exactly
that rule: score(free) = log P_a(free); score(c) = log P_a(occupied) + log P_n(c) - max_c' log P_n(c')
for the 17 non-free classes. So the best non-free class scores log P_a(occupied) and wins iff
P_a(occupied) > P_a(free); exp(score(free)) is the status head's probability of free space.

Loss (Eq. 9-10): lambda1 * L_r(semantics, over occupied voxels) + lambda2 * L_r(status) + L_vq,
with L_r = CE + lambda3 * Lovasz-softmax.
"""

from __future__ import annotations

import torch
from torch import nn

from occtrain.config.tokenizer import latent_hw
from occtrain.families.occllama.config import OccLLaMATokenizerConfig
from occtrain.formats.occ3d import FREE, GRID_SHAPE
from occtrain.models.tokenizers.base import SceneTokenizer, TokenizerOutput, check_semantics
from occtrain.models.tokenizers.conv import ConvDecoder, ResnetBlock
from occtrain.models.tokenizers.losses import ce_lovasz, class_balance_weights
from occtrain.models.tokenizers.quantizer import VectorQuantizer
from occtrain.models.tokenizers.swin import SwinStage

#: Status classes of the occupancy-status head h_a.
STATUS_OCCUPIED, STATUS_FREE = 0, 1


class PillarEncoder(nn.Module):
    """Each BEV pillar's non-free voxels as points (height d, label l) -> one pillar feature.

    A point's feature is MLP(embed(l) + embed(d)); a pillar takes the max over its points
    (PointPillars-style); pillars without points get a learned empty-pillar vector. Only
    the non-free voxels are computed on, gathered with ``nonzero``.
    """

    def __init__(self, dim: int):
        super().__init__()
        self.label_embed = nn.Embedding(FREE, dim)  # labels 0..16; free voxels are not points
        self.height_embed = nn.Embedding(GRID_SHAPE[2], dim)
        self.point_mlp = nn.Sequential(nn.Linear(dim, dim), nn.LayerNorm(dim), nn.ReLU())
        self.empty = nn.Parameter(torch.zeros(dim))

    def forward(self, semantics: torch.Tensor) -> torch.Tensor:
        """(B, X, Y, Z) labels -> (B, dim, X, Y) pillar features."""
        b, x, y, _ = semantics.shape
        occupied = semantics != FREE
        where = occupied.nonzero()  # (n, 4): batch, x, y, z in the same order as semantics[occupied]
        points = self.point_mlp(self.label_embed(semantics[occupied]) + self.height_embed(where[:, 3]))
        pillar = (where[:, 0] * x + where[:, 1]) * y + where[:, 2]
        dim = points.shape[1]
        pooled = points.new_zeros(b * x * y, dim).scatter_reduce(
            0, pillar[:, None].expand(-1, dim), points, reduce="amax", include_self=False
        )
        filled = occupied.any(-1).view(-1, 1)
        pooled = torch.where(filled, pooled, self.empty)
        return pooled.view(b, x, y, dim).permute(0, 3, 1, 2)


class SparseEncoder(nn.Module):
    """Pillar features -> per-stage (ResNet block, patch merging by the stage's stride) -> Swin at the latent."""

    def __init__(self, cfg: OccLLaMATokenizerConfig):
        super().__init__()
        widths = [cfg.base_channels * m for m in cfg.channel_mult]
        self.pillars = PillarEncoder(cfg.class_embed_dim)
        self.stem = nn.Conv2d(cfg.class_embed_dim, widths[0], 3, padding=1)
        stages: list[nn.Module] = []
        for i, stride in enumerate(cfg.strides):
            # A stride x stride conv with equal stride is patch merging: a linear map of each patch.
            stages += [ResnetBlock(widths[i], widths[i]), nn.Conv2d(widths[i], widths[i + 1], stride, stride=stride)]
        self.stages = nn.Sequential(*stages)
        self.swin = SwinStage(
            widths[-1], cfg.swin_depth, cfg.swin_heads, cfg.window_size, latent_hw(cfg), cfg.mlp_ratio
        )
        self.norm = nn.LayerNorm(widths[-1])
        self.proj = nn.Linear(widths[-1], cfg.code_dim)

    def forward(self, semantics: torch.Tensor) -> torch.Tensor:
        """(B, X, Y, Z) labels -> (B, code_dim, h, w) continuous latent."""
        bev = self.stages(self.stem(self.pillars(semantics)))
        z = self.proj(self.norm(self.swin(bev.permute(0, 2, 3, 1))))
        return z.permute(0, 3, 1, 2)


def _head(dim: int, classes: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(dim, dim), nn.SiLU(), nn.Linear(dim, classes))


def combine_decoupled(status_logits: torch.Tensor, semantic_logits: torch.Tensor) -> torch.Tensor:
    """Eq. 8 as 18-class scores (see the module docstring): (B, 2, ...) + (B, 17, ...) -> (B, 18, ...).

    Non-free classes keep their label index 0..16; free space is the last label (occ3d.FREE).
    """
    # Computed channels-last (contiguous for the heads' output), returned as a (B, 18, ...) view.
    log_status = status_logits.movedim(1, -1).log_softmax(-1)
    log_sem = semantic_logits.movedim(1, -1).log_softmax(-1)
    occupied = log_status[..., STATUS_OCCUPIED : STATUS_OCCUPIED + 1]
    semantic_scores = occupied + log_sem - log_sem.amax(-1, keepdim=True)
    return torch.cat([semantic_scores, log_status[..., STATUS_FREE : STATUS_FREE + 1]], dim=-1).movedim(-1, 1)


def decoupled_labels(
    status_logits: torch.Tensor, semantic_logits: torch.Tensor, tolerance: float = 1e-4
) -> torch.Tensor:
    """Eq. 8's labels (B, ...) without the 18-class scores: the semantics head's class where
    the status head says occupied, free space elsewhere; exactly the argmax of
    :func:`combine_decoupled`, whose log-softmax over 17 classes of every voxel it skips.

    Where two logits lie within ``tolerance`` of each other, the scores' float rounding can
    order them differently from the logits (a tie, and the first index wins): those few
    voxels (about one in 25 million) take their label from the scores themselves.
    """
    occ, free = status_logits[:, STATUS_OCCUPIED], status_logits[:, STATUS_FREE]
    labels = torch.where(occ >= free, semantic_logits.argmax(1), FREE)
    best = semantic_logits.amax(1, keepdim=True)
    close = ((occ - free).abs() <= tolerance) | ((semantic_logits >= best - tolerance).sum(1) > 1)
    if close.any():
        where = close.nonzero(as_tuple=True)
        # Gathered as (n, classes) rows: combine_decoupled reads dim 1 as the class axis.
        rows = status_logits.movedim(1, -1)[where], semantic_logits.movedim(1, -1)[where]
        labels[where] = combine_decoupled(*rows).argmax(1)
    return labels


class OccLLaMATokenizer(SceneTokenizer):
    """Sparse encoder -> VQ (K codes) -> OccWorld-style conv decoder to a (X, Y, Z, C) feature volume,
    read by the status head h_a (occupied / free) and the semantics head h_n (17 non-free classes)."""

    def __init__(self, cfg: OccLLaMATokenizerConfig):
        super().__init__()
        self.cfg = cfg
        self.latent_hw = latent_hw(cfg)
        self.encoder = SparseEncoder(cfg)
        self.quantizer = VectorQuantizer(
            cfg.num_codes, cfg.code_dim, cfg.beta, cfg.ema_decay, cfg.restart_threshold, cfg.usage_decay
        )
        self.decoder = ConvDecoder(
            in_ch=cfg.code_dim, ch=cfg.base_channels, channel_mult=list(cfg.channel_mult), strides=list(cfg.strides),
            num_res_blocks=cfg.num_res_blocks, latent_attention=True, out_ch=GRID_SHAPE[2] * cfg.voxel_feature_dim,
        )  # fmt: skip
        self.status_head = _head(cfg.voxel_feature_dim, 2)
        self.semantic_head = _head(cfg.voxel_feature_dim, FREE)

    def compiled_blocks(self) -> list[nn.Module]:
        """The decoder alone: the sparse encoder gathers each scene's occupied voxels, as
        many as it has (a new shape every batch)."""
        return [self.decoder]

    def encode_latent(self, semantics: torch.Tensor) -> torch.Tensor:
        return self.encoder(semantics)

    def voxel_features(self, z_q: torch.Tensor) -> torch.Tensor:
        """The decoder's feature volume (B, X, Y, Z, C) of a quantized latent, read by both heads."""
        feats = self.decoder(z_q)  # (B, Z * C, X, Y)
        b, _, x, y = feats.shape
        return feats.view(b, GRID_SHAPE[2], self.cfg.voxel_feature_dim, x, y).permute(0, 3, 4, 1, 2)

    def decode_heads(self, z_q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Status logits (B, 2, X, Y, Z) and semantics logits (B, 17, X, Y, Z) of a quantized latent."""
        voxels = self.voxel_features(z_q)
        status = self.status_head(voxels).permute(0, 4, 1, 2, 3)
        semantic = self.semantic_head(voxels).permute(0, 4, 1, 2, 3)
        return status, semantic

    def decode_logits(self, z_q: torch.Tensor) -> torch.Tensor:
        return combine_decoupled(*self.decode_heads(z_q))

    def decode_labels(self, codes: torch.Tensor, tolerance: float = 1e-4) -> torch.Tensor:
        """The argmax of :meth:`decode`, with the semantics head read only where the status
        head says occupied (or within ``tolerance`` of it): a few per cent of the voxels."""
        voxels = self.voxel_features(self.quantized(codes))
        status = self.status_head(voxels)  # (B, X, Y, Z, 2)
        candidates = status[..., STATUS_OCCUPIED] >= status[..., STATUS_FREE] - tolerance
        labels = torch.full(candidates.shape, FREE, dtype=torch.long, device=codes.device)
        # (n, classes) rows: decoupled_labels reads dim 1 as the class axis.
        labels[candidates] = decoupled_labels(status[candidates], self.semantic_head(voxels[candidates]), tolerance)
        return labels

    def forward(self, semantics: torch.Tensor) -> TokenizerOutput:
        """Reconstruct (B, 200, 200, 16) labels; Eq. 9-10 losses and codebook stats."""
        semantics = check_semantics(semantics)
        vq = self.quantizer(self.encode_latent(semantics))
        voxels = self.voxel_features(vq.z_q)
        status_logits = self.status_head(voxels).permute(0, 4, 1, 2, 3)
        occupied = semantics != FREE
        status = torch.where(occupied, STATUS_OCCUPIED, STATUS_FREE)
        weights = class_balance_weights(semantics, self.cfg.class_balance)
        # The semantics loss reads the occupied voxels only (a few per cent of them), so
        # the semantics head runs on those alone, as (n, 17) rows.
        sem_ce, sem_lovasz = ce_lovasz(
            self.semantic_head(voxels[occupied]),
            semantics[occupied],
            lovasz_voxels=self.cfg.lovasz_voxels,
            weights=None if weights is None else weights[occupied],
        )
        # Unweighted: the occupied/free decision keeps the data's odds (see class_balance_weights).
        status_ce, status_lovasz = ce_lovasz(status_logits, status, lovasz_voxels=self.cfg.lovasz_voxels)
        cfg = self.cfg
        total = (
            cfg.lambda1 * (sem_ce + cfg.lambda3 * sem_lovasz)
            + cfg.lambda2 * (status_ce + cfg.lambda3 * status_lovasz)
            + cfg.vq_weight * vq.loss
        )
        losses = {
            "loss": total,
            "semantic_ce": sem_ce,
            "semantic_lovasz": sem_lovasz,
            "status_ce": status_ce,
            "status_lovasz": status_lovasz,
            "vq": vq.loss,
        }
        # The loss reads the two heads; the combined scores serve evaluation (argmax, display)
        # and would cost a training step a sixth of its time.
        if self.training:
            return TokenizerOutput(logits=None, losses=losses, stats=vq.stats, codes=vq.codes)
        semantic_logits = self.semantic_head(voxels).permute(0, 4, 1, 2, 3)
        logits = combine_decoupled(status_logits.detach(), semantic_logits.detach())
        return TokenizerOutput(logits=logits, losses=losses, stats=vq.stats, codes=vq.codes)
