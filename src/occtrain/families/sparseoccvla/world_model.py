"""SparseOccVLA's unified LLM (Sec. 3.2): occupancy tokens, global scene queries and an
ego-state token before the text, and the residual-fusion forecaster after it.

Sequence layout (causal attention throughout, as the paper's)::

    bos  T_o (N <patch_j> tokens)  T_g (<global_0> ... <global_{G-1}>)  <ego>  text ...

An occupancy token carries its encoder row ``[P_L | Q_L]`` as payload and is embedded by
the connector ``MLP(Q_L + PE(P_L))`` (Eq. 2; its weights start from stage 1's). The global
tokens are learnable queries that cross-attend the sequence's occupancy tokens (Eq. 4);
the ego token embeds the ego state (its current velocity and past waypoints, from the
poses). Forecasting (Eq. 6-7): the LLM's outputs at the occupancy tokens T'_o are fused
with the encoder's queries, ``MLP([T'_o, Q_L])``, and a shared forecaster steps them
through the future frames, adding ``embed(x, y, z, t) + Ego`` at each, and decodes each
frame's points and classes, supervised by the Chamfer distance and the focal loss against
that frame's ground truth (Eq. 11).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from occtrain.core.builder import SequenceBuilder, batch_payload, sample_means
from occtrain.core.lm_world_model import LMWorldModel, WorldInputs, WorldModelOutput, token_ce
from occtrain.core.protocols import PromptInputs, WorldEngine
from occtrain.core.sequence import IGNORE, PayloadSpec, TokenSequence, empty_payload
from occtrain.core.vocab import JointVocab
from occtrain.data.clips import Part, PromptPart, clip_rng
from occtrain.errors import ConfigError
from occtrain.families.sparseoccvla.config import SparseOccVLAWorldConfig
from occtrain.families.sparseoccvla.encoder import (
    FeedForward,
    PointHead,
    SparseOccEncoder,
    SpatialSelfAttention,
    normalized,
    sinusoid,
)
from occtrain.formats.occ3d import FRAME_DT, PAST_STEPS
from occtrain.models.planning_heads import current_velocity
from occtrain.models.point_sets import chamfer_distance, occupied_points, sigmoid_focal_loss, voxelize

if TYPE_CHECKING:
    from transformers import PreTrainedModel

EGO = "<ego>"
#: The ego state's features: current velocity (2) and the past waypoints (PAST_STEPS x 2).
EGO_FEATURES = 2 + 2 * PAST_STEPS
#: The ego-state features are metres (per second, for the velocity) over this.
EGO_SCALE = 10.0


def global_token(j: int) -> str:
    return f"<global_{j}>"


def ego_state(anchor: dict) -> tuple[float, ...]:
    """The ego-state token's features from a clip anchor (metres / 10; unknown past waypoints 0)."""
    past = (
        np.asarray(anchor["ego_past"], dtype=np.float64).reshape(-1, 2)
        * np.asarray(anchor["ego_past_mask"], dtype=np.float64)[:, None]
    )
    return tuple(float(v) for v in np.concatenate([current_velocity(anchor), past.reshape(-1)]) / EGO_SCALE)


@dataclass(frozen=True)
class Ego(PromptPart):
    """The ego-state token (its features, see ``ego_state``)."""

    features: tuple[float, ...]
    supervise: bool = False


@dataclass(frozen=True)
class Forecast(PromptPart):
    """The forecast of the future frames ``tokens`` (sample tokens, 0.5 s apart) from the
    occupancy tokens before it: laid out as no token, trained by the forecaster's loss."""

    tokens: tuple[str, ...]
    supervise: bool = False  # its loss is the forecaster's, not the text's


