"""A metrics file: the numbers, and what they were measured on.

Every ``metrics.json`` occtrain writes (a stage's final validation, ``occtrain eval``'s
scores) maps metric names to numbers, plus one reserved key, ``provenance``: which split,
how many items of how many per task (a subset says so), which world (by its content, not
by where it lies), which code, and which attempt of the stage (its config hash, attempt
number and start). A number whose provenance is missing is shown as such, never as a
whole-split figure; :func:`read_metrics` is the one reader.

Each number also belongs to a :class:`SampleSet`: the items it was scored on, by their
identity (a digest of the items' keys), so a number and a baseline are set side by side
only when they were scored on the same items, and an eval of one subset merged over an
eval of another keeps each number with its own items.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field, replace
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
class SampleSet:
    """The items some numbers were scored on: ``items`` of the ``total`` the split holds for
    the ``tasks`` that fed them (the clips of a planning task, the questions of QA, ...),
    ``digest`` naming exactly which (``digest_items``), and the metric keys scored on them."""

    digest: str
    items: int
    total: int
    tasks: list[str]
    keys: list[str]
    #: What the items are where they are not the provenance's split (closed-loop rollouts
    #: on training routes); empty: items of the split.
    on: str = ""

    def describe(self) -> str:
        if self.on:
            return f"{'+'.join(self.tasks)}: {self.on}"
        return f"{'+'.join(self.tasks)} {self.items} of {self.total}"


def digest_items(keys: Iterable[str]) -> str:
    """Which items were scored, in 12 hex digits: the same items give the same digest,
    whatever order or task scored them (a clip's key is its sample token)."""
    return hashlib.sha256("\n".join(sorted(set(keys))).encode()).hexdigest()[:12]


@dataclass(frozen=True)
class Provenance:
    """What a metrics file's numbers were measured on (see the module docstring)."""

    #: Who measured: ``occtrain eval``, or the stage's validation at the end of training.
    by: str
    split: str
    #: Per task (or ``frames``, ``clips``): [items scored, items the split holds].
    coverage: dict[str, list[int]] = field(default_factory=dict)
    #: The world by content (``data.identity.world_identity``), its version and a readable name.
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
    #: Which items each number was scored on (empty: not recorded, files before it was).
    sample_sets: list[SampleSet] = field(default_factory=list)

    @property
    def subset(self) -> bool:
        """Some task was scored on fewer items than the split holds."""
        return any(scored < total for scored, total in self.coverage.values())

    def describe(self) -> str:
        """``the whole val split`` or ``a subset of the val split (qa 64 of 412, ...)``, and
        any numbers not of the split (``the whole val split; rollouts: 120 frames ...``)."""
        elsewhere = "".join(f"; {s.describe()}" for s in self.sample_sets if s.on)
        if not self.coverage:
            return f"the {self.split} split (item counts not recorded){elsewhere}"
        if not self.subset:
            return f"the whole {self.split} split{elsewhere}"
        parts = ", ".join(f"{what} {scored} of {total}" for what, (scored, total) in sorted(self.coverage.items()))
        return f"a subset of the {self.split} split ({parts}){elsewhere}"

    def same_model_and_data(self, other: Provenance) -> bool:
        """Both measured the same attempt of the stage on the same dataset, as it lay on disk,
        by the same code (another checkout may score differently)."""
        mine = (self.dataset, self.world, self.stage, self.code_version)
        return mine == (other.dataset, other.world, other.stage, other.code_version)

    def sample_set(self, key: str) -> SampleSet | None:
        """The items ``key`` was scored on (None: not recorded)."""
        return next((s for s in self.sample_sets if key in s.keys), None)

    def merged(self, earlier: Provenance | None) -> Provenance:
        """This measurement over an earlier one of the same world and attempt: the tasks
        scored now replace theirs, the others are kept (an eval of one task after another).
        Every number keeps the items it was scored on: an earlier number this one does not
        rewrite stays in its earlier sample set, whatever this one scored."""
        if earlier is None:
            return self
        rewritten = {k for s in self.sample_sets for k in s.keys}
        kept = [replace(s, keys=[k for k in s.keys if k not in rewritten]) for s in earlier.sample_sets]
        sets = [s for s in kept if s.keys] + list(self.sample_sets)
        coverage = {**earlier.coverage, **self.coverage}
        return Provenance(**{**self.__dict__, "coverage": coverage, "sample_sets": sets})

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, raw: Any, where: Path) -> Provenance:
        try:
            stage = StageAttempt(**raw.get("stage", {}))
            coverage = {str(k): [int(v[0]), int(v[1])] for k, v in raw.get("coverage", {}).items()}
            sets = [
                SampleSet(
                    str(s["digest"]),
                    int(s["items"]),
                    int(s["total"]),
                    list(s["tasks"]),
                    list(s["keys"]),
                    str(s.get("on", "")),
                )
                for s in raw.get("sample_sets", [])
            ]
            return cls(**{**raw, "stage": stage, "coverage": coverage, "sample_sets": sets})
        except (TypeError, ValueError, IndexError, AttributeError, KeyError) as err:
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
