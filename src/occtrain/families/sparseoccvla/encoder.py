"""SparseOccVLA's Sparse Occupancy Encoder (Sec. 3.1, App. A) and its connector (Eq. 2).

N learnable queries with 3D positions read multi-view, multi-scale (and multi-frame) image
features through a stack of SparseBEV-style layers: each samples its image features at
points around its position projected into the cameras, mixes them adaptively (weights
generated from the query, as in AdaMixer/SparseBEV), attends to the other queries with
spatial-aware self-attention (Eq. 9) and an FFN, then decodes a set of 3D points with
classes; the number of points grows layer by layer (coarse to fine) and the query moves to
their mean. Training (Eq. 10): the Chamfer distance of every layer's points (and of the
initial positions) to the sparsified ground truth, a focal loss on each point's class
against its nearest ground-truth point's (lambda_focal = 0.2), and feature distillation
(Eq. 3) of the connector's occupancy tokens against a frozen vision teacher's features
sampled where the queries project, through a projection and two independent LayerNorms
(the branch is dropped at inference). The connector ``MLP(Q_L + PE(P_L))`` maps the last
queries to the LLM's width: the occupancy tokens.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from occtrain.data.frames import frames_batch
from occtrain.data.layout import DatasetIndex
from occtrain.errors import ConfigError, DataError
from occtrain.families.sparseoccvla.config import SparseOccConfig
from occtrain.families.sparseoccvla.inputs import CameraFrames, camera_frames, ground_truth
from occtrain.formats.occ3d import FREE, GRID_SHAPE, NUM_CLASSES, RANGE_MAX, RANGE_MIN
from occtrain.models.camera_encoder import pixel_losses
from occtrain.models.point_sets import POINT_CLASSES, chamfer_distance, lifted_pixels, sigmoid_focal_loss, voxelize
from occtrain.models.projection import average_views, in_cameras, project, read_views, sample_views
from occtrain.models.tokenizers.base import TokenizerModel, TokenizerOutput

if TYPE_CHECKING:
    from transformers import PreTrainedModel

#: ImageNet statistics, what a torchvision/Hugging Face ResNet is trained with.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
#: Frequencies of the sinusoidal position features.
PE_FREQUENCIES = 6
#: The height (metres, ego frame) of a ``grid`` layout's initial positions: most occupied
#: voxels lie within a query's reach (``offset_scale``) of it, from the ground to the roofs of cars.
GRID_QUERY_HEIGHT = 1.0


def normalized(points: torch.Tensor) -> torch.Tensor:
    """Ego-frame metres (..., 3) -> the grid's range mapped to [0, 1]."""
    low = torch.tensor(RANGE_MIN, dtype=points.dtype, device=points.device)
    high = torch.tensor(RANGE_MAX, dtype=points.dtype, device=points.device)
    return (points - low) / (high - low)


def sinusoid(x: torch.Tensor, frequencies: int = PE_FREQUENCIES) -> torch.Tensor:
    """Sine and cosine features (..., k * 2 * frequencies) of values (..., k) near [0, 1]."""
    scales = (2.0 ** torch.arange(frequencies, dtype=x.dtype, device=x.device)) * math.pi
    angles = x[..., None] * scales
    return torch.cat([angles.sin(), angles.cos()], -1).flatten(-2)


class PositionEmbedding(nn.Module):
    """PE(P): an MLP of the sinusoidal features of 3D positions (metres)."""

    def __init__(self, dim: int):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(3 * 2 * PE_FREQUENCIES, dim), nn.GELU(), nn.Linear(dim, dim))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.mlp(sinusoid(normalized(points)))