class SparseBuilder(SequenceBuilder):
    """Lays the occupancy tokens with the global tokens after them, the ego token, and the
    forecast targets."""

    def __init__(self, world: SparseOccVLAWorldModel):
        super().__init__(world.vocab, "next_scene", world.payload_spec)
        self.world = world

    def lay(self, part: Part, inputs: PromptInputs, scenes: dict[int, torch.Tensor]) -> SequenceBuilder:
        if isinstance(part, Ego):
            return self.ego(part.features)
        if isinstance(part, Forecast):
            return self.forecast(part.tokens, inputs)
        return super().lay(part, inputs, scenes)

    def scene(self, rows: torch.Tensor, supervise: bool = False) -> SparseBuilder:
        """The occupancy tokens of encoder rows (N, 3 + D), then the global tokens."""
        if supervise:
            raise ValueError("SparseOccVLA forecasts through its forecaster (a Forecast part), not scene tokens")
        v, n = self.vocab, self.vocab.scene_len
        payload = empty_payload(self.payload_spec, n)
        payload["scene"] = torch.as_tensor(rows, dtype=torch.float32).reshape(n, -1).cpu()
        self.add(torch.arange(v.occ_start, v.occ_start + n), False, payload=payload)
        if self.world.cfg.global_queries:
            self.add(torch.tensor([v.extra_id(global_token(j)) for j in range(self.world.cfg.global_queries)]), False)
        return self

    def ego(self, features: tuple[float, ...]) -> SparseBuilder:
        payload = empty_payload(self.payload_spec, 1)
        payload["ego"] = torch.tensor(features, dtype=torch.float32)[None]
        self.add(torch.tensor([self.vocab.extra_id(EGO)]), False, payload=payload)
        return self

    def forecast(self, tokens: tuple[str, ...], inputs: PromptInputs) -> SparseBuilder:
        """Per future frame its ground-truth point set (``forecast_points`` (T, K, 3),
        ``forecast_classes`` (T, K), ``forecast_valid`` (T, K))."""
        frames = [self.world.future_points(inputs, t) for t in tokens]
        self.targets["forecast_points"] = torch.stack([f[0] for f in frames])
        self.targets["forecast_classes"] = torch.stack([f[1] for f in frames])
        self.targets["forecast_valid"] = torch.stack([f[2] for f in frames])
        return self


