"""Scoring a world model's generated answers with the papers' metrics, beside baselines."""

from __future__ import annotations

import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import torch
from torchmetrics import MeanMetric

from occtrain.data.clips import Actions, Clip, Images, Part, PlanTarget, Scene, frame_clips, plan_target
from occtrain.data.layout import DatasetIndex
from occtrain.data.meta_actions import commonest
from occtrain.data.text_formats import format_meta_action, parse_meta_action
from occtrain.engine.world_model import WorldModelEngine
from occtrain.errors import ConfigError
from occtrain.io import rank_world
from occtrain.families.occllama.tasks import TASKS
from occtrain.metrics import CaptionMetric, ForecastMetric, MetaActionAccuracy, OccupancyMetric, PlanningMetric, QAMetric, flatten_metrics
from occtrain.models.planner import constant_velocity_plan
from occtrain.occ3d import FRAME_DT, FREE, FUTURE_STEPS


@dataclass
class Priors:
    """The commonest training answers: the baselines a model must beat by learning."""

    #: NuScenes-QA template type -> its commonest answer.
    qa: dict[str, str] = field(default_factory=dict)
    #: The commonest meta action ({"speed", "direction"}), None without frame sidecars.
    meta_action: dict | None = None

    @classmethod
    def of(cls, data_root: str | Path) -> Priors:
        index = DatasetIndex.open(data_root)
        by_type: dict[str, Counter] = {}
        for q in index.questions("train") or []:
            by_type.setdefault(q["template_type"], Counter())[q["answer"]] += 1
        metas = Counter(
            (f["meta_action"]["speed"], f["meta_action"]["direction"])
            for scene in index.splits.get("train", []) if index.has_frame_annotations(scene)
            for f in index.frames(scene) if "meta_action" in f
        )
        meta = None
        if metas:
            speed, direction = metas.most_common(1)[0][0]
            meta = {"speed": speed, "direction": direction}
        return cls({t: c.most_common(1)[0][0] for t, c in by_type.items()}, meta)


def item_key(task: str, clip: Clip, parts: list[Part]) -> str:
    """What identifies one scored item: the clip's sample token, and for QA its question."""
    token = clip.anchor["token"]
    if task == "qa":
        return f"{token}|{question_of(parts)}"
    return token


def question_of(parts: list[Part]) -> str:
    """The question of a single-question QA prompt."""
    return parts[-2].text.removeprefix("Question: ").removesuffix(" Answer:")


def fixed_subset(keys: Iterable[str], size: int, seed: int = 0) -> set[str]:
    """``size`` of ``keys`` chosen by a seeded hash (the same whatever their order), or all
    of them when ``size`` is -1 or at least their number."""
    keys = sorted(set(keys))
    if size < 0 or size >= len(keys):
        return set(keys)
    return set(sorted(keys, key=lambda k: zlib.crc32(f"{seed}|{k}".encode()))[:size])


def evaluation_clips(index: DatasetIndex, split: str, task: str, context: int) -> list[Clip]:
    """The clips ``task`` is scored on, from the dataset index (no shards, no occupancy):
    for QA a clip at every frame of the split (a shorter history at a scene's start); for
    the others every frame with ``context`` history frames and a whole 3 s future."""
    if task == "qa":
        return [c for c in frame_clips(index, split, context) if c.qa]
    return list(frame_clips(index, split, context, FUTURE_STEPS, partial_history=False))


#: Dashboard samples kept per validation: texts per task (chains of thought are long),
#: pictures per kind.
TEXTS_PER_TASK = {"qa": 4, "cot": 2, "meta_action": 2}
PICTURES_PER_KIND = 1


