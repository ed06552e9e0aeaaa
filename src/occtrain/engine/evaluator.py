"""Scoring a world model's generated answers with the papers' metrics, beside baselines."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Iterable

import numpy as np
import torch

from occtrain.data.clips import Actions, Clip, PlanTarget, Scene, plan_target
from occtrain.data.layout import DatasetIndex
from occtrain.data.text_formats import parse_meta_action
from occtrain.engine.world_model import WorldModelEngine
from occtrain.errors import ConfigError
from occtrain.families.occllama.tasks import TASKS
from occtrain.metrics import CaptionMetric, ForecastMetric, PlanningMetric, QAMetric, flatten_metrics
from occtrain.models.planner import constant_velocity_plan
from occtrain.occ3d import FREE, FUTURE_STEPS


def qa_prior(data_root: str | Path) -> dict[str, str]:
    """The commonest training answer of each NuScenes-QA template type (the QA baseline)."""
    questions = DatasetIndex.open(data_root).questions("train") or []
    by_type: dict[str, Counter] = {}
    for q in questions:
        by_type.setdefault(q["template_type"], Counter())[q["answer"]] += 1
    return {t: c.most_common(1)[0][0] for t, c in by_type.items()}


class Evaluator(torch.nn.Module):
    """Rolls out the answers of the evaluation tasks and scores them with the papers' metrics.

    Planning is scored three ways, OccLLaMA's M0-M3 comparison: ``plan_direct`` (the
    planning task's trajectory), ``plan_alternate`` (the waypoints of the forecasting
    rollout, alternating with generated scenes) and ``plan_cot`` (after the chain of thought).
    """

    TASKS = ("forecasting", "planning", "qa", "cot_planning")

    def __init__(self, tasks: Iterable[str], record: bool = False, qa_prior: dict[str, str] | None = None):
        """``tasks``: the evaluation tasks to run (those of :attr:`TASKS` that are named);
        their prompts are built with the engine's own task settings."""
        super().__init__()
        unknown = sorted(set(tasks) - set(self.TASKS))
        if unknown:
            kind = "a task without a generated answer to score" if unknown[0] in TASKS else "an unknown task"
            raise ConfigError(f"'{unknown[0]}' is {kind}; the evaluator scores {', '.join(self.TASKS)}")
        self.tasks = tuple(t for t in self.TASKS if t in set(tasks))
        #: Baselines scored on the same samples: copy the current scene forward, stand still,
        #: drive on at constant velocity, answer the commonest training answer of the type.
        self.qa_prior = qa_prior or {}
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
        })
        self.meta_hits = 0
        self.meta_total = 0
        self.texts: list[dict] = []
        #: With ``record``, every prediction in the formats ``occtrain score`` reads.
        self.record = record
        self.predictions: dict[str, dict] = {"planning": {}, "planning_gt": {}, "forecast": {}, "qa": {}, "captions": {}, "captions_gt": {}}

    @torch.no_grad()
    def update(self, engine: WorldModelEngine, clips: list[Clip], batch: dict) -> None:
        # The planning ground truth of each clip, built once for every plan scored on it.
        targets = [plan_target([c.anchor], self.device) for c in clips]
        for task in self.tasks:
            for b, parts, generated, codes in engine.rollouts(task, clips, batch):
                self._score(engine, task, clips[b], parts, generated, codes, batch["semantics"][b], targets[b])
        if any(t in self.tasks for t in ("planning", "forecasting", "cot_planning")):
            for clip, target in zip(clips, targets):
                self._score_plan_baselines(clip.anchor, target)

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
            if self.record:
                self.predictions["forecast"][token] = (anchor["scene"], decoded[:n].numpy().astype(np.uint8))
        if task == "qa":
            question = parts[-2].text.removeprefix("Question: ").removesuffix(" Answer:")
            q = next(q for q in clip.qa if q["question"] == question)
            answer = generated[0].text.strip()
            self.metrics["qa"].update([answer], [q["answer"]], [q["template_type"]], [q["num_hop"]])
            prior = self.qa_prior.get(q["template_type"], "")
            self.metrics["baseline_prior_qa"].update([prior], [q["answer"]], [q["template_type"]], [q["num_hop"]])
            self._keep_text("qa", parts[-2].text, answer, q["answer"])
            if self.record:
                self.predictions["qa"][f"{token}|{question}"] = (q, answer)
        if task == "cot_planning":
            text, reference = generated[0].text, parts[-2].text
            self.metrics["cot_caption"].update([text], [[reference]], ids=[token])
            self._keep_text("cot", "Task: describe the scene, then plan.", text, reference)
            self.meta_total += 1
            self.meta_hits += int(parse_meta_action(text) == anchor["meta_action"])
            if self.record:
                self.predictions["captions"][token] = text
                self.predictions["captions_gt"][token] = [reference]

    def _keep_text(self, task: str, prompt: str, prediction: str, reference: str) -> None:
        if len(self.texts) < 12:
            self.texts.append({"task": task, "prompt": prompt, "prediction": prediction, "reference": reference})

    def compute(self, prefix: str) -> dict[str, float]:
        """Every metric that saw samples, flattened under ``prefix`` (e.g. ``val/qa_overall``)."""
        out: dict[str, float] = {}
        for name, metric in self.metrics.items():
            if metric.update_count:
                out.update(flatten_metrics(f"{prefix}/{name}", metric.compute()))
        if self.meta_total:
            out[f"{prefix}/meta_action_acc"] = 100.0 * self.meta_hits / self.meta_total
        return out

    def reset(self) -> None:
        for metric in self.metrics.values():
            metric.reset()
        self.meta_hits = self.meta_total = 0
        self.texts = []  # the dashboard shows the last validation's outputs, as the metrics do
