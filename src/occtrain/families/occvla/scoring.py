"""How OccVLA's answers are graded: the meta action its chain of thought ends with
(speed / direction / mean / overall, its Table 4), beside the commonest one; and its
occupancy query branch, decoded and scored in both conventions."""

from __future__ import annotations

import torch
from torchmetrics import MeanMetric

from occtrain.core.protocols import TASK_CLIPS, ScoringContext, WorldEngine, family_tasks, family_world
from occtrain.core.scorers import BaseScorer, Item, last_past_meta_action
from occtrain.data.clips import Clip, text_of
from occtrain.data.meta_actions import commonest
from occtrain.data.schema import MetaAction
from occtrain.data.text_formats import meta_action_words, parse_meta_action
from occtrain.families.occvla.config import TaskConfig
from occtrain.families.occvla.parts import Images
from occtrain.families.occvla.world_model import OccVLAWorldModel
from occtrain.metrics import MetaActionAccuracy, OccupancyMetric
from occtrain.metrics.occupancy import OCC3D, OCCWORLD


class MetaActionScorer(BaseScorer):
    """The meta action the chain of thought ends with against the one the prompt's answer
    holds (labelled from the poses), beside two baselines under the same labeller: the
    commonest training one, and repeating the last past one (which the prompt states)."""

    metrics = {
        "meta_action": MetaActionAccuracy,
        "meta_parsed_fraction": MeanMetric,
        "baseline_prior_meta_action": MetaActionAccuracy,
        "baseline_repeat_last_meta_action": MetaActionAccuracy,
    }

    def __init__(self) -> None:
        self._prior: dict[tuple, MetaAction | None] = {}

    def score(self, ev: ScoringContext, item: Item) -> None:

        text, reference = text_of(item.generated[0]), text_of(item.parts[-1])
        cfg = family_tasks(item.engine, TaskConfig).meta_actions
        last = last_past_meta_action(item.clip, cfg)  # what "as before" means (meta_action_prior)
        truth, parsed = parse_meta_action(reference, last), parse_meta_action(text, last)
        ev.metric("meta_action").update([parsed], [truth])
        ev.metric("meta_parsed_fraction").update(100.0 * (parsed is not None))
        key = tuple(sorted(vars(cfg).items()))
        if key not in self._prior and ev.index is not None:
            self._prior[key] = commonest(ev.index, "train", cfg)
        prior = self._prior.get(key)
        if prior is not None:
            ev.metric("baseline_prior_meta_action").update([prior], [truth])
        # The last one the prompt lists; none (a scene's start) scores as a wrong answer.
        ev.metric("baseline_repeat_last_meta_action").update([last], [truth])
        said = meta_action_words(parsed) if parsed is not None else "none"
        prompt = text_of(item.parts[-2])
        ev.keep_text("meta_action", prompt, f"{text}  [parsed: {said}]", reference)
        if ev.record:
            ev.predictions["meta_actions"][item.clip.anchor["token"]] = {
                "prompt": prompt,
                "generated": text,
                "parsed": parsed,
                "reference": reference,
                "truth": truth,
                "last_past": last,
            }


class OccupancyQueries:
    """OccVLA's query branch on each clip's anchor, when the stage trains it: one forward of
    the images and the queries, decoded by the frozen OccWorld decoder, scored in both conventions."""

    clips = TASK_CLIPS
    metrics = {
        "occupancy_occ3d": lambda: OccupancyMetric(OCC3D),
        "occupancy_occworld": lambda: OccupancyMetric(OCCWORLD),
    }

    def applies(self, engine: WorldEngine) -> bool:

        return family_tasks(engine, TaskConfig).occupancy_weight > 0

    @torch.no_grad()
    def run(self, ev: ScoringContext, engine: WorldEngine, clips: list[Clip]) -> None:

        index, dev = ev.index, ev.device
        assert index is not None  # an evaluator's run sets it before its hooks run
        world = family_world(engine, OccVLAWorldModel)
        for clip in clips:
            token = clip.anchor["token"]
            pred = world.predict_occupancy(engine.encode_parts([Images(token)], {})).argmax(1).cpu()
            labels = index.labels(index.scene_of(token), token)
            target = torch.from_numpy(labels["semantics"]).long()[None]
            mask = torch.from_numpy(labels["mask_camera"].astype(bool))[None]
            ev.metric("occupancy_occ3d").update(pred.to(dev), target.to(dev), mask.to(dev))
            ev.metric("occupancy_occworld").update(pred.to(dev), target.to(dev))
            ev.keep_scene(
                "occupancy",
                f"occupancy from the queries, sample {token[:8]}: truth and prediction",
                [("truth", target[0].numpy()), ("queries", pred[0].numpy())],
            )
