"""SparseOccVLA's LLM-guided anchor-diffusion planner (Sec. 3.3, Fig. 3, Table 11): what
its ``planner`` stage trains (a ``core.protocols.Planner``).

K anchors are the K-means centres of the training split's 3 s trajectories (scikit-learn).
Training noises every anchor with the DDIM forward process (Eq. 8, ``diffusers``'
scheduler, truncated to its first ``noise_timestep`` steps as DiffusionDrive does) and a
decoder regresses the clean trajectories from them: the noised anchors are embedded and
pass stacked layers that cross-attend, in turn, the scene's occupancy queries, the
encoded ego state and the LLM's decision tokens, then an FFN, each modulated by the
timestep; only the positive anchor (the one nearest the ground truth) is supervised, with
L1. A scorer on the LLM's decision tokens and the ego state is trained with BCE, the
positive anchor as the only positive. Inference noises the anchors, denoises them in
``denoise_steps`` DDIM steps and returns the top-scored anchor's trajectory.

Not the paper's, a switch (``plan_prior``): anchors and trajectories as offsets from driving
on straight at the current speed. With the paper's anchors over whole trajectories, the
top-scored anchor alone was 2.4-3.8 m from the truth on average and the denoised plan
1.7-2.4 m, where constant velocity is 0.51 m (docs/families/sparseoccvla.md).

The LLM's decision tokens are the frozen world model's last-layer outputs over the decision
it generates for the planning prompt (generated once per clip and cached). The paper trains
the planner with the LLM in its stages 2-3; here it trains after them, on the frozen
model's outputs, like every planner stage (docs/recipes.md).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, cast

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from torchmetrics import MeanMetric

from occtrain.config import to_object
from occtrain.core.builder import collate
from occtrain.core.decoding import TextAnswer
from occtrain.core.plan_subsets import plan_metrics, subset_rows, update_plans
from occtrain.core.protocols import Planner, PlannerContext, PlannerSettings, Plans, WorldEngine, family_world
from occtrain.core.shared_tasks import PLAN_PRIORS, plan_base
from occtrain.data.clips import Clip, Text, frame_clips, plan_target
from occtrain.data.layout import DatasetIndex
from occtrain.errors import ConfigError
from occtrain.families.sparseoccvla.tasks import PLANNING_PROMPT, context
from occtrain.families.sparseoccvla.world_model import EGO_FEATURES, SparseOccVLAWorldModel, ego_state, scene_rows
from occtrain.formats.exports import check_section, load_state_strict, read_export, write_export
from occtrain.formats.io import atomic_write_safetensors
from occtrain.formats.occ3d import FUTURE_STEPS
from occtrain.metrics import compute_metrics
from occtrain.models import count_parameters
from occtrain.models.planning_heads import constant_acceleration, constant_velocity
from occtrain.progress import progress_bar
from occtrain.ranks import is_rank_zero

#: The condition each decoder layer's cross-attentions read, in order (Fig. 3).
FUSIONS = ("scene", "ego", "reason")
#: Where the frozen world model's decisions are cached in the stage directory.
DECISION_CACHE = "decisions.safetensors"


@dataclass
class AnchorDiffusionConfig(PlannerSettings):
    """The planner's settings (flat in a planner stage's ``model:``)."""

    #: K-means anchors K (Table 11: 15, 18, 21; the paper's 18).
    anchors: int = 18
    #: DDIM steps at inference (Table 11: 1, 2, 3; the paper's 2). ``noise_timestep`` must
    #: split into that many equal steps of the scheduler's grid.
    denoise_steps: int = 2
    #: The truncated diffusion's start: anchors are noised up to this timestep of
    #: ``train_timesteps`` (DiffusionDrive truncates to 50 of 1000).
    noise_timestep: int = 30
    train_timesteps: int = 1000
    dim: int = 64
    layers: int = 2
    heads: int = 4
    #: The decision tokens the planner reads: at most this many of the generated decision's.
    decision_tokens: int = 48
    #: The LLM-guided scorer (Table 4: off, the decoder scores its own anchors).
    llm_scoring: bool = True
    #: The conditions the trajectories are fused with (Table 4 drops one at a time).
    fusions: list[str] = field(default_factory=lambda: list(FUSIONS))
    #: Metres per unit of the diffused trajectories (x forward, y left).
    traj_scale: list[float] = field(default_factory=lambda: [20.0, 10.0])
    #: Weight of the scorer's BCE beside the L1 of the positive anchor.
    score_weight: float = 1.0
    #: What anchors and denoised trajectories are written against. "none" (the paper):
    #: they are the trajectories. "constant_velocity": their offsets from driving on
    #: straight at the current speed (as the world models' ``tasks.plan_prior``).
    plan_prior: str = "none"

    def validate(self, where: str) -> None:
        for key in ("anchors", "denoise_steps", "noise_timestep", "dim", "layers", "heads", "decision_tokens"):
            if getattr(self, key) < 1:
                raise ConfigError(f"{where}: model.{key} {getattr(self, key)} must be at least 1")
        if self.noise_timestep >= self.train_timesteps:
            raise ConfigError(
                f"{where}: model.noise_timestep {self.noise_timestep} must be below train_timesteps "
                f"{self.train_timesteps}"
            )
        if self.dim % self.heads:
            raise ConfigError(f"{where}: model.dim {self.dim} must be divisible by heads {self.heads}")
        unknown = [f for f in self.fusions if f not in FUSIONS]
        if unknown:
            raise ConfigError(f"{where}: model.fusions {list(self.fusions)} must name some of {', '.join(FUSIONS)}")
        if self.plan_prior not in PLAN_PRIORS:
            raise ConfigError(
                f"{where}: model.plan_prior '{self.plan_prior}' is not one of {', '.join(PLAN_PRIORS)} (paper: none)"
            )
        step_spacing(self.noise_timestep, self.denoise_steps, self.train_timesteps, where)


def step_spacing(start: int, steps: int, train_timesteps: int, where: str = "model") -> int:
    """The timestep spacing of ``steps`` DDIM steps from ``start`` to 0, which must be a
    spacing of the scheduler's grid (``train_timesteps // n`` for some n)."""
    spacing = start // steps
    if spacing * steps != start or train_timesteps // (train_timesteps // spacing) != spacing:
        raise ConfigError(
            f"{where}: model.noise_timestep {start} does not split into {steps} DDIM steps of the scheduler's grid; "
            "choose noise_timestep as a multiple of denoise_steps that divides into train_timesteps (e.g. 30 for 1, 2 "
            "or 3 steps)"
        )
    return spacing


