"""A world-model family written outside occtrain: the proof that a family is one module
plus one registration (README's "Adding a family" follows it step by step).

Its scene encoder is continuous, not a VQ tokenizer: a scene is 100 tokens, one per
8 m x 8 m column of the Occ3D grid, each its centre (x, y, z) and the share of every class
at every height in it; decoding paints each column's commonest class at each height. The
world model embeds a scene token from those features (they ride beside the ids as
payload), predicts a scene's tokens from a query block and regresses their features. Its
own task asks how many columns hold a car, graded by its own scorer beside the commonest
answer; its own planner reads the world model's summary of the anchor scene.

It also needs an input no shipped family reads: how much of each column the cameras see
(the share of its voxels in the frame's ``mask_camera``). It registers that input with its
spec (``sample_inputs``); its own prompt part, ``Visibility``, names the frame, and its
builder reads the values by name. Neither core nor the engine knows the input.

Registered by importing this module (a recipe's ``plugins: [plugins.tiny_family]``, or
the ``occtrain.families`` entry point of an installed package).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from torchmetrics import MeanMetric

from occtrain.core import scorers
from occtrain.core.builder import SequenceBuilder, batch_payload
from occtrain.core.lm_world_model import LMWorldModel, WorldInputs, WorldModelOutput, token_ce
from occtrain.core.protocols import Planner, PlannerSettings, Plans, PromptInputs, ScoringContext
from occtrain.core.registry import FamilySpec, WorldSpec, register_family
from occtrain.core.sample_inputs import InputSource, SampleInput, Samples
from occtrain.core.sequence import IGNORE, TokenSequence, empty_payload
from occtrain.core.shared_tasks import TaskConfig, TaskSpec, each_question, forecast_after, questions_after
from occtrain.data.clips import Clip, Part, PromptPart, Scene, Text, plan_target
from occtrain.data.layout import DatasetIndex
from occtrain.formats.exports import write_export
from occtrain.formats.occ3d import CLASS_INDEX, FUTURE_STEPS, GRID_SHAPE, NUM_CLASSES, VOXEL_SIZE
from occtrain.metrics import PlanningMetric, compute_metrics
from occtrain.models.planning_heads import constant_velocity, current_velocity

CELLS = 10  # columns per side
SIDE = GRID_SHAPE[0] // CELLS
FEATURES = 3 + GRID_SHAPE[2] * NUM_CLASSES  # centre, then per height the class shares
CAR = CLASS_INDEX["car"]


# ----------------------------------------------------------------------------- the scene encoder


class ColumnEncoder(nn.Module):
    """Occupancy -> 100 continuous tokens with their positions (``SceneEncoder``, not discrete)."""

    discrete = False
    export_dir = None  # nothing to copy: it has no weights

    def __init__(self) -> None:
        super().__init__()
        c = (torch.arange(CELLS, dtype=torch.float32) + 0.5) * SIDE * VOXEL_SIZE - GRID_SHAPE[0] * VOXEL_SIZE / 2
        xy = torch.stack(torch.meshgrid(c, c, indexing="ij"), -1).reshape(-1, 2)
        self.register_buffer("centres", torch.cat([xy, torch.full((CELLS * CELLS, 1), 1.0)], 1), persistent=False)

    def encode(self, semantics: torch.Tensor) -> torch.Tensor:
        b = semantics.shape[0]
        onehot = F.one_hot(semantics.long(), NUM_CLASSES).float()  # B X Y Z C
        cols = onehot.view(b, CELLS, SIDE, CELLS, SIDE, GRID_SHAPE[2], NUM_CLASSES).mean((2, 4))  # B cx cy Z C
        return torch.cat([self.centres.expand(b, -1, -1), cols.reshape(b, CELLS * CELLS, -1)], -1)

    def decode(self, scenes: torch.Tensor) -> torch.Tensor:
        shares = scenes[..., 3:].reshape(-1, CELLS, CELLS, GRID_SHAPE[2], NUM_CLASSES)
        classes = shares.argmax(-1)  # N cx cy Z
        return classes.repeat_interleave(SIDE, 1).repeat_interleave(SIDE, 2)


def column_encoder(exports: dict, world_cfg: Any = None) -> ColumnEncoder:
    return ColumnEncoder()


def load_column_encoder(export_dir: Path, config: dict) -> ColumnEncoder:
    return ColumnEncoder()


# ----------------------------------------------------------------------------- its own input


VISIBLE = "<visible>"


def visible_columns(source: InputSource, index: DatasetIndex, samples: Samples) -> torch.Tensor:
    """The share of each column's voxels the cameras see, (N, CELLS * CELLS)."""
    masks = np.stack([index.labels(s, t)["mask_camera"] for s, t in samples]).astype(np.float32)
    cols = masks.reshape(len(samples), CELLS, SIDE, CELLS, SIDE, -1).mean((2, 4, 5))
    return torch.from_numpy(cols.reshape(len(samples), CELLS * CELLS))


