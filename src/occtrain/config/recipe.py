"""Recipe schema: a run's name, its data, default trainer settings, ordered stages, and an
optional table of its results beside a paper's figures."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from omegaconf import MISSING

from occtrain.config.groups import DataConfig, TrainerConfig
from occtrain.errors import ConfigError
from occtrain.formats.manifest import NAME_PATTERN, NAME_RULE


def check_name(name: Any, key: str, source: str, what: str) -> str:
    """``name`` if it is a safe folder name (:data:`NAME_PATTERN`); else one line naming ``key``."""
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise ConfigError(
            f"{key} '{name}' in {source}: {what} is a folder name inside "
            f"{'runs_root' if what == 'a run' else 'the run'}, "
            f"so it is {NAME_RULE}; choose another"
        )
    return name


@dataclass
class OptimConfig:
    """AdamW with linear warm-up then cosine (or constant) decay."""

    lr: float = 1e-3
    weight_decay: float = 0.01
    betas: list[float] = field(default_factory=lambda: [0.9, 0.95])
    warmup_steps: int = 0
    schedule: str = "cosine"  # cosine | constant
    min_lr_ratio: float = 0.1
    #: AdamW's epsilon: it bounds the step of a parameter whose gradient is near zero.
    eps: float = 1e-8


@dataclass
class StageSpec:
    """One stage of a recipe.

    ``model`` is validated against the schema of the stage's kind (see occtrain.stages);
    ``trainer`` holds only the keys this stage changes from the recipe's trainer.
    """

    name: str = MISSING
    kind: str = MISSING
    #: Earlier stages whose ``export/`` this stage reads (never their checkpoints).
    consumes: list[str] = field(default_factory=list)
    #: Parameter-name prefixes kept frozen.
    freeze: list[str] = field(default_factory=list)
    model: dict[str, Any] = field(default_factory=dict)
    optim: OptimConfig = field(default_factory=OptimConfig)
    trainer: dict[str, Any] = field(default_factory=dict)
    #: How this stage reads the recipe's data: only the loader keys (``STAGE_DATA_KEYS``),
    #: e.g. a larger batch for a cheap stage; the dataset itself is the recipe's.
    data: dict[str, Any] = field(default_factory=dict)


#: The ``data:`` keys a stage may set for itself.
STAGE_DATA_KEYS = ("batch_size", "num_workers", "shuffle_buffer")


@dataclass
class TableColumn:
    """One measure of a comparison table, read from each row's stage's final metrics."""

    #: The header, e.g. ``IoU``; a row's ``paper:`` figures are keyed by it.
    name: str = MISSING
    #: A key of the stage's final metrics (manifest.json -> stages -> <stage> -> metrics).
    metric: str = MISSING
    #: Our value is multiplied by it before it is shown (1e-6: parameters in millions);
    #: paper figures are written in the shown unit already.
    scale: float = 1.0
    digits: int = 2


@dataclass
class TableRow:
    """One variant: a stage of the recipe, and the paper's figures for it."""

    stage: str = MISSING
    #: Defaults to the stage's name.
    label: str = ""
    #: Column name -> the paper's figure; a column left out (or null) was not reported.
    paper: dict[str, float | None] = field(default_factory=dict)


@dataclass
class ComparisonTable:
    """What a run prints and writes to ``RUN_DIR/table.md`` once every stage is done."""

    title: str = ""
    #: One paragraph under the table (which convention, what differs from the paper).
    note: str = ""
    columns: list[TableColumn] = field(default_factory=list)
    rows: list[TableRow] = field(default_factory=list)


@dataclass
class RecipeConfig:
    """What ``occtrain run`` reads."""

    name: str = MISSING
    #: Another recipe this one builds on: its stages come first, then this one's, and what
    #: this one sets beside ``stages`` replaces that recipe's (e.g. the quickstart chain
    #: and one more stage, in the quickstart's run directory).
    extends: str = ""
    data: DataConfig = field(default_factory=DataConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    stages: list[StageSpec] = field(default_factory=list)
    #: Where runs go; the run directory is ``<runs_root>/<name>`` unless --run-dir is given.
    runs_root: str = "runs"
    #: Importable modules that register extra stage kinds (``occtrain.stages.register``).
    plugins: list[str] = field(default_factory=list)
    #: Our figures beside the paper's, one row per stage (see occtrain.report.compare).
    table: ComparisonTable | None = None
