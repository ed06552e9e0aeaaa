"""How SparseOccVLA's text answers are graded: captions and conversation answers with the
caption metrics (CIDEr, METEOR, ROUGE-L: OmniDrive's), beside the most typical training
text; the decision by the meta action it ends with, beside the commonest training one."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from functools import partial
from typing import Any

from torchmetrics import MeanMetric

from occtrain.core.protocols import ScoringContext
from occtrain.core.scorers import BaseScorer, Item
from occtrain.data.clips import text_of
from occtrain.data.text_formats import meta_action_words, parse_meta_action
from occtrain.metrics import CaptionMetric, MetaActionAccuracy

#: Texts a typical-text baseline is chosen among (a fixed sample: its cost is quadratic).
TYPICAL_POOL = 256


def typical(texts: Iterable[str]) -> str:
    """The text whose word set overlaps most, on average, with the others' (Jaccard): the
    one fixed answer that a model which ignores the scene would do best to give."""
    pool = sorted({t for t in texts if t})[:TYPICAL_POOL]
    if not pool:
        return ""
    words = [set(t.lower().split()) for t in pool]

    def overlap(i: int) -> float:
        return sum(len(words[i] & w) / max(1, len(words[i] | w)) for j, w in enumerate(words) if j != i)

    return pool[max(range(len(pool)), key=overlap)]


class TextScorer(BaseScorer):
    """Generated text against the reference answer with the caption metrics, under
    ``name``, beside the most typical training answer of the same task."""

    def __init__(self, name: str):
        self.name = name
        self.metrics = {name: CaptionMetric, f"baseline_typical_{name}": CaptionMetric}
        self._typical: str | None = None

    def baseline(self, item: Item, ev: Any) -> str:
        if self._typical is None:
            self._typical = typical(_training_answers(item, ev))
        return self._typical

    def score(self, ev: ScoringContext, item: Item) -> None:
        text, reference = text_of(item.generated[0]).strip(), text_of(item.parts[-1])
        prompt = text_of(item.parts[-2])
        key = f"{item.clip.anchor['token']}|{prompt}"
        ev.metric(self.name).update([text], [[reference]], ids=[key])
        ev.metric(f"baseline_typical_{self.name}").update([self.baseline(item, ev)], [[reference]], ids=[key])
        ev.keep_text(self.name, prompt, text, reference)
        if ev.record and self.name == "caption":
            ev.predictions["captions"][item.clip.anchor["token"]] = text
            ev.predictions["captions_gt"][item.clip.anchor["token"]] = [reference]


def _training_answers(item: Item, ev: Any) -> list[str]:
    """The answers ``item``'s task gives on the training frames (its own builder's)."""
    from occtrain.data.clips import frame_clips

    engine, task = item.engine, item.task
    answers: list[str] = []
    for clip in frame_clips(ev.index, "train", engine.tasks.context_frames):
        for parts in engine.task_items(task, clip, every=True):
            answers.append(text_of(parts[-1]))
        if len(answers) >= 4 * TYPICAL_POOL:
            break
    return answers


CaptionScorer = partial(TextScorer, "caption")
ConversationScorer = partial(TextScorer, "conversation")


class DecisionScorer(BaseScorer):
    """The meta action the generated decision ends with against the reference's, beside the
    commonest training meta action (the frame sidecar's)."""

    metrics = {
        "meta_action": MetaActionAccuracy,
        "meta_parsed_fraction": MeanMetric,
        "baseline_prior_meta_action": MetaActionAccuracy,
    }

    def __init__(self) -> None:
        self.said: Counter = Counter()

    def score(self, ev: ScoringContext, item: Item) -> None:
        text, reference = text_of(item.generated[0]), text_of(item.parts[-1])
        truth, parsed = parse_meta_action(reference), parse_meta_action(text)
        if truth is None:
            return
        ev.metric("meta_action").update([parsed], [truth])
        ev.metric("meta_parsed_fraction").update(100.0 * (parsed is not None))
        if ev.priors.meta_action is not None:
            ev.metric("baseline_prior_meta_action").update([ev.priors.meta_action], [truth])
        said = meta_action_words(parsed) if parsed is not None else "none"
        self.said[said] += 1
        ev.keep_text("planning", text_of(item.parts[-2]), f"{text}  [parsed: {said}]", reference)

    def reset(self) -> None:
        self.said = Counter()