#: Encoded once per dataset (it reads every voxel of every frame), into
#: ``visible_columns.safetensors`` in the stage's cache directory.
VISIBLE_COLUMNS = SampleInput("visible_columns", visible_columns, encoded=True, what="measuring what the cameras see")


@dataclass(frozen=True)
class Visibility(PromptPart):
    """How much of each column of sample ``token`` the cameras see (one token)."""

    token: str
    supervise: bool = False  # never: an input


# ----------------------------------------------------------------------------- the world model


class ColumnBuilder(SequenceBuilder):
    """A scene is its 100 slot tokens carrying their features (a query block first when
    supervised); the visibility of a frame is one ``<visible>`` token carrying its shares."""

    def lay(self, part: Part, inputs: PromptInputs, scenes: dict[int, torch.Tensor]) -> ColumnBuilder:
        if isinstance(part, Visibility):
            payload = empty_payload(self.payload_spec, 1)
            payload["visible"] = inputs.read(VISIBLE_COLUMNS.name, part.token).float()[None]
            self.add(torch.tensor([self.vocab.extra_id(VISIBLE)]), False, payload=payload)
            return self
        super().lay(part, inputs, scenes)
        return self

    def scene(self, features: torch.Tensor, supervise: bool = False) -> ColumnBuilder:
        v, n = self.vocab, self.vocab.scene_len
        feats = torch.as_tensor(features, dtype=torch.float32).reshape(n, FEATURES)
        self.add(torch.tensor([v.occ_open_id]), supervise)
        block = self.next_block()
        if supervise:
            queries = empty_payload(self.payload_spec, n)
            queries["target"], queries["has_target"] = feats, torch.ones(n)
            self.add(v.query_ids(), False, seg=-block, payload=queries)
        slots = empty_payload(self.payload_spec, n)
        slots["feat"] = feats
        self.add(torch.arange(v.occ_start, v.occ_start + n), False, seg=block, payload=slots)
        self.add(torch.tensor([v.occ_close_id]), supervise)
        return self


class ColumnScene:
    """Writes a generated scene: its features regressed from the query block's hidden states."""

    def __init__(self, world: ColumnWorldModel):
        self.world, self.feats = world, None

    def from_queries(self, logits: torch.Tensor, hidden: torch.Tensor) -> tuple[torch.Tensor, dict]:
        v = self.world.vocab
        self.feats = self.world.predict_features(hidden)
        n = v.scene_len
        payload = empty_payload(self.world.payload_spec, n, hidden.device)
        payload["feat"] = self.feats
        return torch.arange(v.occ_start, v.occ_start + n, device=hidden.device), payload

    def codes(self) -> torch.Tensor:
        return self.feats