class ImageBackbone(nn.Module):
    """A Hugging Face ResNet (built from config, or a local directory) and a 1 x 1
    projection of each of its stages to the query width: multi-scale feature maps."""

    #: (1, 3, 1, 1): the backbone's input normalisation.
    mean: torch.Tensor
    std: torch.Tensor
    #: A transformers backbone (``channels``, ``feature_maps``).
    resnet: PreTrainedModel

    def __init__(self, cfg: SparseOccConfig):
        super().__init__()
        stages = [f"stage{i + 1}" for i in range(len(cfg.backbone_widths))]
        if cfg.backbone_path:
            self.resnet = _load_backbone(cfg.backbone_path)
        else:
            from transformers import ResNetBackbone, ResNetConfig

            config = ResNetConfig(
                embedding_size=cfg.backbone_widths[0],
                hidden_sizes=list(cfg.backbone_widths),
                depths=list(cfg.backbone_depths),
                layer_type="basic",
                out_features=stages,
            )
            self.resnet = ResNetBackbone(config)
        self.lateral = nn.ModuleList(nn.Conv2d(c, cfg.dim, 1) for c in self.resnet.channels)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, images: torch.Tensor) -> list[torch.Tensor]:
        """uint8 images (..., H, W, 3) -> per scale (..., dim, h, w)."""
        lead = images.shape[:-3]
        x = images.reshape(-1, *images.shape[-3:]).permute(0, 3, 1, 2).float().div(255.0)
        x = (x - self.mean) / self.std
        maps = self.resnet(pixel_values=x).feature_maps
        return [(y := proj(m)).reshape(*lead, *y.shape[1:]) for proj, m in zip(self.lateral, maps)]


def _load_backbone(path: str) -> PreTrainedModel:
    from transformers import AutoBackbone, AutoConfig

    if not (Path(path) / "config.json").is_file():
        raise ConfigError(
            f"model.sparseocc.backbone_path: {path} is not a local Hugging Face model directory (no config.json)"
        )
    try:
        config = AutoConfig.from_pretrained(path, local_files_only=True)
        stages = list(getattr(config, "stage_names", [])[1:])
        return AutoBackbone.from_pretrained(path, local_files_only=True, out_features=stages)
    except (OSError, ValueError, KeyError) as err:
        raise ConfigError(
            f"model.sparseocc.backbone_path: cannot load a backbone from {path} ({str(err).splitlines()[0]})"
        ) from None


