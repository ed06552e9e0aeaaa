"""Scoring a world model's generated answers with the papers' metrics, beside baselines.

The evaluator knows no task: a family's :class:`~occtrain.core.shared_tasks.TaskSpec` names the
scorers of each task it grades, and its evaluation hooks score what belongs to no task.
The evaluator picks the clips, rolls the answers out through the engine, hands each item
to its task's scorers and keeps a few texts and pictures for the dashboard.
"""

from __future__ import annotations

import zlib
from collections import defaultdict
from collections.abc import Callable, Hashable, Iterable
from pathlib import Path

import numpy as np
import torch
from torchmetrics import Metric

from occtrain.core.protocols import FUTURE_CLIPS, EvalHook
from occtrain.core.registry import scorer_factories
from occtrain.core.scorers import Item, Priors
from occtrain.core.shared_tasks import TaskSpec, question_of
from occtrain.data.clips import Clip, Part, frame_clips, plan_target
from occtrain.data.layout import DatasetIndex
from occtrain.engine.world_engine import WorldModelEngine
from occtrain.errors import ConfigError
from occtrain.formats.metrics_file import SampleSet, digest_items
from occtrain.formats.occ3d import FRAME_DT, FUTURE_STEPS
from occtrain.metrics import compute_metrics
from occtrain.metrics.captions import CaptionMetric, start_meteor
from occtrain.ranks import rank_world

__all__ = ["Evaluator", "Priors", "evaluation_clips", "fixed_subset", "item_key", "scorable"]


def item_key(task: str, clip: Clip, parts: list[Part]) -> str:
    """What identifies one scored item: the clip's sample token, and for QA its question."""
    token = clip.anchor["token"]
    if task == "qa":
        return f"{token}|{question_of(parts)}"
    return token


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


def scorable(tasks: dict[str, TaskSpec], weights: dict[str, float] | None = None) -> list[str]:
    """The tasks with a scorer (of ``weights``, when given: those with a positive weight)."""
    return [t for t, spec in tasks.items() if scorer_factories(spec) and (weights is None or weights.get(t, 0) > 0)]


#: What a hook sets ``clips`` to for every frame with a whole 3 s future (not the first task's clips).

#: Dashboard samples kept per validation: texts per task (chains of thought are long),
#: pictures per kind.
TEXTS_PER_TASK = {"qa": 4, "cot": 2, "meta_action": 2}
PICTURES_PER_KIND = 1