class ColumnWorldModel(LMWorldModel):
    """An LLM over slot tokens that carry continuous scene features."""

    def __init__(self, llm: nn.Module, vocab, scene_prediction: str = "next_scene"):
        super().__init__(llm, vocab, scene_prediction)
        hidden = self.hidden_size
        self.embed_features = nn.Linear(FEATURES, hidden)
        self.to_features = nn.Linear(hidden, FEATURES - 3)
        self.payload_spec = {
            "feat": ((FEATURES,), torch.float32, 0.0),
            "target": ((FEATURES,), torch.float32, 0.0),
            "has_target": ((), torch.float32, 0.0),
            "visible": ((CELLS * CELLS,), torch.float32, 0.0),
        }
        self.embed_visible = nn.Linear(CELLS * CELLS, hidden)
        centres = ColumnEncoder().centres
        self.register_buffer("centres", centres, persistent=False)

    def builder(self) -> ColumnBuilder:
        return ColumnBuilder(self.vocab, self.scene_prediction, self.payload_spec)

    def scene_writer(self, recent: torch.Tensor, waypoint: torch.Tensor | None = None) -> ColumnScene:
        return ColumnScene(self)

    def embed(self, input_ids: torch.Tensor, payload: dict | None = None) -> torch.Tensor:
        emb = self.llm.get_input_embeddings()(input_ids)
        if not payload:
            return emb
        slots = self.vocab.is_occ(input_ids)[..., None]
        visible = (input_ids == self.vocab.extra_id(VISIBLE))[..., None]
        emb = emb + slots * self.embed_features(payload["feat"]).to(emb.dtype)
        return emb + visible * self.embed_visible(payload["visible"]).to(emb.dtype)

    def predict_shares(self, hidden: torch.Tensor) -> torch.Tensor:
        """Hidden states (..., H) -> each height's class shares (..., Z * C)."""
        return self.to_features(hidden).view(*hidden.shape[:-1], GRID_SHAPE[2], NUM_CLASSES).softmax(-1).flatten(-2)

    def predict_features(self, hidden: torch.Tensor) -> torch.Tensor:
        """A query block's hidden states (Q, H) -> its scene rows (Q, FEATURES): centres, then class shares."""
        return torch.cat([self.centres, self.predict_shares(hidden)], -1)

    def forward(self, batch: dict, output_hidden_states: bool = False) -> WorldModelOutput:
        payload = batch_payload(batch)
        out = self._run(
            batch["input_ids"], batch["attention_mask"], batch["position_ids"], hidden=True, payload=payload
        )
        labels = batch["labels"]
        ce = token_ce(out.logits, labels)
        valid = labels != IGNORE
        text = (ce * valid).sum() / valid.sum().clamp(min=1)
        rows = payload["has_target"] > 0
        pred = self.predict_shares(out.hidden_states[-1][rows])
        scene = F.mse_loss(pred, payload["target"][rows][..., 3:], reduction="sum") / rows.sum().clamp(min=1)
        per_sample = (ce * valid).sum(1) / valid.sum(1).clamp(min=1)
        return WorldModelOutput(
            text + scene, text, scene, out.logits, out.hidden_states[-1] if output_hidden_states else None, per_sample
        )

    def check_prompt(self, prefix):
        if not isinstance(prefix, TokenSequence) and bool(self.vocab.is_occ(torch.as_tensor(prefix)).any()):
            raise ValueError("a prompt with scene slots needs their features: pass the laid-out sequence")
        return prefix

    @staticmethod
    def vocab_layout(inputs: WorldInputs, world_cfg: Any = None) -> dict:
        return {"codebook_sizes": [], "scene_hw": (CELLS, CELLS), "patch": 1, "extra": (VISIBLE,)}

    @classmethod
    def create(cls, llm, vocab, inputs, scene_prediction, world_cfg=None) -> ColumnWorldModel:
        return cls(llm, vocab, scene_prediction)

    @classmethod
    def from_export(cls, data: dict, llm, vocab, inputs) -> ColumnWorldModel:
        return cls(llm, vocab, data["scene_prediction"])


# ----------------------------------------------------------------------------- tasks and scoring


@dataclass
class ColumnTasks(TaskConfig):
    context_frames: int = 1
    #: Future scenes a forecast alternates with waypoints.
    forecast_frames: int = 2


def _context(clip: Clip, cfg: ColumnTasks) -> list[Part]:
    a = clip.anchor_index
    return [Visibility(clip.anchor["token"]), *(Scene(f) for f in range(max(0, a - cfg.context_frames), a + 1))]