class SpatialSelfAttention(nn.Module):
    """Multi-head self-attention whose logits are ``A_ij = q_i . k_j / sqrt(d) - tau_i ||p_i - p_j||``
    (Eq. 9): each query learns (per head) how fast its attention falls off with distance."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.tau = nn.Linear(dim, heads)
        self.out = nn.Linear(dim, dim)
        self.norm = nn.LayerNorm(dim)

    def logits(self, q: torch.Tensor, pos: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Attention logits (B, heads, N, N) and the values (B, heads, N, d)."""
        b, n, d = q.shape
        qh, kh, vh = self.qkv(q).view(b, n, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        tau = F.softplus(self.tau(q)).transpose(1, 2)  # (B, heads, N)
        dist = torch.cdist(pos.float(), pos.float()).to(q.dtype)
        return qh @ kh.transpose(-1, -2) / math.sqrt(d // self.heads) - tau[..., None] * dist[:, None], vh

    def forward(self, q: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        logits, v = self.logits(q, pos)
        mixed = (logits.softmax(-1) @ v).transpose(1, 2).flatten(2)
        return self.norm(q + self.out(mixed))


class AdaptiveMixing(nn.Module):
    """Adaptive mixing of a query's sampled features (SparseBEV): a channel-mixing and a
    point-mixing matrix generated from the query, per channel group, then a projection."""

    def __init__(self, dim: int, groups: int, in_points: int, out_points: int):
        super().__init__()
        self.groups, self.c, self.in_points, self.out_points = groups, dim // groups, in_points, out_points
        self.channel = nn.Linear(dim, groups * self.c * self.c)
        self.point = nn.Linear(dim, groups * in_points * out_points)
        self.out = nn.Linear(dim * out_points, dim)
        self.norm = nn.LayerNorm(dim)
        # The generated matrices start static (their biases) and learn to depend on the query.
        nn.init.zeros_(self.channel.weight)
        nn.init.zeros_(self.point.weight)
        with torch.no_grad():
            self.channel.bias.copy_(torch.eye(self.c).repeat(groups, 1, 1).flatten())
            nn.init.uniform_(self.point.bias, -1 / math.sqrt(in_points), 1 / math.sqrt(in_points))

    def forward(self, q: torch.Tensor, sampled: torch.Tensor) -> torch.Tensor:
        """Queries (B, N, D) and their sampled features (B, N, P_in, D) -> updated queries."""
        b, n = q.shape[:2]
        g, c = self.groups, self.c
        x = sampled.view(b, n, self.in_points, g, c).permute(0, 1, 3, 2, 4)  # (B, N, G, P_in, c)
        x = F.relu(F.layer_norm(x @ self.channel(q).view(b, n, g, c, c), (c,)))
        x = x.transpose(-1, -2) @ self.point(q).view(b, n, g, self.in_points, self.out_points)  # (B, N, G, c, P_out)
        x = F.relu(F.layer_norm(x, (self.out_points,)))
        return self.norm(q + self.out(x.flatten(2)))


class FeedForward(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))
        self.norm = nn.LayerNorm(dim)

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        return self.norm(q + self.mlp(q))


class PixelHead(nn.Module):
    """Each pixel's class logits (the 18 labels, 17 = sky) and log depth (metres) from a
    feature map (..., D, h, w) -> (..., 19, h, w), as the vision stage's head predicts them."""

    def __init__(self, dim: int):
        super().__init__()
        out = nn.Conv2d(dim, NUM_CLASSES + 1, 1)
        assert out.bias is not None
        nn.init.constant_(out.bias[-1:], math.log(10.0))  # depths start near the scene's typical 10 m
        self.net = nn.Sequential(nn.Conv2d(dim, dim, 3, padding=1), nn.GELU(), out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        lead = x.shape[:-3]
        y = self.net(x.reshape(-1, *x.shape[-3:]))
        return y.reshape(*lead, *y.shape[1:])


def dense_loss(dense: torch.Tensor, cam_class: torch.Tensor, cam_depth: torch.Tensor) -> torch.Tensor:
    """The vision stage's losses (``pixel_losses``, summed) of one frame's maps
    (B, V, 19, h, w) against the renderer's targets (B, V, H, W), read at each cell's
    centre pixel."""
    h, w = dense.shape[-2:]
    rows = ((torch.arange(h, device=dense.device) + 0.5) * cam_class.shape[-2] / h).long()
    cols = ((torch.arange(w, device=dense.device) + 0.5) * cam_class.shape[-1] / w).long()
    target = cam_class.to(dense.device)[..., rows, :][..., cols]
    depth = cam_depth.to(dense.device)[..., rows, :][..., cols]
    class_loss, depth_loss = pixel_losses(dense[:, :, :NUM_CLASSES], dense[:, :, NUM_CLASSES], target, depth)
    return class_loss + depth_loss


def surface_cue(
    points: torch.Tensor,
    dense: torch.Tensor,
    cam_to_ego: torch.Tensor,
    uv: torch.Tensor,
    inside: torch.Tensor,
    image_hw: tuple[int, int],
) -> torch.Tensor:
    """Per point (B, M, 19): in each camera that sees it (its pixel ``uv`` (B, V, M, 2),
    ``inside`` (B, V, M)), the class probabilities the per-pixel maps ``dense``
    (B, V, 19, h, w) give there and the point's own depth minus the pixel's predicted depth
    (log metres), averaged over those cameras: the point lies on a surface of that class
    where the gap is 0, in front of it where negative, behind it where positive."""
    read = read_views(dense, uv, image_hw)  # (B, V, M, 19)
    depth = in_cameras(points, cam_to_ego)[..., 2].clamp(min=1e-3).log().to(read.dtype)
    cue = torch.cat([read[..., :NUM_CLASSES].softmax(-1), (depth - read[..., NUM_CLASSES])[..., None]], -1)
    return average_views(cue, inside)[0]


class PointHead(nn.Module):
    """A query -> M points around its position (offsets up to ``scale`` metres) and their class logits."""

    def __init__(self, dim: int, points: int, scale: float):
        super().__init__()
        self.points, self.scale = points, scale
        self.offsets = nn.Linear(dim, points * 3)
        self.classes = nn.Linear(dim, points * POINT_CLASSES)

    def offsets_of(self, q: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.offsets(q)).view(*q.shape[:-1], self.points, 3) * self.scale

    def forward(self, q: torch.Tensor, pos: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Queries (B, N, D) at ``pos`` (B, N, 3) -> points (B, N, M, 3) and logits (B, N, M, C)."""
        return pos[..., None, :] + self.offsets_of(q), self.classes(q).view(*q.shape[:-1], self.points, POINT_CLASSES)


class EncoderLayer(nn.Module):
    """Feature sampling, adaptive mixing, spatial-aware self-attention, FFN, point decoding."""

    def __init__(self, cfg: SparseOccConfig, scales: int, points: int):
        super().__init__()
        self.cfg = cfg
        self.sampling = nn.Linear(cfg.dim, cfg.sampling_points * 3)
        # The depth cue joins the sampled features as one more "scale".
        self.cue = nn.Linear(NUM_CLASSES + 1, cfg.dim) if cfg.depth_cue else None
        reads = scales + (1 if cfg.depth_cue else 0)
        self.mixing = AdaptiveMixing(
            cfg.dim, cfg.mixing_groups, cfg.frames * reads * cfg.sampling_points, cfg.mixed_points
        )
        self.attention = SpatialSelfAttention(cfg.dim, cfg.heads)
        self.ffn = FeedForward(cfg.dim, cfg.ffn_dim)
        self.head = PointHead(cfg.dim, points, cfg.offset_scale)

    def sample(
        self,
        q: torch.Tensor,
        pos: torch.Tensor,
        features: list[torch.Tensor],
        cams: CameraFrames,
        dense: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The image features (B, N, F * scales * S, D) at S points around each query, in
        every frame and scale (and with ``depth_cue`` the cue read from ``dense``, the
        per-pixel head's maps (B, F, V, 19, h, w), as one more scale)."""
        cfg = self.cfg
        b, n = q.shape[:2]
        s = cfg.sampling_points
        points = pos[:, :, None] + torch.tanh(self.sampling(q)).view(b, n, s, 3) * cfg.offset_scale  # current ego frame
        flat = points.reshape(b, n * s, 3)
        out = []
        for f in range(cfg.frames):
            move = cams.current_to_frame[:, f].to(q.dtype)
            in_frame = flat @ move[:, :3, :3].transpose(1, 2) + move[:, None, :3, 3]
            uv, inside = project(
                in_frame, cams.intrinsics[:, f], cams.cam_to_ego[:, f], (cfg.image_height, cfg.image_width)
            )
            for level in features:
                sampled, _ = sample_views(level[:, f], uv, inside, (cfg.image_height, cfg.image_width))
                out.append(sampled.view(b, n, s, -1))
            if self.cue is not None and dense is not None:
                cue = surface_cue(
                    in_frame, dense[:, f], cams.cam_to_ego[:, f], uv, inside, (cfg.image_height, cfg.image_width)
                )
                out.append(self.cue(cue).view(b, n, s, -1))
        return torch.cat(out, 2)

    def forward(
        self,
        q: torch.Tensor,
        pos: torch.Tensor,
        pos_embed: PositionEmbedding,
        features: list[torch.Tensor],
        cams: CameraFrames,
        dense: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        q_in = q + pos_embed(pos)
        q = self.mixing(q_in, self.sample(q_in, pos, features, cams, dense))
        q = self.ffn(self.attention(q + pos_embed(pos), pos))
        points, logits = self.head(q, pos)
        return q, points, logits


class Connector(nn.Module):
    """Eq. 2: occupancy tokens ``T_o = MLP(Q_L + PE(P_L))`` in the LLM's width (without
    position encoding: ``MLP(Q_L)``, Table 3's failing row)."""

    def __init__(self, dim: int, token_dim: int, position_encoding: bool = True):
        super().__init__()
        self.pe = PositionEmbedding(dim) if position_encoding else None
        self.mlp = nn.Sequential(nn.Linear(dim, token_dim), nn.GELU(), nn.Linear(token_dim, token_dim))

    def forward(self, queries: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        return self.mlp(queries + self.pe(positions) if self.pe is not None else queries)


class Distillation(nn.Module):
    """Eq. 3: ``1 - cos(Norm1(W T_o), Norm2(T^_o))`` between the occupancy tokens (projected
    to the teacher's width) and the teacher's features sampled where the queries project;
    without ``norm`` the LayerNorms are left out (Table 6)."""

    def __init__(self, token_dim: int, teacher_dim: int, norm: bool = True):
        super().__init__()
        self.proj = nn.Linear(token_dim, teacher_dim)
        self.norm_student = nn.LayerNorm(teacher_dim) if norm else nn.Identity()
        self.norm_teacher = nn.LayerNorm(teacher_dim) if norm else nn.Identity()

    def forward(self, tokens: torch.Tensor, teacher: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
        """Tokens (B, N, token_dim) against teacher features (B, N, teacher_dim) where ``seen``."""
        cos = F.cosine_similarity(self.norm_student(self.proj(tokens)), self.norm_teacher(teacher), dim=-1)
        return ((1 - cos) * seen).sum() / seen.sum().clamp(min=1)


def teacher_features(teacher: nn.Module, images: torch.Tensor) -> torch.Tensor:
    """A frozen multi-view encoder's patch tokens as per-camera maps (B, V, C, h, w)."""
    with torch.no_grad():
        tokens, (gh, gw) = teacher(images)
    b, v = images.shape[:2]
    return tokens.view(b, v, gh, gw, -1).permute(0, 1, 4, 2, 3)


class EncodedViews(NamedTuple):
    """What ``SparseOccEncoder.encode_views`` reads from the cameras."""

    queries: torch.Tensor
    positions: torch.Tensor
    layers: list[tuple[torch.Tensor, torch.Tensor | None]]
    dense: torch.Tensor | None


def initial_layout(queries: int, how: str) -> torch.Tensor:
    """P_0 (N, 3) in grid units ([-1, 1] of the half-ranges): uniform draws (``random``) or
    a regular bird's-eye lattice at ``GRID_QUERY_HEIGHT`` (``grid``; rows of
    ceil(sqrt(N)) cells, the last row partly filled)."""
    if how == "random":
        return torch.rand(queries, 3) * 2 - 1
    side = math.ceil(math.sqrt(queries))
    rows = math.ceil(queries / side)
    i = torch.arange(queries)
    x = ((i // side).float() + 0.5) / rows * 2 - 1
    y = ((i % side).float() + 0.5) / side * 2 - 1
    z = torch.full((queries,), (GRID_QUERY_HEIGHT - float(_MID[2])) / float(_HALF[2]))
    return torch.stack([x, y, z], -1)


class SparseOccEncoder(TokenizerModel):
    """The Sparse Occupancy Encoder, its connector and its distillation branch (see the module docstring)."""

    discrete = False
    #: Evaluation reports what its point budget reaches placed on occupied voxels, and what
    #: its cameras show: every pixel's true class lifted to its true depth (where the frames
    #: carry the cameras' class and depth maps), both over what it decodes where no point lands.
    oracles = ("budget_oracle", "lifted_pixels")
    unseen_labels: torch.Tensor

    def __init__(self, cfg: SparseOccConfig):
        super().__init__()
        cfg = cfg if isinstance(cfg, SparseOccConfig) else SparseOccConfig(**dict(cfg))
        self.cfg = cfg
        self.backbone = ImageBackbone(cfg)
        scales = len(self.backbone.lateral)
        self.queries = nn.Parameter(torch.randn(cfg.queries, cfg.dim) * 0.02)
        # P_0 in [-1, 1] of the grid's half-ranges about its centre, not in metres: an
        # optimizer step then moves a query by the learning rate times 40 m, where in
        # metres it moved by the learning rate (1e-3 m) and the initial layout never left
        # its random draw; weight decay pulls toward the grid's centre, the ego.
        self.initial_unit = nn.Parameter(initial_layout(cfg.queries, cfg.query_init))
        self.register_load_state_dict_pre_hook(_metres_to_unit)
        self.pos_embed = PositionEmbedding(cfg.dim)
        self.layers = nn.ModuleList(EncoderLayer(cfg, scales, m) for m in cfg.points_per_layer)
        self.dense = PixelHead(cfg.dim) if cfg.dense_head else None
        self.connector = Connector(cfg.dim, cfg.token_dim, cfg.position_encoding)
        self.distillation: Distillation | None = None
        # What a voxel no decoded point covers holds (cfg.unseen): free until the stage gives
        # the training split's prior; exported, so a loaded encoder decodes as it was scored.
        self.register_buffer("unseen_labels", torch.full(GRID_SHAPE, FREE, dtype=torch.uint8))
        self.register_load_state_dict_pre_hook(_without_unseen_labels)

    def set_voxel_prior(self, prior: torch.Tensor) -> None:
        if self.cfg.unseen == "prior":
            self.unseen_labels.copy_(prior.to(self.unseen_labels))

    @property
    def initial_positions(self) -> torch.Tensor:
        """P_0 (N, 3) in metres, ego frame."""
        return _MID.to(self.initial_unit) + self.initial_unit * _HALF.to(self.initial_unit)

    # -- what a world model reads
    @property
    def num_tokens(self) -> int:
        return self.cfg.queries

    @property
    def token_dim(self) -> int:
        return self.cfg.token_dim

    # -- the encoder
    def encode_views(self, cams: CameraFrames) -> EncodedViews:
        """Camera frames -> the last queries Q_L (B, N, D), their positions P_L (B, N, 3),
        every layer's (points (B, N * M_l, 3), logits (B, N * M_l, C)), P_0 first with no
        logits, and the per-pixel head's maps (B, F, V, 19, h, w) where there is one."""
        b = cams.images.shape[0]
        features = self.backbone(cams.images)  # per scale (B, F, V, D, h, w)
        dense = self.dense(features[0]) if self.dense is not None else None
        q = self.queries.expand(b, -1, -1)
        pos = self.initial_positions.expand(b, -1, -1)
        outputs: list[tuple[torch.Tensor, torch.Tensor | None]] = [(pos, None)]
        for layer in self.layers:
            q, points, logits = layer(q, pos, self.pos_embed, features, cams, dense)
            outputs.append((points.flatten(1, 2), logits.flatten(1, 2)))
            pos = points.mean(2).detach()  # the query moves to its points; the next layer samples there
        return EncodedViews(q, pos, outputs, dense)

    def tokens(self, queries: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        """The occupancy tokens T_o (B, N, token_dim) of the last queries."""
        return self.connector(queries, positions)

    def decode_points(self, queries: torch.Tensor, positions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The last layer's points (B, N * M, 3) and classes (B, N * M) from Q_L and P_L (its
        points' mean, from which their offsets' mean is taken back)."""
        last = self.layers[-1]
        assert isinstance(last, EncoderLayer)
        head = last.head
        offsets = head.offsets_of(queries)
        points = positions[..., None, :] - offsets.mean(-2, keepdim=True) + offsets
        logits = head.classes(queries).view(*queries.shape[:-1], head.points, POINT_CLASSES)
        return points.flatten(1, 2), logits.argmax(-1).flatten(1)

    def voxelize(self, points: torch.Tensor, classes: torch.Tensor) -> torch.Tensor:
        """Points (B, M, 3) with classes (B, M) -> label volumes (B, X, Y, Z), ``unseen_labels``
        where no point lands."""
        return torch.stack([voxelize(p, c, self.cfg.extent, self.unseen_labels) for p, c in zip(points, classes)])

    # -- training (the tokenizer stage's protocol for a camera-reading architecture)
    def forward(
        self, batch: dict[str, Any], index: DatasetIndex | None, teacher: nn.Module | None = None
    ) -> TokenizerOutput:
        cfg = self.cfg
        cams = camera_frames(_checked(batch, cfg), index, cfg.frames)
        q, pos, outputs, dense = self.encode_views(cams)
        gt, gt_classes, valid = ground_truth(
            batch,
            index,
            cfg.gt_points,
            cfg.extended_range,
            int(batch.get("seed", 0)),
            cfg.kept_classes(),
            cfg.movable_share,
        )
        dev = q.device
        gt, gt_classes, valid = gt.to(dev), gt_classes.to(dev), valid.to(dev)
        chamfer = q.new_zeros(())
        focal = q.new_zeros(())
        for points, logits in outputs:
            distance, match = chamfer_distance(points, gt, valid)
            chamfer = chamfer + distance.mean()
            if logits is not None:
                focal = focal + sigmoid_focal_loss(logits, torch.gather(gt_classes, 1, match))
        losses = {"chamfer": chamfer, "focal": focal}
        loss = chamfer + cfg.focal_weight * focal
        if dense is not None and cfg.dense_weight > 0 and "cam_class" in batch:
            losses["dense"] = dense_loss(dense[:, 0], batch["cam_class"], batch["cam_depth"])
            loss = loss + cfg.dense_weight * losses["dense"]
        if teacher is not None and cfg.distill_weight > 0:
            losses["distill"] = self.distill(q, pos, cams, teacher)
            loss = loss + cfg.distill_weight * losses["distill"]
        losses = {"loss": loss, **losses}
        labels, oracles = None, {}
        if not self.training:
            labels = self.voxelize(*self.decode_points(q, pos))
            oracles["budget_oracle"] = self.oracle(batch, int(batch.get("seed", 0))).to(labels.device)
            if "cam_class" in batch and "cam_depth" in batch:
                oracles["lifted_pixels"] = self.lifted_pixels(batch, cams).to(labels.device)
        return TokenizerOutput(None, losses, {}, None, labels, oracles)

    @property
    def point_budget(self) -> int:
        """The points the last layer decodes: queries times its points per query."""
        return self.cfg.queries * self.cfg.points_per_layer[-1]

    def oracle(self, batch: dict[str, Any], seed: int) -> torch.Tensor:
        """The budget's oracle reconstruction (B, X, Y, Z): ``point_budget`` occupied voxel
        centres of each frame (drawn as the ground truth is) with their true classes,
        voxelized as the decoded points are."""
        cfg = self.cfg
        points, classes, real = ground_truth(
            batch, None, self.point_budget, 0, seed, cfg.kept_classes(), cfg.movable_share
        )
        return torch.stack(
            [voxelize(p[r], c[r], self.cfg.extent, self.unseen_labels) for p, c, r in zip(points, classes, real)]
        )

    def lifted_pixels(self, batch: dict[str, Any], cams: CameraFrames) -> torch.Tensor:
        """What the current frame's cameras can carry (B, X, Y, Z): every pixel's true class
        (``cam_class``) at its true depth (``cam_depth``) lifted into the grid, one voxel a
        pixel, ``unseen_labels`` where no pixel lands. A perfect reader of the pixels gets
        this far and no further: the voxels behind what a camera sees, and those between its
        pixels' rays far away, stay the prior."""
        return lifted_pixels(
            batch["cam_class"], batch["cam_depth"], cams.intrinsics[:, 0], cams.cam_to_ego[:, 0], self.unseen_labels
        )

    def distill(self, q: torch.Tensor, pos: torch.Tensor, cams: CameraFrames, teacher: nn.Module) -> torch.Tensor:
        """Eq. 3 on the current frame: the teacher's features read at the queries' projections."""
        cfg = self.cfg
        maps = teacher_features(teacher, cams.images[:, 0])
        if self.distillation is None or self.distillation.proj.out_features != maps.shape[2]:
            raise ConfigError(
                f"model.sparseocc: the distillation teacher is {maps.shape[2]} wide; build the encoder with "
                f"attach_teacher({maps.shape[2]})"
            )
        uv, inside = project(pos, cams.intrinsics[:, 0], cams.cam_to_ego[:, 0], (cfg.image_height, cfg.image_width))
        target, seen = sample_views(maps.to(q.dtype), uv, inside, (cfg.image_height, cfg.image_width))
        return self.distillation(self.tokens(q, pos), target, seen.to(q.dtype))

    def attach_teacher(self, teacher_dim: int) -> None:
        """Add the distillation branch for a teacher ``teacher_dim`` wide (before the optimizer is made)."""
        self.distillation = Distillation(self.cfg.token_dim, int(teacher_dim), self.cfg.distill_norm)

    def export_state_dict(self) -> dict[str, torch.Tensor]:
        """The weights an export keeps: the distillation branch is dropped at inference."""
        return {k: v for k, v in self.state_dict().items() if not k.startswith("distillation.")}

    # -- what a world model's scene cache holds
    @torch.no_grad()
    def encode_samples(self, index: DatasetIndex, samples: list[tuple[str, str]]) -> torch.Tensor:
        """Rows (B, N, 3 + D): each query's position P_L then its features Q_L."""
        batch = frames_batch(index, samples, cameras=True)
        device = self.queries.device
        cams = camera_frames(_checked(batch, self.cfg), index, self.cfg.frames)
        cams = CameraFrames(
            *(t.to(device) for t in (cams.images, cams.intrinsics, cams.cam_to_ego, cams.current_to_frame))
        )
        encoded = self.encode_views(cams)
        return torch.cat([encoded.positions, encoded.queries], -1)


_MID = (torch.tensor(RANGE_MIN, dtype=torch.float32) + torch.tensor(RANGE_MAX, dtype=torch.float32)) / 2
_HALF = (torch.tensor(RANGE_MAX, dtype=torch.float32) - torch.tensor(RANGE_MIN, dtype=torch.float32)) / 2


def _without_unseen_labels(module: nn.Module, state: dict, prefix: str, *args: Any) -> None:
    """Exports written before a decoded scene kept the prior where no point lands decoded free there."""
    if prefix + "unseen_labels" not in state and prefix + "queries" in state:
        state[prefix + "unseen_labels"] = torch.full(GRID_SHAPE, FREE, dtype=torch.uint8)


def _metres_to_unit(module: nn.Module, state: dict, prefix: str, *args: Any) -> None:
    """Exports and checkpoints written before P_0 was kept in grid units hold it in metres."""
    old = state.pop(prefix + "initial_positions", None)
    if old is not None and prefix + "initial_unit" not in state:
        state[prefix + "initial_unit"] = (old - _MID.to(old)) / _HALF.to(old)


def _checked(batch: dict[str, Any], cfg: SparseOccConfig) -> dict[str, Any]:
    images = batch.get("images")
    want = (cfg.num_cameras, cfg.image_height, cfg.image_width, 3)
    if images is None:
        raise DataError("the sparse occupancy encoder reads the cameras; the frames carry no images")
    if tuple(images.shape[1:]) != want:
        raise DataError(
            f"images: expected (B, {', '.join(map(str, want))}), got {tuple(images.shape)}; "
            "set model.sparseocc.image_height/image_width/num_cameras to the dataset's"
        )
    return batch