class Forecaster(nn.Module):
    """Eq. 6-7: residual fusion of T'_o and Q_L, then one shared layer stepped through the
    future frames with ``embed(x, y, z, t) + Ego`` added, decoding each frame's points."""

    def __init__(
        self, hidden: int, dim: int, heads: int, ffn: int, points: int, scale: float, cfg: SparseOccVLAWorldConfig
    ):
        super().__init__()
        self.cfg = cfg
        width = hidden * cfg.residual_token + dim * cfg.residual_query
        self.fuse = nn.Sequential(nn.Linear(width, dim), nn.GELU(), nn.Linear(dim, dim))
        self.embed4d = nn.Sequential(nn.Linear(3 * 2 * 6 + 1, dim), nn.GELU(), nn.Linear(dim, dim))
        self.ego = nn.Linear(EGO_FEATURES, dim)
        self.attention = SpatialSelfAttention(dim, heads)
        self.ffn = FeedForward(dim, ffn)
        self.head = PointHead(dim, points, scale)

    def forward(
        self, llm_out: torch.Tensor, queries: torch.Tensor, positions: torch.Tensor, ego: torch.Tensor
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """T'_o (B, N, hidden), Q_L (B, N, D), P_L (B, N, 3) and the ego state (B, E) -> per
        future frame its points (B, N * M, 3) and class logits (B, N * M, C)."""
        parts = ([llm_out] if self.cfg.residual_token else []) + ([queries] if self.cfg.residual_query else [])
        q = self.fuse(torch.cat([p.to(queries.dtype) for p in parts], -1))
        ego_emb = self.ego(ego.to(q.dtype))[:, None]
        pos, out = positions, []
        steps = self.cfg.forecast_frames
        shift = self.base_shift(ego).to(pos.dtype)
        for t in range(1, steps + 1):
            pos = pos - shift
            time = torch.full((*pos.shape[:-1], 1), t / steps, dtype=q.dtype, device=q.device)
            q = self.ffn(
                self.attention(q + self.embed4d(torch.cat([sinusoid(normalized(pos)), time], -1)) + ego_emb, pos)
            )
            points, logits = self.head(q, pos)
            out.append((points.flatten(1, 2), logits.flatten(1, 2)))
            pos = points.mean(2).detach()
        return out

    def base_shift(self, ego: torch.Tensor) -> torch.Tensor:
        """(B, 1, 3): how far the base moves before each future frame: the ego's
        constant-velocity step (its velocity, the ego state's first two features, times a
        frame's 0.5 s) with ``moved_base``, else nothing."""
        shift = torch.zeros(ego.shape[0], 1, 3, dtype=ego.dtype, device=ego.device)
        if self.cfg.moved_base:
            shift[:, 0, :2] = ego[:, :2] * EGO_SCALE * FRAME_DT
        return shift


class SparseOccVLAWorldModel(LMWorldModel):
    """The LLM with the connector, the global queries, the ego embedding and the forecaster;
    the sparse occupancy encoder is the engine's frozen scene encoder (its rows are cached)."""

    frame_separation = False
    #: Stage 3 (Sec. 4.2) trains everything but the LLM, which trains through LoRA.
    trains_own_parts_with_lora = True
    #: Its forecast targets (points, classes) are per sequence, read by row.
    packs_sequences = False
    unseen_labels: torch.Tensor

    def __init__(
        self, llm: PreTrainedModel, vocab: JointVocab, encoder: SparseOccEncoder, cfg: SparseOccVLAWorldConfig
    ):
        super().__init__(llm, vocab, "next_scene")
        enc = encoder.cfg
        hidden = self.hidden_size
        if hidden != enc.token_dim:
            raise ConfigError(
                f"model.llm.hidden_size: {hidden} differs from the sparse occupancy encoder's token_dim "
                f"{enc.token_dim} "
                "(the connector maps the queries to the LLM's width); set them equal"
            )
        self.cfg = cfg
        self.query_dim = enc.dim
        self.gt_points = enc.gt_points
        self.gt_keep, self.gt_share = enc.kept_classes(), enc.movable_share
        self.voxel_extent = enc.extent
        # The encoder's fill where no point lands (its training split's prior): a forecast's
        # points are voxelized as a reconstruction's are. Not state: the encoder's export holds it.
        self.register_buffer("unseen_labels", encoder.unseen_labels.clone(), persistent=False)
        self.focal_weight = enc.focal_weight
        self.connector = copy.deepcopy(encoder.connector).requires_grad_(True)  # stage 1's, trained on
        if cfg.global_queries:
            self.global_queries = nn.Parameter(torch.randn(cfg.global_queries, hidden) * 0.02)
            self.global_attention = nn.MultiheadAttention(hidden, max(1, hidden // 32), batch_first=True)
            self.global_norm = nn.LayerNorm(hidden)
        self.ego_embed = nn.Sequential(nn.Linear(EGO_FEATURES, hidden), nn.GELU(), nn.Linear(hidden, hidden))
        self.forecaster = Forecaster(
            hidden, enc.dim, enc.heads, enc.ffn_dim, enc.points_per_layer[-1], enc.offset_scale, cfg
        )
        self.payload_spec: PayloadSpec = {
            "scene": ((3 + enc.dim,), torch.float32, 0.0),
            "ego": ((EGO_FEATURES,), torch.float32, 0.0),
        }
        # Ground-truth point sets of future frames, read once per sample token (not state).
        self.__dict__["_future_points"] = {}

    def builder(self) -> SparseBuilder:
        return SparseBuilder(self)

    # -- embeddings
    def embed(self, input_ids: torch.Tensor, payload: dict[str, torch.Tensor] | None = None) -> torch.Tensor:
        emb = self.llm.get_input_embeddings()(input_ids)
        occ = self.vocab.is_occ(input_ids)
        ego = input_ids == self.vocab.extra_id(EGO)
        if not payload:
            if bool(occ.any() or ego.any()):
                raise ValueError("occupancy and ego tokens need their rows: pass the laid-out sequence, not bare ids")
            payload = {}
        if bool(occ.any()):
            rows = payload["scene"][occ].to(emb.dtype)
            emb = emb.masked_scatter(occ[..., None], self.connector(rows[:, 3:], rows[:, :3]).to(emb.dtype))
        if self.cfg.global_queries:
            emb = self._global_tokens(input_ids, emb, occ)
        if bool(ego.any()):
            emb = emb.masked_scatter(ego[..., None], self.ego_embed(payload["ego"][ego].to(emb.dtype)).to(emb.dtype))
        return emb

    def _global_tokens(self, ids: torch.Tensor, emb: torch.Tensor, occ: torch.Tensor) -> torch.Tensor:
        """Eq. 4: each sequence's global tokens cross-attend its own occupancy tokens (fed with them)."""
        start = self.vocab.extra_id(global_token(0))
        is_global = (ids >= start) & (ids < start + self.cfg.global_queries)
        rows = is_global.any(1).nonzero().squeeze(1)
        if not len(rows):
            return emb
        n = self.vocab.scene_len
        if bool((occ[rows].sum(1) != n).any()):
            raise ValueError("global tokens are fed in one forward with the occupancy tokens they read")
        tokens = emb[rows][occ[rows]].view(len(rows), n, -1)
        queries = self.global_queries.to(emb.dtype).expand(len(rows), -1, -1)
        attended, _ = self.global_attention(queries, tokens, tokens, need_weights=False)
        out = self.global_norm(queries + attended)  # (r, G, hidden)
        row_of = torch.full((len(ids),), -1, dtype=torch.long, device=ids.device)
        row_of[rows] = torch.arange(len(rows), device=ids.device)
        b, pos = is_global.nonzero(as_tuple=True)
        return emb.index_put((b, pos), out[row_of[b], ids[b, pos] - start].to(emb.dtype))

    # -- forecasting
    def future_points(self, inputs: PromptInputs, token: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A future frame's sparsified ground truth (points, classes, real): drawn once per
        sample token (the same subset whichever clip reaches the frame)."""
        cache = self.__dict__["_future_points"]
        if token not in cache:
            points, classes, n = occupied_points(
                inputs.read("voxels", token).numpy(), self.gt_points, clip_rng(0, token), self.gt_keep, self.gt_share
            )
            cache[token] = (points, classes, torch.arange(self.gt_points) < n)
        return cache[token]

    def forecast_inputs(
        self, batch: dict[str, torch.Tensor], hidden: torch.Tensor, rows: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        """For sequences ``rows``: T'_o (r, N, hidden), Q_L (r, N, D), P_L (r, N, 3), ego (r, E)."""
        ids, payload = batch["input_ids"][rows], batch_payload(batch)
        occ = self.vocab.is_occ(ids)
        ego = ids == self.vocab.extra_id(EGO)
        n, r = self.vocab.scene_len, len(rows)
        scene = payload["scene"][rows][occ].view(r, n, -1)
        return hidden[rows][occ].view(r, n, -1), scene[..., 3:], scene[..., :3], payload["ego"][rows][ego].view(r, -1)

    def forecast_loss(
        self, steps: list[tuple[torch.Tensor, torch.Tensor]], batch: dict, rows: torch.Tensor
    ) -> torch.Tensor:
        """Eq. 11 averaged over the frames: Chamfer + lambda_focal * focal against each frame's points."""
        dev = steps[0][0].device
        gt, classes, valid = (batch[k][rows].to(dev) for k in ("forecast_points", "forecast_classes", "forecast_valid"))
        total = steps[0][0].new_zeros(())
        for t, (points, logits) in enumerate(steps):
            distance, match = chamfer_distance(points, gt[:, t], valid[:, t])
            total = (
                total
                + distance.mean()
                + self.focal_weight * sigmoid_focal_loss(logits, torch.gather(classes[:, t], 1, match))
            )
        return total / len(steps)

    def forward(self, batch: dict[str, torch.Tensor], output_hidden_states: bool = False) -> WorldModelOutput:
        """L_LM over the text targets + forecast_weight * L_fore over the forecast sequences."""
        out = self._run(
            batch["input_ids"],
            batch["attention_mask"],
            batch["position_ids"],
            hidden=True,
            payload=batch_payload(batch),
        )
        logits, labels = out.logits, batch["labels"]
        ce = token_ce(logits, labels)
        valid = labels != IGNORE
        text_loss = (ce * valid).sum() / valid.sum().clamp(min=1)
        per_sample = sample_means(ce * valid, valid, batch)
        hidden = out.hidden_states[-1]
        fore = logits.new_zeros((), dtype=torch.float32)
        if "forecast_valid" in batch:
            rows = batch["forecast_valid"].flatten(1).any(1).nonzero().squeeze(1).to(hidden.device)
            if len(rows):
                fore = self.forecast_loss(self.forecaster(*self.forecast_inputs(batch, hidden, rows)), batch, rows)
        if fore.grad_fn is None:
            # No forecast in this batch: the forecaster still joins the graph (DDP waits for every gradient).
            fore = fore + sum(p.sum() for p in self.forecaster.parameters()) * 0.0
        loss = text_loss + self.cfg.forecast_weight * fore
        return WorldModelOutput(loss, text_loss, fore, logits, hidden if output_hidden_states else None, per_sample)

    @torch.no_grad()
    def forecast(self, prompt: TokenSequence) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """One forward of a laid-out prompt; per future frame its points (M, 3) and classes (M,)."""
        ids = prompt.input_ids[None].to(self.device)
        payload = {k: v[None].to(self.device) for k, v in prompt.payload.items()}
        allowed = torch.ones(1, 1, len(ids[0]), len(ids[0]), dtype=torch.bool, device=self.device).tril()
        out = self._run(ids, allowed, prompt.position_ids[None].to(self.device), hidden=True, payload=payload)
        batch = {"input_ids": ids, **{f"payload_{k}": v for k, v in payload.items()}}
        steps = self.forecaster(
            *self.forecast_inputs(batch, out.hidden_states[-1], torch.zeros(1, dtype=torch.long, device=self.device))
        )
        return [(points[0], logits[0].argmax(-1)) for points, logits in steps]

    def voxelize(self, points: torch.Tensor, classes: torch.Tensor) -> torch.Tensor:
        """One forecast frame's points (M, 3) and classes (M,) -> its label volume (X, Y, Z),
        voxelized as the encoder's reconstructions are."""
        return voxelize(points, classes, self.voxel_extent, self.unseen_labels)

    # -- export
    def export_config(self) -> dict:
        return {**super().export_config(), "sparseoccvla": asdict(self.cfg)}

    @staticmethod
    def vocab_layout(inputs: WorldInputs, world_cfg: SparseOccVLAWorldConfig | None = None) -> dict:
        """One ``<patch_j>`` token per sparse query, the global tokens and the ego token."""
        cfg = world_cfg or SparseOccVLAWorldConfig()
        extra = tuple(global_token(j) for j in range(cfg.global_queries)) + (EGO,)
        return {"codebook_sizes": [], "scene_hw": (inputs.scene.num_tokens, 1), "patch": 1, "extra": extra}

    @classmethod
    def create(
        cls,
        llm: nn.Module,
        vocab: JointVocab,
        inputs: WorldInputs,
        scene_prediction: str,
        world_cfg: SparseOccVLAWorldConfig | None = None,
    ) -> SparseOccVLAWorldModel:
        return cls(llm, vocab, inputs.scene.encoder, world_cfg or SparseOccVLAWorldConfig())

    @classmethod
    def from_export(cls, data: dict, llm: nn.Module, vocab: JointVocab, inputs: WorldInputs) -> SparseOccVLAWorldModel:
        return cls(llm, vocab, inputs.scene.encoder, SparseOccVLAWorldConfig(**data["sparseoccvla"]))


def scene_rows(engine: WorldEngine) -> Mapping[str, torch.Tensor]:
    """The engine's encoder rows by sample token: a SparseOccVLA engine encodes every
    frame from the cameras ahead (``prepare_inputs``)."""
    rows = engine.scene_cache
    if rows is None:
        raise ValueError("the scenes are encoded from the cameras ahead: prepare the engine on a dataset first")
    return rows
