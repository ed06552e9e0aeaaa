"""Scorers several families share: each grades one task's generated answers with the
papers' metrics and adds the baselines the literature compares with, on the same samples.

A family names a task's scorers in its :class:`~occtrain.core.shared_tasks.TaskSpec`; the
evaluator (``engine.evaluator``) makes one of each per evaluation, makes every metric a
scorer names once (so scorers share a baseline by naming it alike), and hands each
generated item to its task's scorers. A family with its own way of grading writes its own
scorer against :class:`~occtrain.core.protocols.Scorer`.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torchmetrics import MeanMetric

from occtrain.core.plan_subsets import SUBSETS, subset_rows, update_plans
from occtrain.core.protocols import ScoringContext, WorldEngine
from occtrain.core.shared_tasks import question_of
from occtrain.data.clips import Actions, Clip, Part, PlanTarget, Scene, text_of
from occtrain.data.geometry import moved_scene
from occtrain.data.layout import DatasetIndex
from occtrain.data.meta_actions import MetaActionConfig, past_labels
from occtrain.data.schema import MetaAction
from occtrain.data.text_formats import meta_action_words, parse_meta_action
from occtrain.data.voxel_prior import voxel_prior
from occtrain.formats.occ3d import CLASS_NAMES, FREE, FUTURE_STEPS, MOVABLE_CLASSES
from occtrain.metrics import CaptionMetric, ForecastMetric, MetaActionAccuracy, PlanningMetric, QAMetric
from occtrain.models.planning_heads import ALONG_ROUTE, constant_acceleration, constant_velocity, prior_plan


@dataclass
class Priors:
    """The commonest training answers: the baselines a model must beat by learning."""

    #: NuScenes-QA template type -> its commonest answer.
    qa: dict[str, str] = field(default_factory=dict)
    #: The commonest meta action ({"speed", "direction"}) of the frame sidecars, None without them.
    meta_action: dict | None = None
    #: The dataset the per-voxel prior is counted on (``voxels``), and where it is kept.
    data_root: str | None = None
    cache_dir: Path | None = None
    _voxels: torch.Tensor | None = field(default=None, repr=False)

    def voxels(self) -> torch.Tensor:
        """(X, Y, Z) long: each voxel's commonest train label (``data.voxel_prior``), counted
        at the first call (a forecast scorer's), kept in ``cache_dir``."""
        if self._voxels is None:
            if self.data_root is None:
                raise ValueError("these priors were made without a dataset: no per-voxel prior to count")
            self._voxels = torch.from_numpy(voxel_prior(self.data_root, self.cache_dir)).long()
        return self._voxels

    @classmethod
    def of(cls, data_root: str | Path, cache_dir: Path | None = None) -> Priors:
        index = DatasetIndex.open(data_root)
        by_type: dict[str, Counter] = {}
        for q in index.questions("train") or []:
            by_type.setdefault(q["template_type"], Counter())[q["answer"]] += 1
        metas = Counter(
            (f["meta_action"]["speed"], f["meta_action"]["direction"])
            for scene in index.splits.get("train", [])
            if index.has_frame_annotations(scene)
            for f in index.frames(scene)
            if "meta_action" in f
        )
        meta = None
        if metas:
            speed, direction = metas.most_common(1)[0][0]
            meta = {"speed": speed, "direction": direction}
        return cls({t: c.most_common(1)[0][0] for t, c in by_type.items()}, meta, str(data_root), cache_dir)


@dataclass
class Item:
    """One generated item to score: the task, its clip, the prompt-answer parts, the
    generated parts, the scene of every clip frame it saw or generated, the clip's label
    volumes (for scorers that read them), its planning target and the engine."""

    task: str
    clip: Clip
    parts: list[Part]
    generated: list[Part]
    scenes: dict[int, torch.Tensor]
    semantics: torch.Tensor | None
    target: PlanTarget
    engine: WorldEngine


class BaseScorer:
    """What the shared scorers have in common: no own state, nothing derived."""

    metrics: dict[str, Any] = {}
    needs_semantics = False

    def score(self, evaluator: ScoringContext, item: Item) -> None:
        raise NotImplementedError

    def summary(self, prefix: str) -> dict[str, float]:
        return {}

    def reset(self) -> None:
        pass


#: The plan baselines, scored once on every clip any plan is scored on (with their twins on
#: the clips that depart from constant velocity, ``core.plan_subsets``).
PLAN_BASELINES = {
    name + subset: PlanningMetric
    for name in (
        "baseline_constant_velocity",
        "baseline_constant_acceleration",
        "baseline_constant_acceleration_along_route",
        "baseline_stationary",
    )
    for subset in ("", *SUBSETS)
}


class PlanScorer(BaseScorer):
    """A plan from the generated waypoints (the last action block's, or with ``alternate``
    every block's point in turn: a forecast's waypoints between its scenes), under metric
    ``name``; with ``record``, the predictions ``occtrain score planning`` reads."""

    def __init__(self, name: str, alternate: bool = False, record: bool = False):
        self.name, self.alternate, self.record = name, alternate, record
        self.metrics = {n: PlanningMetric for n in (name, *(name + subset for subset in SUBSETS))} | PLAN_BASELINES

    def score(self, ev: ScoringContext, item: Item) -> None:
        target, anchor, token = item.target, item.clip.anchor, item.clip.anchor["token"]
        subsets = subset_rows([anchor], target)
        if ev.once(("plan baselines", token)):  # standing still, constant velocity and acceleration, once a clip
            cv = constant_velocity([anchor], ev.device)
            update_plans(ev.metrics, "baseline_constant_velocity", cv, target, subsets)
            ca = constant_acceleration([anchor], ev.device)
            update_plans(ev.metrics, "baseline_constant_acceleration", ca, target, subsets)
            along = prior_plan([anchor], ALONG_ROUTE, ev.device)
            assert along is not None
            update_plans(ev.metrics, "baseline_constant_acceleration_along_route", along, target, subsets)
            update_plans(ev.metrics, "baseline_stationary", torch.zeros_like(target.traj), target, subsets)
        actions = [p for p in item.generated if isinstance(p, Actions)]
        if not actions:
            return
        xy = [pt for p in actions for pt in p.xy] if self.alternate else list(actions[-1].xy)
        pred = torch.zeros_like(target.traj)
        pred[0, : len(xy)] = torch.tensor(xy[: pred.shape[1]], dtype=torch.float32, device=ev.device)
        plan_mask = target.mask.clone()
        plan_mask[0, len(xy) :] = False
        update_plans(ev.metrics, self.name, pred, PlanTarget(target.traj, plan_mask, target.agents), subsets)
        ev.keep_plan_picture(self.name, anchor, np.asarray(xy), target.traj[0][target.mask[0]].cpu().numpy())
        if self.record and ev.record:
            ev.predictions["planning"][token] = pred[0].tolist()
            ev.predictions["planning_gt"][token] = {
                "traj": target.traj[0].tolist(),
                "mask": target.mask[0].int().tolist(),
                "agents": [a.tolist() for a in target.agents[0]],
            }


#: A forecast's baselines, on the same samples (``forecast_baselines``), and the metric of each.
FORECAST_BASELINES = (
    "baseline_copy_forecast",
    "baseline_copy_reconstruction_forecast",
    "baseline_cv_moved_forecast",
    "baseline_cv_moved_reconstruction_forecast",
    "baseline_prior_forecast",
    # The ceilings: what a forecast in this tokenizer's codes can reach.
    "baseline_true_future_reconstruction_forecast",
    "baseline_cv_moved_movers_reconstruction_forecast",
)
MOVABLE_IDS = torch.tensor(sorted(CLASS_NAMES.index(c) for c in MOVABLE_CLASSES))


def with_movers(moved: torch.Tensor, future: torch.Tensor) -> torch.Tensor:
    """The moved present (X, Y, Z) with its movable-class voxels cleared and the future's
    pasted in: the scene a forecast that moves every agent right and keeps the rest would
    draw."""
    out = moved.clone()
    out[torch.isin(out, MOVABLE_IDS.to(out.device))] = FREE
    agents = torch.isin(future, MOVABLE_IDS.to(future.device))
    out[agents] = future[agents].to(out.dtype)
    return out


#: Forecasts are scored on every class and on the movable ones, where forecasting shows.
forecast_metric = partial(ForecastMetric, subsets={"movable": MOVABLE_CLASSES})


def forecast_baselines(
    current: torch.Tensor,
    reconstruction: torch.Tensor,
    anchor: dict,
    steps: int = FUTURE_STEPS,
    prior: torch.Tensor | None = None,
    through: Callable[[torch.Tensor], torch.Tensor] | None = None,
    scored: list[int] | None = None,
    future: torch.Tensor | None = None,
    future_reconstruction: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """The forecasts a world model must beat, (1, steps, X, Y, Z) each, from the current
    label volume (X, Y, Z) and the scene encoder's reconstruction of it: the exact scene
    copied forward; the reconstruction copied forward (OccWorld's Copy&Paste, which no
    tokenizer error can favour); the exact scene moved by the ego's constant-velocity
    motion, everything else standing still; with ``through`` (labels (N, X, Y, Z) -> their
    reconstruction by the scene encoder), that moved scene reconstructed, at the ``scored``
    steps only (what a model given the moved present as its query and copying it scores);
    with ``prior``, the per-voxel prior of the train split at every step (no input at all).

    And the ceilings, given the ``future`` labels (steps, X, Y, Z) and ``through``: the moved
    present with the future's agents pasted in, reconstructed (a forecast that moves every
    agent right); and ``future_reconstruction``, the future through the scene encoder (a
    perfect forecast in its codes), both at the ``scored`` steps."""
    plan = constant_velocity([anchor])[0]
    moved = torch.stack([moved_scene(current, tuple(plan[t].tolist())) for t in range(steps)])
    out = {
        "baseline_copy_forecast": current[None, None].expand(1, steps, *current.shape),
        "baseline_copy_reconstruction_forecast": reconstruction[None, None].expand(1, steps, *current.shape),
        "baseline_cv_moved_forecast": moved[None],
    }
    if through is not None:
        at = list(range(steps)) if scored is None else scored
        moved_reconstruction = torch.full_like(moved, FREE)
        pasted = torch.full_like(moved, FREE)
        if at:
            # One pass through the encoder for every volume of the clip (the largest cost of a forecast's scoring).
            volumes = [moved[at]] + (
                [torch.stack([with_movers(moved[k], future[k]) for k in at])] if future is not None else []
            )
            back = through(torch.cat(volumes)).to(moved.dtype)
            moved_reconstruction[at] = back[: len(at)]
            pasted[at] = back[len(at) :] if future is not None else pasted[at]
        out["baseline_cv_moved_reconstruction_forecast"] = moved_reconstruction[None]
        if future is not None:
            out["baseline_cv_moved_movers_reconstruction_forecast"] = pasted[None]
    if future_reconstruction is not None:
        out["baseline_true_future_reconstruction_forecast"] = future_reconstruction.to(current.dtype)[None]
    if prior is not None:
        out["baseline_prior_forecast"] = prior.to(current.device, current.dtype)[None, None].expand(
            1, steps, *current.shape
        )
    return out


class ForecastScorer(BaseScorer):
    """The generated scenes, decoded by the scene encoder, against the following frames
    (``occworld`` convention, at 1 / 2 / 3 s, all classes and the movable ones), beside the
    baselines of ``forecast_baselines`` on the same samples."""

    metrics = {f"{name}_occworld": forecast_metric for name in ("forecast", *FORECAST_BASELINES)}
    needs_semantics = True

    def score(self, ev: ScoringContext, item: Item) -> None:
        scenes = [p for p in item.generated if isinstance(p, Scene)]
        if not scenes:
            return
        semantics, a = item.semantics, item.clip.anchor_index
        if semantics is None:
            raise ValueError("the forecast scorer reads the clip's label volumes (needs_semantics)")
        n = min(len(scenes), FUTURE_STEPS, semantics.shape[0] - a - 1)
        # Decoding a scene is most of a forecast's scoring: only the scored horizons (and
        # the pictures, which show them) are decoded, every frame when predictions are kept.
        forecast = ev.metric("forecast_occworld")
        assert isinstance(forecast, ForecastMetric)
        horizons = forecast.horizons
        steps = list(range(n)) if ev.record else [k for k in horizons if k < n]
        pred = torch.full((1, FUTURE_STEPS, *semantics.shape[1:]), FREE, dtype=torch.long)
        if steps:
            decoded = item.engine.decode_scenes(torch.stack([item.scenes[scenes[k].frame] for k in steps])).cpu()
            pred[0, steps] = decoded
        target = torch.full_like(pred, FREE)
        valid = torch.zeros(1, FUTURE_STEPS, dtype=torch.bool)
        target[0, :n] = semantics[a + 1 : a + 1 + n].long()
        valid[0, :n] = True
        dev = ev.device
        ev.metric("forecast_occworld").update(pred.to(dev), target.to(dev), valid.to(dev))
        current = semantics[a].long()
        engine = item.engine
        tokens = item.clip.ann["tokens"]
        reconstruction = ev.reconstructed(tokens[a], lambda: engine.decode_scenes(item.scenes[a][None])[0].cpu())

        def through(labels: torch.Tensor) -> torch.Tensor:
            return engine.decode_scenes(engine.encode_scenes(labels)).cpu()

        def through_target(k: int) -> torch.Tensor:
            return through(target[0, k][None])[0]

        scored = [k for k in horizons if k < n]
        encodes = engine.encodes_labels()
        future = None
        if encodes:  # each dataset frame through the encoder once per evaluation, whichever clip asks
            future = torch.full((FUTURE_STEPS, *semantics.shape[1:]), FREE, dtype=torch.long)
            for k in scored:
                future[k] = ev.reconstructed(tokens[a + 1 + k], partial(through_target, k))
        baselines = forecast_baselines(
            current,
            reconstruction,
            item.clip.anchor,
            prior=ev.priors.voxels() if ev.priors.data_root is not None else None,
            through=through if encodes else None,
            scored=scored,
            future=target[0] if encodes else None,
            future_reconstruction=future,
        )
        for name, volumes in baselines.items():
            ev.metric(f"{name}_occworld").update(volumes.to(dev), target.to(dev), valid.to(dev))
        token = item.clip.anchor["token"]
        ev.keep_forecast_picture(token, pred[0].numpy(), target[0].numpy(), n)
        if ev.record:
            ev.predictions["forecast"][token] = (item.clip.anchor["scene"], pred[0, :n].numpy().astype(np.uint8))


class QAScorer(BaseScorer):
    """NuScenes-QA accuracy by type and hop, beside the commonest training answer per type;
    the share of the most frequent answer string (a model stuck on one shows here)."""

    metrics = {"qa": QAMetric, "baseline_prior_qa": QAMetric}

    def __init__(self) -> None:
        self.answers: Counter = Counter()

    def score(self, ev: ScoringContext, item: Item) -> None:
        question = question_of(item.parts)
        q = next(q for q in item.clip.qa if q["question"] == question)
        answer = text_of(item.generated[0]).strip()
        self.answers[answer] += 1
        ev.metric("qa").update([answer], [q["answer"]], [q["template_type"]], [q["num_hop"]])
        prior = ev.priors.qa.get(q["template_type"], "")
        ev.metric("baseline_prior_qa").update([prior], [q["answer"]], [q["template_type"]], [q["num_hop"]])
        ev.keep_text("qa", text_of(item.parts[-2]), answer, q["answer"])
        if ev.record:
            ev.predictions["qa"][f"{item.clip.anchor['token']}|{question}"] = (q, answer)

    def summary(self, prefix: str) -> dict[str, float]:
        if not self.answers:
            return {}
        # Of this process's answers (the share is a diagnostic, not a paper metric).
        return {f"{prefix}/qa_top_answer_share": 100.0 * self.answers.most_common(1)[0][1] / sum(self.answers.values())}

    def reset(self) -> None:
        self.answers = Counter()


def last_past_meta_action(clip: Clip, cfg: MetaActionConfig | None = None) -> MetaAction | None:
    """The meta action of the frame before the clip's anchor, from the poses up to the
    anchor (what a model that saw the past could repeat); None at a scene's start."""
    poses = np.asarray(clip.ann["ego_poses"], dtype=np.float64).reshape(-1, 3)
    past = past_labels(poses, clip.anchor_index, 1, cfg or MetaActionConfig())
    return past[-1] if past else None


def said_meta_action(text: str, clip: Clip) -> MetaAction | None:
    """The meta action a generated text ends with, "as before" read as the clip's last past
    one (what a model trained with ``meta_action_prior: repeat_last`` says)."""
    return parse_meta_action(text, last_past_meta_action(clip))


class ChainOfThoughtScorer(BaseScorer):
    """A generated chain of thought that ends with the frame's meta action (from the frame
    sidecar): caption metrics against the reference narration, the meta action parsed from
    it, right or not, beside the commonest training meta action and repeating the last
    past one (labelled from the poses up to the anchor, by the rules the sidecars follow)."""

    metrics = {
        "cot_caption": CaptionMetric,
        "meta_action_acc": MeanMetric,
        "meta_parsed_fraction": MeanMetric,
        "baseline_prior_meta_action_acc": MeanMetric,
        "meta_action": MetaActionAccuracy,
        "baseline_prior_meta_action": MetaActionAccuracy,
        "baseline_repeat_last_meta_action": MetaActionAccuracy,
    }

    def __init__(self) -> None:
        self.scored = 0

    def score(self, ev: ScoringContext, item: Item) -> None:
        anchor, token = item.clip.anchor, item.clip.anchor["token"]
        text, reference = text_of(item.generated[0]), text_of(item.parts[-2])
        ev.metric("cot_caption").update([text], [[reference]], ids=[token])
        parsed = said_meta_action(text, item.clip)
        said = meta_action_words(parsed) if parsed is not None else "none"
        ev.keep_text("cot", "Task: describe the scene, then plan.", f"{text}  [parsed meta action: {said}]", reference)
        ev.metric("meta_parsed_fraction").update(100.0 * (parsed is not None))
        ev.metric("meta_action_acc").update(100.0 * (parsed == anchor["meta_action"]))
        ev.metric("meta_action").update([parsed], [anchor["meta_action"]])
        self.scored += 1
        if ev.priors.meta_action is not None:
            ev.metric("baseline_prior_meta_action_acc").update(100.0 * (ev.priors.meta_action == anchor["meta_action"]))
            ev.metric("baseline_prior_meta_action").update([ev.priors.meta_action], [anchor["meta_action"]])
        ev.metric("baseline_repeat_last_meta_action").update(
            [last_past_meta_action(item.clip)], [anchor["meta_action"]]
        )
        if ev.record:
            ev.predictions["captions"][token] = text
            ev.predictions["captions_gt"][token] = [reference]

    def summary(self, prefix: str) -> dict[str, float]:
        return {f"{prefix}/meta_action_samples": float(self.scored)} if self.scored else {}

    def reset(self) -> None:
        self.scored = 0


def plan_scorer(name: str, alternate: bool = False, record: bool = False) -> partial:
    """A factory of :class:`PlanScorer` (a task spec names factories)."""
    return partial(PlanScorer, name, alternate, record)