class Evaluator(torch.nn.Module):
    """Rolls out the answers of the evaluation tasks and scores them with the papers' metrics.

    Planning is scored three ways, OccLLaMA's M0-M3 comparison: ``plan_direct`` (the
    planning task's trajectory), ``plan_alternate`` (the waypoints of the forecasting
    rollout, alternating with generated scenes) and ``plan_cot`` (after the chain of thought).
    """

    TASKS = ("forecasting", "planning", "qa", "cot_planning", "meta_action")

    def __init__(
        self, tasks: Iterable[str], record: bool = False, priors: Priors | None = None,
        subset: dict[str, set[str]] | None = None,
    ):
        """``tasks``: the evaluation tasks to run (those of :attr:`TASKS` that are named);
        their prompts are built with the engine's own task settings. Every item is scored
        (every question of a frame for QA) unless ``subset`` names, per task, the item
        keys (``item_key``) to score."""
        super().__init__()
        unknown = sorted(set(tasks) - set(self.TASKS))
        if unknown:
            kind = "a task without a generated answer to score" if unknown[0] in TASKS else "an unknown task"
            raise ConfigError(f"'{unknown[0]}' is {kind}; the evaluator scores {', '.join(self.TASKS)}")
        self.tasks = tuple(t for t in self.TASKS if t in set(tasks))
        #: Baselines scored on the same samples: copy the current scene forward, stand still,
        #: drive on at constant velocity, answer the commonest training answer of the type.
        self.priors = priors or Priors()
        self.subset = subset
        self.metrics = torch.nn.ModuleDict({
            "forecast_occworld": ForecastMetric(),
            "baseline_copy_forecast_occworld": ForecastMetric(),
            "baseline_constant_velocity": PlanningMetric(),
            "baseline_stationary": PlanningMetric(),
            "baseline_prior_qa": QAMetric(),
            "plan_direct": PlanningMetric(),
            "plan_alternate": PlanningMetric(),
            "plan_cot": PlanningMetric(),
            "qa": QAMetric(),
            "cot_caption": CaptionMetric(),
            "meta_action_acc": MeanMetric(),
            "meta_parsed_fraction": MeanMetric(),
            "baseline_prior_meta_action_acc": MeanMetric(),
            # Speed / direction / mean / overall (OccVLA's split), for both chain-of-thought tasks.
            "meta_action": MetaActionAccuracy(),
            "baseline_prior_meta_action": MetaActionAccuracy(),
            # OccVLA's query branch, when the stage trains it.
            "occupancy_occ3d": OccupancyMetric("occ3d"),
            "occupancy_occworld": OccupancyMetric("occworld"),
        })
        self._meta_prior: dict[tuple, dict | None] = {}
        self._clip_cache: dict[tuple, list[Clip]] = {}
        self._baselined: set[str] = set()  # clips whose plan baselines are scored
        #: How often each QA answer string was generated (a model stuck on one shows here).
        self.answers: Counter = Counter()
        self.texts: list[dict] = []
        #: A few pictures for the dashboard: (caption, [(label, semantics, trajectories)]).
        self.scenes: list[tuple[str, list[tuple]]] = []
        self._index: DatasetIndex | None = None  # set by run(): anchor scenes for the pictures
        #: With ``record``, every prediction in the formats ``occtrain score`` reads.
        self.record = record
        self.predictions: dict[str, dict] = {"planning": {}, "planning_gt": {}, "forecast": {}, "qa": {}, "captions": {}, "captions_gt": {}}

    @torch.no_grad()
    def update(self, engine: WorldModelEngine, clips: list[Clip], batch: dict, tasks: Iterable[str] | None = None) -> None:
        """Generate and score the evaluator's tasks (or those of ``tasks``) on ``clips``."""
        tasks = self.tasks if tasks is None else [t for t in self.tasks if t in set(tasks)]
        # The planning ground truth of each clip, built once for every plan scored on it.
        targets = [plan_target([c.anchor], self.device) for c in clips]
        planned: set[int] = set()
        for task in tasks:
            for b, parts, generated, codes in engine.rollouts(task, clips, batch, every=True, select=self._selector(task)):
                semantics = batch["semantics"][b] if task == "forecasting" else None
                self._score(engine, task, clips[b], parts, generated, codes, semantics, targets[b])
                if task in ("planning", "forecasting", "cot_planning"):
                    planned.add(b)
        for b in sorted(planned):  # baselines once on each clip a plan was scored on
            token = clips[b].anchor["token"]
            if token not in self._baselined:
                self._baselined.add(token)
                self._score_plan_baselines(clips[b].anchor, targets[b])

    def _selector(self, task: str):
        if self.subset is None:
            return None
        keys = self.subset.get(task, set())
        return lambda clip, parts: item_key(task, clip, parts) in keys

    def run(
        self, engine: WorldModelEngine, data_root: str | Path, split: str, batch_size: int = 16,
        samples: int = -1, seed: int = 0, advance: Callable[[int], None] | None = None,
    ) -> None:
        """Generate and score every task on ``split`` (clips from ``evaluation_clips``):
        every item, or with ``samples`` >= 0 a fixed seeded subset of that many items per
        task (the same at every call). Under DDP each process takes every world-th clip
        (no clip twice: no padding duplicates); metrics sum across processes. Each run
        starts afresh: ``compute``, the texts and the pictures then describe this run."""
        self.reset()
        index = DatasetIndex.open(data_root)
        self._index = index
        engine.prepare_inputs(data_root)  # a vision-language world model's camera tokens (in memory)
        rank, world = rank_world()
        for task in self.tasks:
            clips = self._task_clips(engine, index, split, task, samples, seed)[rank::world]
            for i in range(0, len(clips), batch_size):
                chunk = clips[i : i + batch_size]
                self.update(engine, chunk, self._batch(engine, index, chunk, task), tasks=[task])
                if advance is not None:
                    advance(len(chunk))
        if self.tasks and self.scores_occupancy(engine):
            clips = self._task_clips(engine, index, split, self.tasks[0], samples, seed)[rank::world]
            self.score_occupancy(engine, clips)
            if advance is not None:
                advance(len(clips))

    @staticmethod
    def scores_occupancy(engine: WorldModelEngine) -> bool:
        """Whether the world model has an occupancy query branch that its tasks train."""
        return hasattr(engine.world, "predict_occupancy") and engine.tasks.occupancy_weight > 0

    def _task_clips(self, engine, index, split, task, samples, seed) -> list[Clip]:
        key = (split, task, samples, seed, engine.tasks.context_frames)
        if key not in self._clip_cache:
            clips = evaluation_clips(index, split, task, engine.tasks.context_frames)
            if samples >= 0:
                keys = {c.anchor["token"]: [item_key(task, c, p) for p in engine.task_items(task, c, every=True)] for c in clips}
                chosen = fixed_subset([k for ks in keys.values() for k in ks], samples, seed)
                self.subset = {**(self.subset or {}), task: chosen}
                clips = [c for c in clips if chosen.intersection(keys[c.anchor["token"]])]
            self._clip_cache[key] = clips
        return self._clip_cache[key]

    @staticmethod
    def _batch(engine: WorldModelEngine, index: DatasetIndex, clips: list[Clip], task: str) -> dict:
        """What ``update`` reads besides the clips: the annotations, and the clips' occupancy
        when scenes must be encoded (no code cache) or forecasts scored."""
        batch: dict = {"ann": [c.ann for c in clips]}
        # A vision-language model's prompts hold no scenes: it reads no occupancy here.
        if (engine.code_cache is None and engine.vision is None) or task == "forecasting":
            # One (T, X, Y, Z) tensor per clip: QA clips at a scene's start have shorter windows.
            batch["semantics"] = [
                torch.from_numpy(np.stack([index.labels(index.scene_of(t), t)["semantics"] for t in c.ann["tokens"]])) for c in clips
            ]
        return batch

    def total(self, engine: WorldModelEngine, data_root: str | Path, split: str, samples: int = -1, seed: int = 0) -> int:
        """How many clips ``run`` visits (for a progress bar)."""
        index = DatasetIndex.open(data_root)
        rank, world = rank_world()
        total = sum(len(self._task_clips(engine, index, split, t, samples, seed)[rank::world]) for t in self.tasks)
        if self.tasks and self.scores_occupancy(engine):
            total += len(self._task_clips(engine, index, split, self.tasks[0], samples, seed)[rank::world])
        return total

    @classmethod
    def scorable(cls, weights: dict[str, float]) -> list[str]:
        """The tasks of a stage's task weights that have a generated answer to score."""
        return [t for t in cls.TASKS if weights.get(t, 0) > 0]

    @property
    def device(self) -> torch.device:
        return self.metrics["plan_direct"].device  # metrics follow the module onto the accelerator

    def _score_plan_baselines(self, anchor: dict, target: PlanTarget) -> None:
        """Standing still and constant velocity, on every clip a plan is scored on."""
        speed = torch.tensor([float(anchor.get("ego_speed", 0.0))], device=self.device)
        self.metrics["baseline_constant_velocity"].update(constant_velocity_plan(speed, FUTURE_STEPS), target.traj, target.mask, target.agents)
        self.metrics["baseline_stationary"].update(torch.zeros_like(target.traj), target.traj, target.mask, target.agents)

    def _score(self, engine, task, clip, parts, generated, codes, semantics, plan: PlanTarget) -> None:
        anchor, token = clip.anchor, clip.anchor["token"]
        dev = self.device
        gt_xy, gt_mask, agents = plan.traj, plan.mask, plan.agents
        actions = [p for p in generated if isinstance(p, Actions)]
        if task in ("planning", "forecasting", "cot_planning") and actions:
            # The forecasting rollout yields one waypoint per scene; together they are its plan.
            xy = [pt for p in actions for pt in p.xy] if task == "forecasting" else list(actions[-1].xy)
            pred = torch.zeros_like(gt_xy)
            pred[0, : len(xy)] = torch.tensor(xy[: pred.shape[1]], dtype=torch.float32, device=dev)
            plan_mask = gt_mask.clone()
            plan_mask[0, len(xy):] = False
            name = {"planning": "plan_direct", "forecasting": "plan_alternate", "cot_planning": "plan_cot"}[task]
            self.metrics[name].update(pred, gt_xy, plan_mask, agents)
            self._keep_plan_picture(name, anchor, np.asarray(xy), gt_xy[0][gt_mask[0]].cpu().numpy())
            if self.record and task == "planning":
                self.predictions["planning"][token] = pred[0].tolist()
                self.predictions["planning_gt"][token] = {
                    "traj": gt_xy[0].tolist(), "mask": gt_mask[0].int().tolist(), "agents": [a.tolist() for a in agents[0]],
                }
        if task == "forecasting":
            scenes = [p for p in generated if isinstance(p, Scene)]
            decoded = engine.decode_scenes(torch.stack([codes[p.frame] for p in scenes])).cpu()
            a = clip.anchor_index
            steps = FUTURE_STEPS
            pred = torch.full((1, steps, *decoded.shape[1:]), FREE, dtype=torch.long)
            target = torch.full_like(pred, FREE)
            valid = torch.zeros(1, steps, dtype=torch.bool)
            n = min(len(scenes), steps, semantics.shape[0] - a - 1)
            pred[0, :n] = decoded[:n]
            target[0, :n] = semantics[a + 1 : a + 1 + n].long()
            valid[0, :n] = True
            self.metrics["forecast_occworld"].update(pred.to(dev), target.to(dev), valid.to(dev))
            copy = semantics[a].long()[None, None].expand_as(pred)
            self.metrics["baseline_copy_forecast_occworld"].update(copy.to(dev), target.to(dev), valid.to(dev))
            self._keep_forecast_picture(token, pred[0].numpy(), target[0].numpy(), n)
            if self.record:
                self.predictions["forecast"][token] = (anchor["scene"], decoded[:n].numpy().astype(np.uint8))
        if task == "qa":
            question = question_of(parts)
            q = next(q for q in clip.qa if q["question"] == question)
            answer = generated[0].text.strip()
            self.answers[answer] += 1
            self.metrics["qa"].update([answer], [q["answer"]], [q["template_type"]], [q["num_hop"]])
            prior = self.priors.qa.get(q["template_type"], "")
            self.metrics["baseline_prior_qa"].update([prior], [q["answer"]], [q["template_type"]], [q["num_hop"]])
            self._keep_text("qa", parts[-2].text, answer, q["answer"])
            if self.record:
                self.predictions["qa"][f"{token}|{question}"] = (q, answer)
        if task == "meta_action":
            self._score_meta_action(engine, clip, parts, generated)
        if task == "cot_planning":
            text, reference = generated[0].text, parts[-2].text
            self.metrics["cot_caption"].update([text], [[reference]], ids=[token])
            parsed = parse_meta_action(text)
            said = format_meta_action(parsed).removeprefix("Meta action: ") if parsed is not None else "none"
            self._keep_text("cot", "Task: describe the scene, then plan.", f"{text}  [parsed meta action: {said}]", reference)
            self.metrics["meta_parsed_fraction"].update(100.0 * (parsed is not None))
            self.metrics["meta_action_acc"].update(100.0 * (parsed == anchor["meta_action"]))
            self.metrics["meta_action"].update([parsed], [anchor["meta_action"]])
            if self.priors.meta_action is not None:
                self.metrics["baseline_prior_meta_action_acc"].update(100.0 * (self.priors.meta_action == anchor["meta_action"]))
                self.metrics["baseline_prior_meta_action"].update([self.priors.meta_action], [anchor["meta_action"]])
            if self.record:
                self.predictions["captions"][token] = text
                self.predictions["captions_gt"][token] = [reference]

    def _score_meta_action(self, engine: WorldModelEngine, clip: Clip, parts: list[Part], generated: list[Part]) -> None:
        """OccVLA's chain of thought: the meta action it ends with against the one the
        prompt's answer holds (labelled from the poses), beside the commonest training one."""
        text, reference = generated[0].text, parts[-1].text
        truth = parse_meta_action(reference)
        parsed = parse_meta_action(text)
        self.metrics["meta_action"].update([parsed], [truth])
        self.metrics["meta_parsed_fraction"].update(100.0 * (parsed is not None))
        cfg = engine.tasks.meta_actions
        key = tuple(sorted(vars(cfg).items()))
        if key not in self._meta_prior and self._index is not None:
            self._meta_prior[key] = commonest(self._index, "train", cfg)
        prior = self._meta_prior.get(key)
        if prior is not None:
            self.metrics["baseline_prior_meta_action"].update([prior], [truth])
        said = format_meta_action(parsed).removeprefix("Meta action: ") if parsed is not None else "none"
        self._keep_text("meta_action", parts[-2].text, f"{text}  [parsed: {said}]", reference)

    @torch.no_grad()
    def score_occupancy(self, engine: WorldModelEngine, clips: list[Clip]) -> None:
        """The occupancy query branch (OccVLA) on each clip's anchor: one forward of the
        images and the queries, decoded, scored in both conventions."""
        index = self._index
        for clip in clips:
            token = clip.anchor["token"]
            prefix = engine.encode_parts([Images(token)], {})
            pred = engine.world.predict_occupancy(prefix).argmax(1).cpu()
            labels = index.labels(index.scene_of(token), token)
            target = torch.from_numpy(labels["semantics"]).long()[None]
            mask = torch.from_numpy(labels["mask_camera"].astype(bool))[None]
            self.metrics["occupancy_occ3d"].update(pred.to(self.device), target.to(self.device), mask.to(self.device))
            self.metrics["occupancy_occworld"].update(pred.to(self.device), target.to(self.device))
            if not any(c.startswith("occupancy") for c, _ in self.scenes):
                self.scenes.append((f"occupancy from the queries, sample {token[:8]}: truth and prediction", [("truth", target[0].numpy()), ("queries", pred[0].numpy())]))

    def _keep_text(self, task: str, prompt: str, prediction: str, reference: str) -> None:
        if sum(t["task"] == task for t in self.texts) < TEXTS_PER_TASK.get(task, 2):
            self.texts.append({"task": task, "prompt": prompt, "prediction": prediction, "reference": reference})

    def _keep_forecast_picture(self, token: str, pred: np.ndarray, target: np.ndarray, n: int) -> None:
        """Ground truth above the forecast at 1, 2 and 3 s (future steps 2, 4, 6)."""
        if sum(c.startswith("forecast") for c, _ in self.scenes) >= PICTURES_PER_KIND:
            return
        steps = [k for k in (1, 3, 5) if k < n]
        rows = [(f"truth {(k + 1) * FRAME_DT:g} s", target[k]) for k in steps]
        rows += [(f"forecast {(k + 1) * FRAME_DT:g} s", pred[k]) for k in steps]
        self.scenes.append((f"forecast of sample {token[:8]}: truth (left) and forecast (right) at 1, 2, 3 s", rows))

    def _keep_plan_picture(self, name: str, anchor: dict, plan: np.ndarray, truth: np.ndarray) -> None:
        """The plan (red) beside the true future (green) on the anchor's bird's-eye view."""
        if self._index is None or sum(c.startswith(name) for c, _ in self.scenes) >= PICTURES_PER_KIND:
            return
        token = anchor["token"]
        semantics = self._index.labels(self._index.scene_of(token), token)["semantics"]
        self.scenes.append((f"{name} of sample {token[:8]}: true future green, plan red", [("plan vs truth", semantics, {"truth": truth, "plan": plan})]))

    def compute(self, prefix: str) -> dict[str, float]:
        """Every metric that saw samples, flattened under ``prefix`` (e.g. ``val/qa_overall``)."""
        out: dict[str, float] = {}
        for name, metric in self.metrics.items():
            if metric.update_count:
                value = metric.compute()
                if isinstance(value, dict):
                    out.update(flatten_metrics(f"{prefix}/{name}", value))
                else:  # a plain mean (meta-action accuracy and parse rate)
                    out[f"{prefix}/{name}"] = float(value)
        if self.metrics["meta_action_acc"].update_count:
            out[f"{prefix}/meta_action_samples"] = float(self.metrics["meta_action_acc"].update_count)
        if self.answers:
            # Of this process's answers (the share is a diagnostic, not a paper metric).
            out[f"{prefix}/qa_top_answer_share"] = 100.0 * self.answers.most_common(1)[0][1] / sum(self.answers.values())
        return out

    def reset(self) -> None:
        for metric in self.metrics.values():
            metric.reset()
        self.answers = Counter()
        self._baselined = set()
        self.scenes = []
        self.texts = []
