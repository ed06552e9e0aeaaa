"""SparseOccVLA's settings: the sparse occupancy encoder (``model.sparseocc`` of a tokenizer
stage) and the world model around the LLM (``model.sparseoccvla`` of a pretrain stage).

The defaults are a CPU-sized model; the paper's values (Sec. 4.2, App. A) are given beside
each key.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from occtrain.errors import ConfigError
from occtrain.formats.occ3d import CLASS_INDEX, MOVABLE_CLASSES

if TYPE_CHECKING:
    from occtrain.core.lm_world_model import WorldInputs

#: How the queries' initial positions are laid out (``SparseOccConfig.query_init``).
QUERY_INITS = ("random", "grid")
#: What a decoded scene holds where no point lands (``SparseOccConfig.unseen``).
UNSEEN = ("prior", "free")


@dataclass
class SparseOccConfig:
    """The Sparse Occupancy Encoder (Sec. 3.1): multi-view, multi-frame images -> N sparse
    queries with 3D positions, decoded after each layer into a coarse-to-fine point set."""

    #: A local Hugging Face ResNet directory (the paper: ResNet-50); empty: a small ResNet
    #: built from the widths and depths below (random init, no download).
    backbone_path: str = ""
    backbone_widths: list[int] = field(default_factory=lambda: [16, 32, 64, 64])
    backbone_depths: list[int] = field(default_factory=lambda: [1, 1, 1, 1])
    #: The cameras' image size (the dataset's; the paper: 256 x 704) and count.
    image_height: int = 72
    image_width: int = 128
    num_cameras: int = 6
    #: Input image frames: the current one and ``frames - 1`` before it (Table 8: 1-8; 8).
    frames: int = 1
    #: Sparse occupancy queries N (paper: 600, a 300 version too) and their width D (1024).
    queries: int = 64
    dim: int = 64
    #: Where the queries' learnable positions P_0 start: ``random`` (uniform over the grid's
    #: range, the paper's learnable initialisation) or ``grid`` (a regular bird's-eye lattice
    #: over the range, 1 m above the ground: every patch of the scene has a query from the
    #: first step; not the paper's, see docs/families/sparseoccvla.md).
    query_init: str = "random"
    heads: int = 4  # paper: 32
    #: Points each query decodes after each layer, coarse to fine; one entry per layer
    #: (paper: 6 layers, (2, 4, 16, 32, 56, 112)).
    points_per_layer: list[int] = field(default_factory=lambda: [4, 16, 64])
    #: Sampling points per query and frame (paper: 4), each read at every feature scale.
    sampling_points: int = 4
    #: Adaptive mixing: channel groups, and the points the sampled ones are mixed into.
    mixing_groups: int = 4
    mixed_points: int = 8
    ffn_dim: int = 128
    #: How far (metres) a layer's sampling points and decoded points reach from their query.
    offset_scale: float = 6.0
    #: The connector's output width: the LLM's hidden size (Eq. 2 aligns the queries to it).
    token_dim: int = 128
    #: Add PE(P_L) to the queries in the connector (Eq. 2; Table 3: without it training fails).
    position_encoding: bool = True
    #: Ground-truth points sampled per frame from its occupied voxels (the sparsified G).
    gt_points: int = 2048
    #: The share of ``gt_points`` that voxels of a movable class (cars, pedestrians, ...)
    #: take before the rest is drawn (not the paper's, which supervises with every voxel: a
    #: uniform draw of a few thousand of a scene's 10^5 leaves a car a handful of points,
    #: and the encoder learns no movable object). 0: the uniform draw. Taking every movable
    #: voxel (1.0) gave movable objects at the cost of most of the scene's geometry
    #: (docs/families/sparseoccvla.md).
    movable_share: float = 0.0
    #: Future frames whose occupied voxels, moved into the current frame by the ego poses,
    #: join its ground truth (App. A's extended-range supervision; 0: the current frame only).
    extended_range: int = 0
    #: Weight of a dense loss on the backbone: a head on its finest feature map predicts each
    #: pixel's class (the 18 labels, 17 = sky) and log depth, against the renderer's
    #: per-pixel targets (0: off, the paper's; not the paper's, whose ResNet-50 comes
    #: pretrained: a backbone trained from scratch by the Chamfer loss alone learned
    #: nothing the queries read, docs/families/sparseoccvla.md).
    dense_weight: float = 0.0
    #: Each sampling point also reads, in every camera that sees it, that head's class
    #: probabilities and the gap between its own depth and the pixel's predicted depth (log
    #: metres): "is there a surface here, and of what", the cue a query needs to place its
    #: points (not the paper's).
    depth_cue: bool = False
    #: lambda_focal of Eq. 10 (paper: 0.2) and the weight of the distillation loss (0: off).
    focal_weight: float = 0.2
    distill_weight: float = 1.0
    #: The two independent LayerNorms before the cosine of Eq. 3 (Table 6's "Norm").
    distill_norm: bool = True
    #: Voxels each decoded point fills when points are voxelized to be scored (x, y, z): a
    #: few thousand points cover a scene's 10^5 occupied voxels only as small boxes. One
    #: layer high: the ground is one voxel thick, and a second layer over it is wrong
    #: wherever the point lies on the road (4,096 points on the truth over the prior, the
    #: quickstart world's val split: 36.7 mIoU at 3x3x1, 32.0 at 3x3x2, by
    #: ``tools/camera_ceiling.py``; docs/families/sparseoccvla-cameras.md).
    voxel_extent: list[int] = field(default_factory=lambda: [3, 3, 1])
    #: What a voxel no decoded point covers holds: ``prior``, the training split's per-voxel
    #: prior (the road below, buildings beside: a few thousand points leave most of a scene
    #: uncovered, and calling all of it free throws away what any frame's layout says), or
    #: ``free`` (the paper's voxelization).
    unseen: str = "prior"

    @property
    def extent(self) -> tuple[int, int, int]:
        """``voxel_extent`` as ``voxelize`` takes it: (x, y, z)."""
        x, y, z = self.voxel_extent
        return x, y, z

    @property
    def dense_head(self) -> bool:
        """Whether the encoder has the per-pixel head (trained by ``dense_weight``, read by ``depth_cue``)."""
        return self.dense_weight > 0 or self.depth_cue

    @property
    def layers(self) -> int:
        return len(self.points_per_layer)

    def kept_classes(self) -> tuple[int, ...]:
        """The classes the ground-truth draw takes first (up to ``movable_share``)."""
        return tuple(CLASS_INDEX[name] for name in MOVABLE_CLASSES) if self.movable_share > 0 else ()

    def validate(self, where: str) -> None:
        positive = (
            "image_height",
            "image_width",
            "num_cameras",
            "frames",
            "queries",
            "dim",
            "heads",
            "sampling_points",
            "mixing_groups",
            "mixed_points",
            "ffn_dim",
            "token_dim",
            "gt_points",
        )
        for key in positive:
            if getattr(self, key) < 1:
                raise ConfigError(f"{where}.{key}: {getattr(self, key)} must be at least 1")
        if not self.points_per_layer or min(self.points_per_layer) < 1:
            raise ConfigError(
                f"{where}.points_per_layer: {list(self.points_per_layer)} must list at least one layer, each >= 1 point"
            )
        if self.dim % self.heads or self.dim % self.mixing_groups:
            raise ConfigError(
                f"{where}.dim: {self.dim} must be divisible by heads ({self.heads}) and mixing_groups "
                f"({self.mixing_groups})"
            )
        if len(self.backbone_widths) != len(self.backbone_depths) or not self.backbone_widths:
            raise ConfigError(f"{where}.backbone_widths: one width per backbone stage, as many as backbone_depths")
        if self.query_init not in QUERY_INITS:
            raise ConfigError(f"{where}.query_init: {self.query_init!r} is not one of {', '.join(QUERY_INITS)}")
        if not 0 <= self.movable_share <= 1:
            raise ConfigError(f"{where}.movable_share: {self.movable_share} must be a share, 0 to 1")
        if self.offset_scale <= 0:
            raise ConfigError(f"{where}.offset_scale: {self.offset_scale} must be positive")
        if min(self.extended_range, self.focal_weight, self.distill_weight, self.dense_weight) < 0:
            raise ConfigError(
                f"{where}: extended_range, focal_weight, distill_weight and dense_weight must not be negative"
            )
        if self.unseen not in UNSEEN:
            raise ConfigError(f"{where}.unseen: {self.unseen!r} is not one of {', '.join(UNSEEN)}")
        if len(self.voxel_extent) != 3 or min(self.voxel_extent) < 1:
            raise ConfigError(f"{where}.voxel_extent: {list(self.voxel_extent)} must be [x, y, z] voxels, each >= 1")


@dataclass
class SparseOccVLAWorldConfig:
    """What surrounds the LLM (Sec. 3.2): global scene queries, the ego-state token and the
    residual-fusion forecaster (``model.sparseoccvla`` of a pretrain stage)."""

    #: Global scene queries T_g cross-attending the occupancy tokens (Eq. 4; Table 7: 0-16, 12).
    global_queries: int = 12
    #: Forecast heads over the occupancy tokens (Eq. 6-7): ``residual_query`` fuses the
    #: encoder's queries Q_L into the LLM's outputs T'_o (Table 3 "w/o Residual-Query" turns
    #: it off), ``residual_token`` feeds T'_o (off: the forecaster reads Q_L alone, "w/o
    #: Residual-Token", the LLM decoupled from forecasting).
    residual_query: bool = True
    residual_token: bool = True
    #: Future frames forecast at 0.5 s (6 = 3 s).
    forecast_frames: int = 6
    #: Move the forecaster's residual base (the query positions each future frame's points
    #: are decoded around) back by the ego's constant-velocity step before each frame, so
    #: what stands still starts where the next frame's ego sees it (not the paper's: its
    #: forecaster learns the ego's motion from the ego-state embedding alone).
    moved_base: bool = False
    #: Weight of the forecasting loss beside the language loss (Eq. 12: 1).
    forecast_weight: float = 1.0

    def validate(self, where: str, inputs: WorldInputs) -> None:
        if self.global_queries < 0:
            raise ConfigError(f"{where}.global_queries: {self.global_queries} must not be negative")
        if not 1 <= self.forecast_frames <= 6:
            raise ConfigError(f"{where}.forecast_frames: {self.forecast_frames} must be 1 to 6 (0.5 s each)")
        if self.forecast_weight < 0:
            raise ConfigError(f"{where}.forecast_weight: {self.forecast_weight} must not be negative")
        if not (self.residual_query or self.residual_token):
            raise ConfigError(
                f"{where}: residual_query and residual_token are both off; the forecaster would read nothing"
            )
