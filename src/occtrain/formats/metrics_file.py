"""A metrics file: the numbers, and what they were measured on.

Every ``metrics.json`` occtrain writes (a stage's final validation, ``occtrain eval``'s
scores) maps metric names to numbers, plus one reserved key, ``provenance``: which split,
how many items of how many per task (a subset says so), which world (by its content, not
by where it lies), which code, and which attempt of the stage (its config hash, attempt
number and start). A number whose provenance is missing is shown as such, never as a
whole-split figure; :func:`read_metrics` is the one reader.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from occtrain.errors import DataError
from occtrain.formats.io import atomic_write_json

PROVENANCE_KEY = "provenance"


@dataclass(frozen=True)
class StageAttempt:
    """Which training of a stage a number is of: its manifest entry's config hash, attempt
    count and start time (a ``--restart`` resets the count, the start tells them apart)."""

    config_hash: str = ""
    attempt: int = 0
    started: float | None = None


@dataclass(frozen=True)
class Provenance:
    """What a metrics file's numbers were measured on (see the module docstring)."""

    #: Who measured: ``occtrain eval``, or the stage's validation at the end of training.
    by: str
    split: str
    #: Per task (or ``frames``, ``clips``): [items scored, items the split holds].
    coverage: dict[str, list[int]] = field(default_factory=dict)
    #: The world by content (``data.layout.world_identity``), its version and a readable name.
    world: str = ""
    world_version: str = ""
    world_name: str = ""
    #: The dataset as it lay on disk (``data.shards.world_key``: its place and files' state),
    #: which decides whether two measurements may be merged into one file.
    dataset: str = ""
    code_version: str = ""
    stage: StageAttempt = field(default_factory=StageAttempt)
    #: When the numbers were measured (ISO 8601, UTC).
    measured: str = ""

    @property
    def subset(self) -> bool:
        """Some task was scored on fewer items than the split holds."""
        return any(scored < total for scored, total in self.coverage.values())

    def describe(self) -> str:
        """``the whole val split`` or ``a subset of the val split (qa 64 of 412, ...)``."""
        if not self.coverage:
            return f"the {self.split} split (item counts not recorded)"
        if not self.subset:
            return f"the whole {self.split} split"
        parts = ", ".join(f"{what} {scored} of {total}" for what, (scored, total) in sorted(self.coverage.items()))
        return f"a subset of the {self.split} split ({parts})"

    def same_model_and_data(self, other: Provenance) -> bool:
        """Both measured the same attempt of the stage on the same dataset, as it lay on disk."""
        return (self.dataset, self.world, self.stage) == (other.dataset, other.world, other.stage)

    def merged(self, earlier: Provenance | None) -> Provenance:
        """This measurement over an earlier one of the same world and attempt: the tasks
        scored now replace theirs, the others are kept (an eval of one task after another)."""
        if earlier is None:
            return self
        return Provenance(**{**asdict(self), "stage": self.stage, "coverage": {**earlier.coverage, **self.coverage}})

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, raw: Any, where: Path) -> Provenance:
        try:
            stage = StageAttempt(**raw.get("stage", {}))
            coverage = {str(k): [int(v[0]), int(v[1])] for k, v in raw.get("coverage", {}).items()}
            return cls(**{**raw, "stage": stage, "coverage": coverage})
        except (TypeError, ValueError, IndexError, AttributeError) as err:
            raise DataError(
                f"{where}: its '{PROVENANCE_KEY}' is malformed ({err}); measure it again (`occtrain eval`)"
            ) from None


@dataclass(frozen=True)
class MetricsFile:
    """A metrics file read back: the numbers (``null`` as NaN) and their provenance, if recorded."""

    metrics: dict[str, float]
    provenance: Provenance | None


def write_metrics(path: str | Path, metrics: dict[str, float], provenance: Provenance) -> Path:
    """Write ``metrics`` and their provenance to ``path`` atomically."""
    if PROVENANCE_KEY in metrics:
        raise ValueError(f"'{PROVENANCE_KEY}' is the metrics file's own key, not a metric name")
    return atomic_write_json(path, {**metrics, PROVENANCE_KEY: provenance.to_json()})


def read_metrics(path: str | Path) -> MetricsFile:
    """The numbers and provenance of a metrics file; one line naming it when it is unreadable."""
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as err:
        raise DataError(f"{path}: unreadable metrics ({err}); measure it again (`occtrain eval`)") from None
    if not isinstance(raw, dict):
        raise DataError(f"{path}: holds no metrics object; measure it again (`occtrain eval`)")
    provenance = raw.pop(PROVENANCE_KEY, None)
    numbers: dict[str, float] = {}
    for key, value in raw.items():
        if value is None:
            numbers[str(key)] = float("nan")
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            numbers[str(key)] = float(value)
        else:
            raise DataError(f"{path}: metric '{key}' is {value!r}, not a number; measure it again (`occtrain eval`)")
    return MetricsFile(numbers, None if provenance is None else Provenance.from_json(provenance, path))