class Evaluator(torch.nn.Module):
    """Rolls out the answers of the evaluation tasks and scores them (see the module docstring)."""

    def __init__(
        self,
        tasks: Iterable[str],
        family_tasks: dict[str, TaskSpec],
        record: bool = False,
        priors: Priors | None = None,
        subset: dict[str, set[str]] | None = None,
        hooks: Iterable[type] = (),
    ):
        """``tasks``: the evaluation tasks to run, of ``family_tasks`` (the world model's
        family's); their prompts are built with the engine's own task settings. Every item
        is scored (every question of a frame for QA) unless ``subset`` names, per task, the
        item keys (``item_key``) to score. ``hooks``: the family's evaluation hooks."""
        super().__init__()
        tasks = list(tasks)
        can = scorable(family_tasks)
        for name in tasks:
            if name not in family_tasks:
                raise ConfigError(f"'{name}' is an unknown task; the world model's tasks are {', '.join(family_tasks)}")
            if name not in can:
                raise ConfigError(
                    f"'{name}' is a task without a generated answer to score; the evaluator scores {', '.join(can)}"
                )
        self.tasks = tuple(t for t in can if t in set(tasks))
        self.scorers = {t: [make() for make in scorer_factories(family_tasks[t])] for t in self.tasks}
        self.hooks = [make() for make in hooks]
        metrics: dict[str, torch.nn.Module] = {}
        for scorer in [s for ss in self.scorers.values() for s in ss] + self.hooks:
            for name, make in scorer.metrics.items():
                if name not in metrics:
                    metrics[name] = make()
        self.metrics = torch.nn.ModuleDict(metrics)
        #: The baselines a model must beat: the commonest training answers.
        self.priors = priors or Priors()
        self.subset = subset
        #: Per task (and ``FUTURE_CLIPS`` for the hooks on every future frame): [items
        #: scored, items the split holds] of the last ``run`` (a metrics file's provenance).
        self.coverage: dict[str, list[int]] = {}
        #: Per task (and ``FUTURE_CLIPS``): the keys of the items it scored, and of every
        #: item the split holds for it: which numbers were scored on the same items.
        self.items: dict[str, set[str]] = {}
        self.universe: dict[str, set[str]] = {}
        self.sample_sets: list[SampleSet] = []
        self._clip_cache: dict[tuple, list[Clip]] = {}
        self._once: set = set()
        self._reconstructed: dict[str, torch.Tensor] = {}
        self.texts: list[dict] = []
        #: A few pictures for the dashboard: (caption, [(label, semantics, trajectories)]).
        self.scenes: list[tuple[str, list[tuple]]] = []
        self.index: DatasetIndex | None = None  # set by run(): anchor scenes for the pictures
        #: With ``record``, every prediction by kind (the scorers name the kinds;
        #: ``evaluate.write_predictions`` writes those ``occtrain score`` reads).
        self.record = record
        self.predictions: dict[str, dict] = defaultdict(dict)

    # -- what scorers call
    @property
    def device(self) -> torch.device:
        for metric in self.metrics.values():
            if isinstance(metric, Metric):
                return metric.device
        return torch.device("cpu")

    def metric(self, name: str) -> Metric:
        """The metric a scorer or hook declared as ``name``."""
        metric = self.metrics[name]
        assert isinstance(metric, Metric), name  # every declared factory makes a torchmetrics Metric
        return metric

    def once(self, key: Hashable) -> bool:
        """True the first time ``key`` is asked about in this run (e.g. a baseline per clip)."""
        if key in self._once:
            return False
        self._once.add(key)
        return True

    def reconstructed(self, token: str, make: Callable[[], torch.Tensor]) -> torch.Tensor:
        """Dataset frame ``token``'s labels through the scene encoder, made once per run by
        ``make`` whichever clip asks (a frame is the future of six clips and the present of one)."""
        if token not in self._reconstructed:
            self._reconstructed[token] = make()
        return self._reconstructed[token]

    def keep_text(self, task: str, prompt: str, prediction: str, reference: str) -> None:
        if sum(t["task"] == task for t in self.texts) < TEXTS_PER_TASK.get(task, 2):
            self.texts.append({"task": task, "prompt": prompt, "prediction": prediction, "reference": reference})

    def keep_scene(self, kind: str, caption: str, panels: list[tuple]) -> None:
        """A picture for the dashboard, ``PICTURES_PER_KIND`` per kind (the caption starts with it)."""
        if sum(c.startswith(kind) for c, _ in self.scenes) < PICTURES_PER_KIND:
            self.scenes.append((caption, panels))

    def keep_forecast_picture(self, token: str, pred: np.ndarray, target: np.ndarray, n: int) -> None:
        """Ground truth above the forecast at 1, 2 and 3 s (future steps 2, 4, 6)."""
        steps = [k for k in (1, 3, 5) if k < n]
        rows = [(f"truth {(k + 1) * FRAME_DT:g} s", target[k]) for k in steps]
        rows += [(f"forecast {(k + 1) * FRAME_DT:g} s", pred[k]) for k in steps]
        self.keep_scene(
            "forecast", f"forecast of sample {token[:8]}: truth (left) and forecast (right) at 1, 2, 3 s", rows
        )

    def keep_plan_picture(self, name: str, anchor: dict, plan: np.ndarray, truth: np.ndarray) -> None:
        """The plan (red) beside the true future (green) on the anchor's bird's-eye view."""
        if self.index is None or sum(c.startswith(name) for c, _ in self.scenes) >= PICTURES_PER_KIND:
            return
        token = anchor["token"]
        semantics = self.index.labels(self.index.scene_of(token), token)["semantics"]
        self.keep_scene(
            name,
            f"{name} of sample {token[:8]}: true future green, plan red",
            [("plan vs truth", semantics, {"truth": truth, "plan": plan})],
        )

    # -- running
    @torch.no_grad()
    def update(
        self, engine: WorldModelEngine, clips: list[Clip], batch: dict, tasks: Iterable[str] | None = None
    ) -> None:
        """Generate and score the evaluator's tasks (or those of ``tasks``) on ``clips``."""
        tasks = self.tasks if tasks is None else [t for t in self.tasks if t in set(tasks)]
        # The planning ground truth of each clip, built once for every plan scored on it.
        targets = [plan_target([c.anchor], self.device) for c in clips]
        for task in tasks:
            for b, parts, generated, scenes in engine.rollouts(
                task, clips, batch, every=True, select=self._selector(task)
            ):
                semantics = batch["semantics"][b] if "semantics" in batch else None
                item = Item(task, clips[b], parts, generated, scenes, semantics, targets[b], engine)
                for scorer in self.scorers[task]:
                    scorer.score(self, item)

    def _selector(self, task: str) -> Callable[[Clip, list[Part]], bool] | None:
        if self.subset is None:
            return None
        keys = self.subset.get(task, set())
        return lambda clip, parts: item_key(task, clip, parts) in keys

    def run(
        self,
        engine: WorldModelEngine,
        data_root: str | Path,
        split: str,
        batch_size: int = 16,
        samples: int = -1,
        seed: int = 0,
        advance: Callable[[int], None] | None = None,
    ) -> None:
        """Generate and score every task on ``split`` (clips from ``evaluation_clips``):
        every item, or with ``samples`` >= 0 a fixed seeded subset of that many items per
        task (the same at every call). Under DDP each process takes every world-th clip
        (no clip twice: no padding duplicates); metrics sum across processes. Each run
        starts afresh: ``compute``, the texts and the pictures then describe this run."""
        self.reset()
        if any(isinstance(m, CaptionMetric) for m in self.metrics.values()):
            start_meteor()  # its Java program loads while the captions are generated
        index = DatasetIndex.open(data_root)
        self.index = index
        engine.prepare_inputs(data_root)  # what a world model reads through a frozen encoder (in memory)
        rank, world = rank_world()
        for task in self.tasks:
            clips = self._task_clips(engine, index, split, task, samples, seed)[rank::world]
            for i in range(0, len(clips), batch_size):
                chunk = clips[i : i + batch_size]
                self.update(engine, chunk, self._batch(engine, index, chunk, task), tasks=[task])
                if advance is not None:
                    advance(len(chunk))
        for hook in self._hooks(engine):
            clips = self._hook_clips(engine, index, split, hook, samples, seed)[rank::world]
            hook.run(self, engine, clips)
            if advance is not None:
                advance(len(clips))

    def _hooks(self, engine: WorldModelEngine) -> list[EvalHook]:
        """The hooks that run: those that apply, and that have clips (a hook on the first
        task's clips runs only beside a task)."""
        return [h for h in self.hooks if h.applies(engine) and (self.tasks or h.clips == FUTURE_CLIPS)]

    def _hook_clips(
        self, engine: WorldModelEngine, index: DatasetIndex, split: str, hook: EvalHook, samples: int, seed: int
    ) -> list[Clip]:
        """A hook's clips: with ``clips = "future"`` every frame with a whole 3 s future (a
        fixed subset of ``samples`` of them), else the first evaluated task's."""
        if hook.clips != FUTURE_CLIPS:
            return self._task_clips(engine, index, split, self.tasks[0], samples, seed)
        key = (split, FUTURE_CLIPS, samples, seed, engine.tasks.context_frames)
        if key not in self._clip_cache:
            clips = evaluation_clips(index, split, FUTURE_CLIPS, engine.tasks.context_frames)
            chosen = fixed_subset([c.anchor["token"] for c in clips], samples, seed)
            self._clip_cache[key] = [c for c in clips if c.anchor["token"] in chosen]
            self.coverage[FUTURE_CLIPS] = [len(chosen), len(clips)]
            self.items[FUTURE_CLIPS], self.universe[FUTURE_CLIPS] = chosen, {c.anchor["token"] for c in clips}
        return self._clip_cache[key]

    def _task_clips(
        self, engine: WorldModelEngine, index: DatasetIndex, split: str, task: str, samples: int, seed: int
    ) -> list[Clip]:
        key = (split, task, samples, seed, engine.tasks.context_frames)
        if key not in self._clip_cache:
            clips = evaluation_clips(index, split, task, engine.tasks.context_frames)
            # Every item is keyed, subset or not: the provenance counts how many of them are scored.
            keys = {
                c.anchor["token"]: [item_key(task, c, p) for p in engine.task_items(task, c, every=True)] for c in clips
            }
            every = [k for ks in keys.values() for k in ks]
            chosen = set(every) if self.subset is None or task not in self.subset else self.subset[task]
            if samples >= 0:
                chosen = fixed_subset(every, samples, seed)
                self.subset = {**(self.subset or {}), task: chosen}
                clips = [c for c in clips if chosen.intersection(keys[c.anchor["token"]])]
            self.coverage[task] = [len(chosen.intersection(every)), len(set(every))]
            self.items[task], self.universe[task] = chosen.intersection(every), set(every)
            self._clip_cache[key] = clips
        return self._clip_cache[key]

    def _batch(self, engine: WorldModelEngine, index: DatasetIndex, clips: list[Clip], task: str) -> dict:
        """What ``update`` reads besides the clips: the annotations, and the clips' label
        volumes when scenes must be encoded (no cache) or a scorer reads them."""
        batch: dict = {"ann": [c.ann for c in clips]}
        if engine.needs_semantics() or any(s.needs_semantics for s in self.scorers[task]):
            # One (T, X, Y, Z) tensor per clip: QA clips at a scene's start have shorter windows.
            # A batch's clips are mostly consecutive, their windows overlapping: each frame is
            # read once (16 clips of 14 frames read about 30 frames, not 224).
            frames = {t: index.labels(index.scene_of(t), t)["semantics"] for c in clips for t in c.ann["tokens"]}
            batch["semantics"] = [torch.from_numpy(np.stack([frames[t] for t in c.ann["tokens"]])) for c in clips]
        return batch

    def total(
        self, engine: WorldModelEngine, data_root: str | Path, split: str, samples: int = -1, seed: int = 0
    ) -> int:
        """How many clips ``run`` visits (for a progress bar)."""
        index = DatasetIndex.open(data_root)
        rank, world = rank_world()
        total = sum(len(self._task_clips(engine, index, split, t, samples, seed)[rank::world]) for t in self.tasks)
        return total + sum(
            len(self._hook_clips(engine, index, split, h, samples, seed)[rank::world]) for h in self._hooks(engine)
        )

    def compute(self, prefix: str) -> dict[str, float]:
        """Every metric that saw samples on any process, flattened under ``prefix`` (e.g.
        ``val/qa_overall``). Every process calls it. ``sample_sets`` then says which items
        each was scored on."""
        out: dict[str, float] = {}
        fed = self._feeders()
        self.sample_sets = []
        by_feeders: dict[tuple[str, ...], list[str]] = defaultdict(list)
        for name, metric in self.metrics.items():  # one at a time: each key knows its metric
            computed = compute_metrics(prefix, {name: metric})
            out.update(computed)
            by_feeders[fed.get(name, ())] += list(computed)
        for task, scorers in self.scorers.items():
            for scorer in scorers:
                summary = scorer.summary(prefix)
                out.update(summary)
                by_feeders[(task,)] += list(summary)
        for feeders, keys in by_feeders.items():
            if keys:
                self.sample_sets.append(self._sample_set(feeders, keys))
        return out

    def _feeders(self) -> dict[str, tuple[str, ...]]:
        """Metric name -> the tasks (or ``FUTURE_CLIPS``) whose items update it: a baseline
        several scorers name is fed by each of their tasks."""
        fed: dict[str, set[str]] = defaultdict(set)
        for task, scorers in self.scorers.items():
            for scorer in scorers:
                for name in scorer.metrics:
                    fed[name].add(task)
        for hook in self.hooks:
            feeder = FUTURE_CLIPS if hook.clips == FUTURE_CLIPS or not self.tasks else self.tasks[0]
            for name in hook.metrics:
                fed[name].add(feeder)
        return {name: tuple(sorted(tasks)) for name, tasks in fed.items()}

    def _sample_set(self, feeders: tuple[str, ...], keys: list[str]) -> SampleSet:
        scored = {i for f in feeders for i in self.items.get(f, ())}
        every = {i for f in feeders for i in self.universe.get(f, ())}
        return SampleSet(digest_items(scored), len(scored), len(every), list(feeders), sorted(keys))

    def reset(self) -> None:
        for metric in self.metrics.values():
            if isinstance(metric, Metric):
                metric.reset()
        for scorer in [s for ss in self.scorers.values() for s in ss]:
            scorer.reset()
        self._once = set()
        self._reconstructed = {}
        self.scenes = []
        self.texts = []
        self.sample_sets = []