def car_columns(clip: Clip, cfg: ColumnTasks, rng) -> list[Part] | None:
    """How many of the anchor's columns hold a car (from the boxes: one per car's column)."""
    cells = {
        (int((b["center"][0] + 40) // 8), int((b["center"][1] + 40) // 8))
        for b in clip.anchor.get("boxes", [])
        if b["category"] == "car"
    }
    return [*_context(clip, cfg), Text("How many columns hold a car?"), Text(str(len(cells)), True)]


def forecasting(clip: Clip, cfg: ColumnTasks, rng) -> list[Part] | None:
    return forecast_after([*_context(clip, cfg), Text("Forecast.")], clip, cfg.forecast_frames)


def qa(clip: Clip, cfg: ColumnTasks, rng) -> list[Part] | None:
    return questions_after(_context(clip, cfg), clip, cfg, rng)


def every_question(clip: Clip, cfg: ColumnTasks) -> list[list[Part]]:
    return each_question(_context(clip, cfg), clip)


class CarColumnScorer(scorers.BaseScorer):
    """Exact-match accuracy of the car-column count, beside always answering the commonest count."""

    metrics = {"car_columns_acc": MeanMetric, "baseline_commonest_car_columns_acc": MeanMetric}

    def __init__(self) -> None:
        self.answers: Counter = Counter()

    def score(self, ev: ScoringContext, item: scorers.Item) -> None:
        truth, said = item.parts[-1].text, item.generated[0].text.strip()
        self.answers[truth] += 1
        ev.metric("car_columns_acc").update(100.0 * (said == truth))
        ev.metric("baseline_commonest_car_columns_acc").update(
            100.0 * (truth == "0")
        )  # the synthetic world's commonest
        ev.keep_text("car_columns", item.parts[-2].text, said, truth)


TASKS = {
    "car_columns": TaskSpec(car_columns, scorer=CarColumnScorer),
    "forecasting": TaskSpec(
        forecasting, scorer=(scorers.ForecastScorer, scorers.plan_scorer("plan_alternate", alternate=True))
    ),
    "qa": TaskSpec(qa, every_question, scorers.QAScorer),
}


# ----------------------------------------------------------------------------- the planner


@dataclass
class SummaryPlannerConfig(PlannerSettings):
    """The planner's settings (flat in a planner stage's ``model:``)."""

    hidden: int = 32


class SummaryPlanner(Planner):
    """Waypoints from the world model's mean output over the anchor scene's tokens, added to
    constant velocity."""

    monitor = "val/head_L2_stp3_avg"

    def closed_loop_refusal(self) -> str | None:
        return None

    def __init__(self, ctx: Any, teacher: Any):
        super().__init__()
        self.teacher = teacher.requires_grad_(False).eval()
        self.head = nn.Sequential(
            nn.Linear(teacher.world.hidden_size + 2, ctx.model_cfg.hidden),
            nn.GELU(),
            nn.Linear(ctx.model_cfg.hidden, FUTURE_STEPS * 2),
        )
        self.metrics = nn.ModuleDict({"head": PlanningMetric(), "constant_velocity": PlanningMetric()})

    @property
    def device(self) -> torch.device:
        return next(self.head.parameters()).device

    @torch.no_grad()
    def _summary(self, clips: list[Clip]) -> torch.Tensor:
        engine = self.teacher
        rows = engine.scenes({"ann": [c.ann for c in clips]}, [{c.anchor_index} for c in clips])
        seqs = [
            engine.encode_parts([Scene(c.anchor_index)], {c.anchor_index: rows[(b, c.anchor_index)]})
            for b, c in enumerate(clips)
        ]
        from occtrain.core.builder import collate

        batch = {
            k: v.to(self.device) if torch.is_tensor(v) else v for k, v in collate(seqs, engine.vocab.pad_id).items()
        }
        hidden = engine.world(batch, output_hidden_states=True).hidden
        slots = engine.vocab.is_occ(batch["input_ids"]).float()[..., None]
        return (hidden * slots).sum(1) / slots.sum(1).clamp(min=1)

    def _plan(self, clips: list[Clip]) -> torch.Tensor:
        velocity = torch.tensor(
            np.stack([current_velocity(c.anchor) for c in clips]), dtype=torch.float32, device=self.device
        )
        x = torch.cat([self._summary(clips), velocity / 10.0], 1)
        return constant_velocity([c.anchor for c in clips], self.device) + self.head(x).view(-1, FUTURE_STEPS, 2)

    def training_loss(self, clips: list[Clip]) -> torch.Tensor:
        gt = plan_target([c.anchor for c in clips], self.device)
        err = (self._plan(clips) - gt.traj).pow(2).sum(-1)
        return (err * gt.mask).sum() / gt.mask.sum().clamp(min=1)

    def validate(self, clips: list[Clip], batch_idx: int, generate_batches: int = -1) -> None:
        gt = plan_target([c.anchor for c in clips], self.device)
        self.metrics["head"].update(self._plan(clips), gt.traj, gt.mask, gt.agents)
        self.metrics["constant_velocity"].update(
            constant_velocity([c.anchor for c in clips], self.device), gt.traj, gt.mask, gt.agents
        )

    @torch.no_grad()
    def waypoints(self, clips: list[Clip]) -> Plans:
        return Plans.own(self._plan(clips).cpu().numpy())

    def compute(self, prefix: str) -> dict[str, float]:
        return compute_metrics(prefix, self.metrics, reset=True)

    def prepare_training(self, device: torch.device) -> None:
        self.teacher.to(device)

    def sidecar_tasks(self) -> list[str]:
        return []

    def summary(self) -> tuple[str, dict[str, float]]:
        n = sum(p.numel() for p in self.head.parameters())
        return f"summary planner {n} params", {"params": float(n)}

    def export(self, path: Path) -> Path:
        return write_export(path, self.head.state_dict(), {"stage_kind": "planner", "planner": "summary"})


def describe_scene(engine: Any, clip: Clip) -> str:
    """An operation of its own for the Python API: the number of car columns it counts."""
    from occtrain.core import shared_operations

    generated, _ = shared_operations.generate_one(engine, "car_columns", clip)
    return f"{generated[0].text.strip()} columns hold a car"


TINY = register_family(
    FamilySpec(
        name="tiny_columns",
        paper="occtrain's plugin example",
        world=WorldSpec(
            model=ColumnWorldModel,
            task_config=ColumnTasks,
            tasks=TASKS,
            default_tasks={
                "pretrain": {"forecasting": 1.0, "car_columns": 1.0},
                "instruct": {"qa": 1.0, "car_columns": 1.0},
            },
            prompt_words=("How many columns hold a car?", "Forecast."),
            inputs=(),
            sample_inputs=(VISIBLE_COLUMNS,),
            scene_encoder=column_encoder,
            load_scene_encoder=load_column_encoder,
            planner=SummaryPlanner,
            planner_config=SummaryPlannerConfig,
            operations={"describe_scene": describe_scene},
        ),
    )
)
