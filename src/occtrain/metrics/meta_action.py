"""OccVLA's meta-action accuracy (Tables 4, 6, 7, 8): speed, direction ("trajectory" in the
paper), their mean, and "overall" (both parts right), in percent.

OccVLA has no public code; the four numbers follow the paper's definitions: speed and
direction are each scored against the reference alone, "Avg." is their arithmetic mean
(its Table 4: (53.77 + 77.24) / 2 = 65.51) and "Overall" counts a sample right only when
both parts are. A generated chain of thought whose meta action cannot be parsed counts as
wrong on both parts: a model is not let off for not answering.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torchmetrics import Metric


class MetaActionAccuracy(Metric):
    """``update(predictions, references)``: lists of meta actions ({"speed", "direction"};
    a prediction may be None, unparsed). ``compute()``: ``speed``, ``direction``, ``mean``,
    ``overall`` (%) and ``samples``; counts are summed across DDP processes."""

    is_differentiable = False
    higher_is_better = True
    full_state_update = False
    speed: torch.Tensor
    direction: torch.Tensor
    both: torch.Tensor
    total: torch.Tensor

    def __init__(self, **kwargs: Any):
        super().__init__(**kwargs)
        for name in ("speed", "direction", "both", "total"):
            self.add_state(name, default=torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")

    def update(self, predictions: Sequence[Mapping[str, str] | None], references: Sequence[Mapping[str, str]]) -> None:
        if len(predictions) != len(references):
            raise ValueError(f"{len(predictions)} predictions for {len(references)} references")
        for pred, ref in zip(predictions, references):
            speed = pred is not None and pred["speed"] == ref["speed"]
            direction = pred is not None and pred["direction"] == ref["direction"]
            self.speed += int(speed)
            self.direction += int(direction)
            self.both += int(speed and direction)
        self.total += len(references)

    def compute(self) -> dict[str, float]:
        n = max(int(self.total), 1)
        speed, direction = 100.0 * float(self.speed) / n, 100.0 * float(self.direction) / n
        return {
            "speed": speed,
            "direction": direction,
            "mean": (speed + direction) / 2,
            "overall": 100.0 * float(self.both) / n,
            "samples": float(self.total),
        }