def ddim_scheduler(cfg: AnchorDiffusionConfig) -> Any:
    """diffusers' DDIM scheduler over ``train_timesteps``, predicting the clean sample."""
    from diffusers import DDIMScheduler

    return DDIMScheduler(num_train_timesteps=cfg.train_timesteps, prediction_type="sample", clip_sample=False)


def ddim_denoise(
    scheduler: Any,
    x: torch.Tensor,
    start: int,
    spacing: int,
    train_timesteps: int,
    predict: Callable[[torch.Tensor, int], tuple[torch.Tensor, Any]],
) -> tuple[torch.Tensor, Any]:
    """DDIM from ``x`` (noised to timestep ``start``) down to 0 in steps of ``spacing``,
    each by diffusers' ``scheduler.step`` on ``predict(x, t)``'s clean-sample prediction
    (``predict`` returns it and anything else, of which the last step's is returned)."""
    scheduler.set_timesteps(train_timesteps // spacing)
    extra = None
    for t in range(start, 0, -spacing):
        pred, extra = predict(x, t)
        x = scheduler.step(pred, t, x).prev_sample
    return x, extra


def offset_bases(clips: list[Clip], prior: str, device: torch.device | str = "cpu") -> torch.Tensor:
    """(B, 6, 2): what each clip's trajectory is written against under ``prior``
    (``core.shared_tasks.plan_base``; zeros for the paper's "none")."""
    bases = [plan_base(c, prior) for c in clips]
    return torch.stack(
        [torch.zeros(FUTURE_STEPS, 2) if b is None else torch.as_tensor(b, dtype=torch.float32) for b in bases]
    ).to(device)


def kmeans_anchors(index: DatasetIndex, k: int, seed: int = 0, prior: str = "none") -> np.ndarray:
    """K-means centres (K, 6, 2) of the training split's whole 3 s ego trajectories, written
    against ``prior`` (see ``offset_bases``)."""
    from sklearn.cluster import KMeans

    clips = [
        c
        for c in frame_clips(index, "train", 0, FUTURE_STEPS, partial_history=False)
        if len(c.anchor.get("ego_future", [])) >= FUTURE_STEPS
        and all(c.anchor.get("ego_future_mask", [1] * FUTURE_STEPS)[:FUTURE_STEPS])
    ]
    if len(clips) < k:
        raise ConfigError(
            f"{index.root}: {len(clips)} training trajectories with a whole 3 s future, fewer than model.anchors {k}"
        )
    trajs = np.stack([np.asarray(c.anchor["ego_future"], dtype=np.float64)[:FUTURE_STEPS] for c in clips])
    trajs = trajs - offset_bases(clips, prior).double().numpy()
    centres = KMeans(n_clusters=k, n_init=10, random_state=seed).fit(trajs.reshape(len(trajs), -1)).cluster_centers_
    return centres.reshape(k, FUTURE_STEPS, 2).astype(np.float32)


def clip_noise(clip: Clip, shape: torch.Size, seed: int = 0) -> torch.Tensor:
    """The noise a clip's anchors start from at inference: drawn from the clip's own token,
    so its plan does not depend on the batch it is planned in (validation and ``occtrain
    eval`` batch differently)."""
    generator = torch.Generator().manual_seed(seed * 2**32 + zlib.crc32(clip.anchor["token"].encode()))
    return torch.randn(shape, generator=generator)


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    angles = t.float()[:, None] * freqs[None]
    return torch.cat([angles.sin(), angles.cos()], -1)


class DecoderLayer(nn.Module):
    """Cross-attention to each condition in turn, an FFN, and the timestep's modulation."""

    def __init__(self, dim: int, heads: int, fusions: list[str]):
        super().__init__()
        self.fusions = [f for f in FUSIONS if f in fusions]
        self.attend = nn.ModuleDict({f: nn.MultiheadAttention(dim, heads, batch_first=True) for f in self.fusions})
        self.norms = nn.ModuleDict({f: nn.LayerNorm(dim) for f in self.fusions})
        self.ffn = nn.Sequential(nn.Linear(dim, 2 * dim), nn.GELU(), nn.Linear(2 * dim, dim))
        self.ffn_norm = nn.LayerNorm(dim)
        self.modulation = nn.Linear(dim, 2 * dim)

    def forward(
        self, x: torch.Tensor, conditions: dict[str, tuple[torch.Tensor, torch.Tensor | None]], time: torch.Tensor
    ) -> torch.Tensor:
        for name in self.fusions:
            keys, pad = conditions[name]
            attended, _ = self.attend[name](x, keys, keys, key_padding_mask=pad, need_weights=False)
            x = self.norms[name](x + attended)
        x = self.ffn_norm(x + self.ffn(x))
        scale, shift = self.modulation(time)[:, None].chunk(2, -1)
        return x * (1 + scale) + shift


class SparseEngine(WorldEngine, Protocol):
    """The engine the planner reads its decisions from: a SparseOccVLA world model's (the
    planner stage builds the planner of its teacher's family)."""

    @property
    def world(self) -> SparseOccVLAWorldModel: ...


def sparse_engine(teacher: WorldEngine | None, where: str) -> SparseEngine:
    """``teacher`` as the SparseOccVLA engine the planner reads, checked: the planner stage
    builds the planner of its teacher's family, so another is a bug, not a user's mistake."""
    if teacher is None:
        raise ConfigError(f"{where}: SparseOccVLA's planner reads its world model's decisions; consume its stage")
    family_world(teacher, SparseOccVLAWorldModel)
    return cast(SparseEngine, teacher)


class AnchorDiffusionPlanner(Planner):
    """The planner, the frozen world model's decisions it reads (cached per clip) and its
    validation metrics (see the module docstring)."""

    #: What picks the best checkpoint (lower is better).
    monitor = "val/plan_L2_stp3_avg"
    #: (K, 6, 2) metres, and the metres per unit of the diffused trajectories (2,).
    anchors: torch.Tensor
    scale: torch.Tensor
    #: The anchor scorer: on the decision and the ego state, or on the decoder's own features.
    scorer: nn.Module

    def closed_loop_refusal(self) -> str | None:
        return None  # it reads the world model's decision, which closed loop generates too

    def __init__(
        self,
        cfg: AnchorDiffusionConfig,
        teacher: SparseEngine,
        data_root: str,
        cache_dir: Path,
        anchors: np.ndarray | None = None,
        seed: int = 0,
    ):
        """``anchors``: (K, 6, 2) in metres; None: the K-means centres of ``data_root``'s training trajectories."""
        super().__init__()
        self.cfg, self.teacher = cfg, teacher
        self.data_root = data_root
        self._cache_file = Path(cache_dir) / DECISION_CACHE
        if anchors is None:
            anchors = kmeans_anchors(DatasetIndex.open(data_root), cfg.anchors, seed, cfg.plan_prior)
        self.register_buffer("anchors", torch.as_tensor(anchors, dtype=torch.float32))
        self.register_buffer("scale", torch.tensor(cfg.traj_scale, dtype=torch.float32))
        hidden, query_dim, d = teacher.world.hidden_size, teacher.world.query_dim, cfg.dim
        self.scheduler = ddim_scheduler(cfg)
        self.traj_in = nn.Sequential(nn.Linear(FUTURE_STEPS * 2, d), nn.GELU(), nn.Linear(d, d))
        self.time_in = nn.Sequential(nn.Linear(d, d), nn.GELU(), nn.Linear(d, d))
        self.scene_in = nn.Linear(query_dim + 3, d)
        self.ego_in = nn.Sequential(nn.Linear(EGO_FEATURES, d), nn.GELU(), nn.Linear(d, d))
        self.reason_in = nn.Linear(hidden, d)
        self.layers = nn.ModuleList(DecoderLayer(d, cfg.heads, cfg.fusions) for _ in range(cfg.layers))
        self.traj_out = nn.Linear(d, FUTURE_STEPS * 2)
        if cfg.llm_scoring:
            self.scorer = nn.Sequential(nn.Linear(hidden + d, d), nn.GELU(), nn.Linear(d, cfg.anchors))
        else:
            self.scorer = nn.Linear(d, 1)
        self._decisions: dict[str, dict[str, torch.Tensor]] = {}
        self._load_cache()
        names = ("plan", "plan_top_anchor", "constant_velocity", "constant_acceleration", "baseline_stationary")
        self.metrics = nn.ModuleDict(plan_metrics(names))
        self.positive_hit = MeanMetric()

    @classmethod
    def from_stage(cls, ctx: PlannerContext, teacher: WorldEngine | None) -> AnchorDiffusionPlanner:
        """The planner a planner stage trains (``WorldSpec.planner``)."""
        engine = sparse_engine(teacher, f"stages '{ctx.spec.name}'")
        return cls(to_object(ctx.model_cfg), engine, ctx.data.root, ctx.cache_dir, seed=ctx.data.seed)

    @classmethod
    def from_export(
        cls, export_dir: Path, teacher: WorldEngine, data_root: str, cache_dir: Path
    ) -> AnchorDiffusionPlanner:
        """A trained planner back from its export (``WorldSpec.load_planner``)."""
        state, config = read_export(export_dir)
        check_section(AnchorDiffusionConfig, config["config"], "config", export_dir)
        cfg = AnchorDiffusionConfig(**config["config"])
        engine = sparse_engine(teacher, str(export_dir))
        planner = cls(cfg, engine, data_root, cache_dir, anchors=state["anchors"].numpy())
        load_state_strict(planner, state, ("teacher.",), str(export_dir))
        return planner.eval()

    @property
    def device(self) -> torch.device:
        return self.anchors.device

    def sidecar_tasks(self) -> list[str]:
        return []

    # -- the frozen world model's decisions, once per clip
    def _load_cache(self) -> None:
        if self._cache_file.is_file():
            from safetensors.torch import load_file

            flat = load_file(str(self._cache_file))
            for key, value in flat.items():
                token, name = key.split("/")
                self._decisions.setdefault(token, {})[name] = value

    def save_cache(self) -> None:
        if is_rank_zero() and self._decisions:
            atomic_write_safetensors(
                self._cache_file, {f"{t}/{k}": v.contiguous() for t, d in self._decisions.items() for k, v in d.items()}
            )

    @torch.no_grad()
    def decisions(self, clips: list[Clip]) -> list[dict[str, torch.Tensor]]:
        """Per clip: ``reason`` (R, hidden) the world model's outputs over the decision it
        generates (zero rows past ``mask``), ``mask`` (R,) and ``scene`` (N, 3 + D) the encoder rows."""
        todo = [c for c in clips if c.anchor["token"] not in self._decisions]
        if todo:
            self._decide(todo)
        return [self._decisions[c.anchor["token"]] for c in clips]

    def _decide(self, clips: list[Clip]) -> None:
        engine, r = self.teacher, self.cfg.decision_tokens
        rows = [scene_rows(engine)[c.anchor["token"]] for c in clips]
        prompts = [[*context(c, engine.tasks), Text(PLANNING_PROMPT)] for c in clips]
        laid = [engine.encode_parts(p, {c.anchor_index: row}) for p, c, row in zip(prompts, clips, rows)]
        texts = [
            engine.vocab.decode_text(out[0])
            for out in engine.world.generate_batch(laid, [[TextAnswer(engine.max_new_text_tokens)]] * len(laid))
        ]
        seqs = [
            engine.encode_parts([*p, Text(t)], {c.anchor_index: row})
            for p, t, c, row in zip(prompts, texts, clips, rows)
        ]
        batch = {
            k: v.to(engine.world.device) if torch.is_tensor(v) else v
            for k, v in collate(seqs, engine.vocab.pad_id).items()
        }
        hidden = engine.world(batch, output_hidden_states=True).hidden.float().cpu()
        for b, (clip, start, seq) in enumerate(zip(clips, (len(x) for x in laid), seqs)):
            states = hidden[b, start : len(seq)][:r]
            reason = torch.zeros(r, hidden.shape[-1])
            reason[: len(states)] = states
            self._decisions[clip.anchor["token"]] = {
                "reason": reason,
                "mask": torch.arange(r) < len(states),
                "scene": rows[b].float().cpu(),
            }

    def prepare_training(self, device: torch.device) -> None:
        """The world model's decisions on every training clip, once (validation's come as its batches do)."""
        index = DatasetIndex.open(self.data_root)
        clips = list(
            frame_clips(index, "train", self.teacher.tasks.context_frames, FUTURE_STEPS, partial_history=False)
        )
        self.teacher.to(device)
        with progress_bar(len(clips), "the world model's decisions on the train split, once") as advance:
            for i in range(0, len(clips), 16):
                self.decisions(clips[i : i + 16])
                advance(len(clips[i : i + 16]))
        self.save_cache()

    # -- the planner
    def conditions(
        self, clips: list[Clip]
    ) -> tuple[dict[str, tuple[torch.Tensor, torch.Tensor | None]], torch.Tensor, torch.Tensor]:
        """The decoder's conditions, the ego embedding (B, d) and the pooled decision (B, hidden)."""
        dec = self.decisions(clips)
        dev = self.device
        scene = torch.stack([d["scene"] for d in dec]).to(dev)
        reason = torch.stack([d["reason"] for d in dec]).to(dev)
        mask = torch.stack([d["mask"] for d in dec]).to(dev)
        ego = self.ego_in(torch.tensor([ego_state(c.anchor) for c in clips], dtype=torch.float32, device=dev))
        conditions = {
            "scene": (self.scene_in(scene), None),
            "ego": (ego[:, None], None),
            # A decision that came out empty still has one (zero) token to attend to.
            "reason": (self.reason_in(reason), ~(mask | (torch.arange(mask.shape[1], device=dev) == 0))),
        }
        pooled = (reason * mask[..., None]).sum(1) / mask.sum(1, keepdim=True).clamp(min=1)
        return conditions, ego, pooled

    def denoise(self, noisy: torch.Tensor, t: torch.Tensor, conditions: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """Noised anchors (B, K, 6, 2) in scaled units at timesteps ``t`` (B,) -> the clean
        trajectories (B, K, 6, 2) the decoder regresses, and its features (B, K, d)."""
        x = self.traj_in(noisy.flatten(2))
        time = self.time_in(timestep_embedding(t, self.cfg.dim))
        x = x + time[:, None]
        for layer in self.layers:
            x = layer(x, conditions, time)
        return self.traj_out(x).view(noisy.shape), x

    def scores(self, features: torch.Tensor, ego: torch.Tensor, pooled: torch.Tensor) -> torch.Tensor:
        """Anchor logits (B, K): from the decision and the ego state, or (Table 4's
        "w/o LLM scoring") from the decoder's own features."""
        if self.cfg.llm_scoring:
            return self.scorer(torch.cat([pooled, ego], -1))
        return self.scorer(features).squeeze(-1)

    def base(self, clips: list[Clip]) -> torch.Tensor:
        """(B, 6, 2): what the clips' anchors and plans are offsets from (``plan_prior``)."""
        return offset_bases(clips, self.cfg.plan_prior, self.device)

    def positives(self, offsets: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """The anchor nearest each ground truth (B,), both written against the base: mean L2
        over its known steps."""
        err = (self.anchors[None] - offsets[:, None]).norm(dim=-1)  # (B, K, 6)
        return ((err * mask[:, None]).sum(-1) / mask.sum(-1, keepdim=True).clamp(min=1)).argmin(-1)

    def training_loss(self, clips: list[Clip]) -> torch.Tensor:
        gt = plan_target([c.anchor for c in clips], self.device)
        offsets = gt.traj - self.base(clips)
        conditions, ego, pooled = self.conditions(clips)
        b, k = len(clips), self.cfg.anchors
        t = torch.randint(0, self.cfg.noise_timestep, (b,), device=self.device)
        clean = (self.anchors / self.scale).expand(b, -1, -1, -1)
        noisy = self.scheduler.add_noise(clean, torch.randn_like(clean), t)
        pred, features = self.denoise(noisy, t, conditions)
        positive = self.positives(offsets, gt.mask)
        chosen = pred[torch.arange(b), positive] * self.scale
        l1 = ((chosen - offsets).abs().sum(-1) * gt.mask).sum() / gt.mask.sum().clamp(min=1)
        target = F.one_hot(positive, k).float()
        bce = F.binary_cross_entropy_with_logits(self.scores(features, ego, pooled), target)
        return l1 + self.cfg.score_weight * bce

    @torch.no_grad()
    def plan(
        self, clips: list[Clip], steps: int | None = None, seed: int = 0
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The plan (B, 6, 2) in metres after ``steps`` DDIM steps (default: the configured
        ones), the top-scored anchor itself (B, 6, 2) and the anchor logits (B, K)."""
        cfg = self.cfg
        spacing = step_spacing(cfg.noise_timestep, steps or cfg.denoise_steps, cfg.train_timesteps)
        conditions, ego, pooled = self.conditions(clips)
        b = len(clips)
        clean = (self.anchors / self.scale).expand(b, -1, -1, -1)
        noise = torch.stack([clip_noise(c, clean.shape[1:], seed) for c in clips]).to(self.device)
        x = self.scheduler.add_noise(
            clean, noise, torch.full((b,), cfg.noise_timestep, dtype=torch.long, device=self.device)
        )

        def predict(x: torch.Tensor, t: int) -> tuple[torch.Tensor, torch.Tensor]:
            return self.denoise(x, torch.full((b,), t, dtype=torch.long, device=self.device), conditions)

        x, features = ddim_denoise(self.scheduler, x, cfg.noise_timestep, spacing, cfg.train_timesteps, predict)
        logits = self.scores(features, ego, pooled)
        best = logits.argmax(-1)
        rows = torch.arange(b, device=self.device)
        base = self.base(clips)
        return x[rows, best] * self.scale + base, self.anchors[best] + base, logits

    @torch.no_grad()
    def waypoints(self, clips: list[Clip]) -> Plans:
        """The denoised plan of the top-scored anchor (the family's main plan): always its own."""
        return Plans.own(self.plan(clips)[0].cpu().numpy())

    def validate(self, clips: list[Clip], batch_idx: int, generate_batches: int = -1) -> None:
        anchors = [c.anchor for c in clips]
        gt = plan_target(anchors, self.device)
        plan, top, logits = self.plan(clips)
        subsets = subset_rows(anchors, gt)
        for name, pred in (
            ("plan", plan),
            ("plan_top_anchor", top),
            ("constant_velocity", constant_velocity(anchors, self.device)),
            ("constant_acceleration", constant_acceleration(anchors, self.device)),
            ("baseline_stationary", torch.zeros_like(gt.traj)),
        ):
            update_plans(self.metrics, name, pred, gt, subsets)
        # How often the scorer picks the anchor nearest the ground truth.
        hit = (logits.argmax(-1) == self.positives(gt.traj - self.base(clips), gt.mask)).float()
        self.positive_hit.update(100.0 * hit.mean(), len(clips))

    def compute(self, prefix: str) -> dict[str, float]:
        return compute_metrics(prefix, reset=True, metrics={**self.metrics, "scorer_top1": self.positive_hit})

    def summary(self) -> tuple[str, dict[str, float]]:
        assert isinstance(self.teacher, nn.Module)  # the engine, a submodule: its parameters are among self's
        n = count_parameters(self) - count_parameters(self.teacher)
        return (
            f"anchor-diffusion planner {n / 1e3:.1f}K params, {self.cfg.anchors} anchors, {self.cfg.denoise_steps} "
            "DDIM steps",
            {"params": float(n)},
        )

    def export(self, path: Path) -> Path:
        state = {k: v for k, v in self.state_dict().items() if not k.startswith("teacher.")}
        config = {
            "stage_kind": "planner",
            "planner": "anchor_diffusion",
            "family": "sparseoccvla",
            "config": {k: getattr(self.cfg, k) for k in AnchorDiffusionConfig.__dataclass_fields__},
        }
        return write_export(path, state, config)
