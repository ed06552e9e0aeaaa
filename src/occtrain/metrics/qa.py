"""NuScenes-QA accuracy: overall, by question template type, and by type and hop count.

The reference (NuScenes-QA ``src/execution/result_eval.py``) scores a question correct
when the predicted answer string equals ``str(answer)`` of the ground truth, with no
other normalisation: no lower-casing, stripping or punctuation removal, because its
models pick answers from a closed vocabulary. Generated text must therefore be decoded
to the bare answer ("yes", "2", "car", ...) before it reaches this metric. Accuracy is
correct / asked in percent, reported only for the types and hops that were asked.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torchmetrics import Metric

from occtrain.formats.nuscenes_qa import HOPS, TEMPLATE_TYPES


def answer_text(answer: Any) -> str:
    """The string the reference compares: ``str()`` of the answer as stored."""
    return str(answer)


class QAMetric(Metric):
    """Exact-match NuScenes-QA accuracy (%) overall, by type (exist, count, ...) and by type and hop.

    ``update(predictions, answers, template_types, num_hops)`` takes one entry per question.
    ``compute()`` returns ``overall``, ``by_type`` ({type: %}), ``by_type_hop``
    ({"exist_H0": %, ...}) and ``questions``; counts are summed across DDP processes.
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False
    #: Counts by (template type, hop).
    correct: torch.Tensor
    asked: torch.Tensor

    def __init__(self, **kwargs: Any):
        super().__init__(**kwargs)
        shape = (len(TEMPLATE_TYPES), len(HOPS))
        self.add_state("correct", torch.zeros(shape, dtype=torch.long), dist_reduce_fx="sum")
        self.add_state("asked", torch.zeros(shape, dtype=torch.long), dist_reduce_fx="sum")

    def update(
        self, predictions: Sequence[str], answers: Sequence[Any], template_types: Sequence[str], num_hops: Sequence[int]
    ) -> None:
        n = len(predictions)
        if not (len(answers) == len(template_types) == len(num_hops) == n):
            raise ValueError(
                f"{n} predictions, {len(answers)} answers, {len(template_types)} types and {len(num_hops)} hops differ "
                "in number"
            )
        unknown = sorted({t for t in template_types if t not in TEMPLATE_TYPES})
        if unknown:
            raise ValueError(f"unknown template type '{unknown[0]}'; NuScenes-QA types are {', '.join(TEMPLATE_TYPES)}")
        bad_hops = sorted({int(h) for h in num_hops if int(h) not in HOPS})
        if bad_hops:
            raise ValueError(f"num_hop {bad_hops[0]} is not one of {HOPS}")
        rows = torch.tensor([TEMPLATE_TYPES.index(t) for t in template_types], dtype=torch.long)
        cols = torch.tensor([int(h) for h in num_hops], dtype=torch.long)
        hits = torch.tensor([str(p) == answer_text(a) for p, a in zip(predictions, answers)], dtype=torch.long)
        flat = rows * len(HOPS) + cols
        size = len(TEMPLATE_TYPES) * len(HOPS)
        self.asked += torch.bincount(flat, minlength=size).reshape(self.asked.shape).to(self.asked.device)
        self.correct += (
            torch.bincount(flat, weights=hits.double(), minlength=size)
            .long()
            .reshape(self.correct.shape)
            .to(self.correct.device)
        )

    def compute(self) -> dict[str, Any]:
        def pct(correct: torch.Tensor, asked: torch.Tensor) -> torch.Tensor:
            return 100.0 * correct.double() / asked.double()

        by_type = {
            t: pct(self.correct[i].sum(), self.asked[i].sum())
            for i, t in enumerate(TEMPLATE_TYPES)
            if self.asked[i].sum() > 0
        }
        by_type_hop = {
            f"{t}_H{h}": pct(self.correct[i, h], self.asked[i, h])
            for i, t in enumerate(TEMPLATE_TYPES)
            for h in HOPS
            if self.asked[i, h] > 0
        }
        return {
            "overall": pct(self.correct.sum(), self.asked.sum()),
            "by_type": by_type,
            "by_type_hop": by_type_hop,
            "questions": self.asked.sum(),
        }
