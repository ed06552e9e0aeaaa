"""The stage interface: everything the runner may call on a stage, declared once.

A stage kind is a :class:`Stage` subclass (a LightningModule) registered with a name and
a model-config schema. The runner builds it from a :class:`StageContext`, feeds it the
shard entries it declares, trains and validates it with Lightning, asks it for a
:class:`StageReport` and has it :meth:`~Stage.export` what later stages consume; it calls
nothing else.
"""

from __future__ import annotations

import functools
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import lightning as L
from torch import nn

from occtrain.config.groups import DataConfig, TrainerConfig
from occtrain.config.recipe import StageSpec
from occtrain.data.shards import world_key
from occtrain.data.shards.positions import PAD_KEY
from occtrain.errors import ConfigError
from occtrain.formats.exports import check_loaded_keys
from occtrain.formats.metrics_file import SampleSet, digest_items
from occtrain.models import count_parameters

if TYPE_CHECKING:  # the registry (stages/__init__.py) imports this module
    from occtrain.engine.closed_loop import StageDriver
    from occtrain.stages import StageKind


class StepClock(Protocol):
    """What a stage asks of the meter timing its steps (``callbacks.StepMeter``, which
    imports this module): to start the step's clock again after work that is not the step's."""

    def restart_step(self) -> None: ...


#: The run directory's folder of caches keyed by their content, shared by its stages.
SHARED_CACHE = "cache"


def shared_cache_dir(stage_dir: Path) -> Path:
    """The caches keyed by their content that the stages of ``stage_dir``'s run share (``<run>/cache/``)."""
    return Path(stage_dir).parent / SHARED_CACHE


def stage_cache_dir(stage_dir: Path, data_root: str | Path) -> Path:
    """Where a stage keeps what it encoded from the dataset at ``data_root`` (see ``world_key``)."""
    return Path(stage_dir) / "cache" / world_key(data_root)


@dataclass
class StageContext:
    """Everything a stage kind needs to build its module."""

    spec: StageSpec
    model_cfg: Any  # the kind's validated model config (an omegaconf structured object)
    data: DataConfig
    trainer: TrainerConfig
    stage_dir: Path
    #: Export directories of the consumed stages, by stage name.
    inputs: dict[str, Path]

    @property
    def shared_cache_dir(self) -> Path:
        """The run's caches keyed by their content, which its stages share (``<run>/cache/``)."""
        return shared_cache_dir(self.stage_dir)

    @functools.cached_property
    def cache_dir(self) -> Path:
        """This stage's own caches (teacher outputs, camera tokens) of the run's dataset as it
        is now: ``<stage>/cache/<world key>/``, so an edited dataset is encoded afresh."""
        return stage_cache_dir(self.stage_dir, self.data.root)


@dataclass
class StageReport:
    """What a finished stage tells the run: its one-line summary, metrics to add to the
    validation ones (parameter counts, ...), sample texts and scenes for the dashboard."""

    summary: str = ""
    metrics: dict[str, float] = field(default_factory=dict)
    #: ``{"task", "prompt", "prediction", "reference"}`` records.
    texts: list[dict] = field(default_factory=list)
    #: ``(caption, [(panel label, semantics (200, 200, 16) uint8)])``: the runner draws them.
    scenes: list[tuple[str, list[tuple[str, Any]]]] = field(default_factory=list)
    #: Per task its validation generated answers for, [items scored, items the split holds]
    #: (``Evaluator.coverage``): the metrics file states the subset.
    coverage: dict[str, list[int]] = field(default_factory=dict)
    #: Which items each of ``metrics``' generated scores was scored on (``Evaluator.sample_sets``).
    sample_sets: list[SampleSet] = field(default_factory=list)


@dataclass
class EvalRequest:
    """What ``occtrain eval`` asks of a stage kind that scores its exports (``Stage.evaluate_export``)."""

    #: The stage's export, and the exports of the stages it consumed, in recipe order.
    export: Path
    consumed: list[Path]
    data_root: str
    split: str = "val"
    #: The tasks to score (None: what the stage trained on); items per task (-1: all).
    tasks: list[str] | None = None
    samples: int = -1
    batch_size: int = 16
    #: Where inputs encoded through frozen encoders are cached for this dataset.
    cache_dir: Path | None = None
    #: The run's caches keyed by their content (see ``StageContext.shared_cache_dir``).
    shared_cache_dir: Path | None = None
    #: Keep every prediction in ``occtrain score``'s formats.
    record: bool = False


@dataclass
class EvalResult:
    metrics: dict[str, float]
    #: The recorded predictions (see ``EvalRequest.record``), by kind.
    predictions: dict[str, dict] = field(default_factory=dict)
    #: Per task (or what else was scored: frames, plans), [items scored, items the split
    #: holds]: the metrics file's provenance states a subset as one.
    coverage: dict[str, list[int]] = field(default_factory=dict)
    #: Which items each number was scored on (see ``formats.metrics_file.SampleSet``).
    sample_sets: list[SampleSet] = field(default_factory=list)

    @classmethod
    def on_items(cls, metrics: dict[str, float], what: str, scored: list[str], every: list[str]) -> EvalResult:
        """Numbers all scored on one set of items (``what``: frames, planning, ...; item keys
        are sample tokens), of ``every`` item the split holds."""
        sample_set = SampleSet(digest_items(scored), len(set(scored)), len(set(every)), [what], sorted(metrics))
        return cls(metrics, coverage={what: [sample_set.items, sample_set.total]}, sample_sets=[sample_set])


#: What a task needs, in the dataset's terms (``DatasetIndex.available_tasks``), where the names differ.
TASK_NEEDS = {"cot_planning": "chain_of_thought"}


def lacking_tasks(data_root: str | Path, tasks: Iterable[str]) -> dict[str, str]:
    """Of ``tasks``, those the dataset at ``data_root`` lacks the sidecar files for, each
    with why (a plain Occ3D release has occupancy and ego poses only)."""
    from occtrain.data.layout import DatasetIndex

    available = DatasetIndex.open(data_root).available_tasks()
    return {task: why for task in tasks if (why := available.get(TASK_NEEDS.get(task, task), ""))}


def _skipping_padding(step: Callable[..., Any]) -> Callable[..., Any]:
    """A validation step that ignores a batch made only of DDP padding (see ``PAD_KEY``)."""

    @functools.wraps(step)
    def wrapped(self: Stage, batch: Any, *args: Any, **kwargs: Any) -> Any:
        if isinstance(batch, dict) and batch.get(PAD_KEY):
            return None
        return step(self, batch, *args, **kwargs)

    return wrapped


@dataclass(frozen=True)
class StepWork:
    """What one training step processed, for the throughput a stage reports
    (``callbacks.StepMeter``): a stage module sets ``step_work`` in its training step."""

    samples: int
    #: The LLM's tokens (padding left out); None for a stage without a language model.
    tokens: int | None = None
    #: The step's model FLOPs (``models.flops``), None where the stage does not count them.
    flops: float | None = None
    #: The token positions the LLM computed over, padding included (rows x row length).
    positions: int | None = None


class Stage(L.LightningModule, ABC):
    """Base of every stage kind (built-in or plugin).

    Subclasses set the class attributes below, build their models in ``__init__(ctx)``,
    implement Lightning's training/validation hooks and :meth:`export`.
    """

    #: Stage kinds whose export this kind may consume (recipe ``consumes:``).
    consumes_kinds: ClassVar[tuple[str, ...]] = ()
    #: How many stages it consumes, (least, most).
    consumes_count: ClassVar[tuple[int, int]] = (0, 0)
    #: Parameter-name prefixes of sub-models that come, frozen, from another stage's export:
    #: checkpoints leave them out and loading does not expect them back.
    frozen_prefixes: tuple[str, ...] = ()
    #: Whether its frames batches carry the camera images and their dense targets (``images``, ``cam_class``, ...).
    reads_cameras: ClassVar[bool] = False
    #: What its last training step processed, set by a stage that counts more than the
    #: batch's samples (tokens, FLOPs); None: ``callbacks.StepMeter`` counts the samples.
    step_work: StepWork | None = None
    #: The step meter timing its training steps (``callbacks.StepMeter`` sets it when the
    #: fit begins), for a stage that does work in a step's hooks that is not the step's.
    step_meter: StepClock | None = None
    #: Whether ``occtrain eval`` scores its exports (``evaluate_export``).
    evaluable: ClassVar[bool] = False
    #: Whether that eval records predictions (``EvalRequest.record``) for ``--save-predictions``.
    saves_predictions: ClassVar[bool] = False
    #: Whether ``occtrain drive`` can put its exports behind the wheel (``driver``).
    drivable: ClassVar[bool] = False
    #: Whether it trains under ``trainer.strategy: fsdp`` (it shards itself in
    #: ``configure_model``); a kind that does not is refused that strategy before training.
    shards: ClassVar[bool] = False
    #: Whether the step meter counts its training steps' model FLOPs with torch's
    #: ``FlopCounterMode`` (one step, counted, then per sample): for kinds whose FLOPs no
    #: formula gives (convolutions, point sets, planner heads). A kind that sets ``step_work``
    #: FLOPs from a formula (the language models' 6N + 12LSd) leaves it off.
    count_flops: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        step = cls.__dict__.get("validation_step")
        if step is not None:
            cls.validation_step = _skipping_padding(step)  # type: ignore[method-assign]

    def __init__(self, ctx: StageContext):
        super().__init__()
        self.ctx = ctx
        #: The optimizer step of the last full validation in this process (None: none yet),
        #: so the runner need not validate again what fit validated at its last step.
        self.validated_at: int | None = None
        #: What the last training step processed; None: its batch's samples are all it says.
        self.step_work: StepWork | None = None

    def on_validation_end(self) -> None:
        if not self.trainer.sanity_checking:
            self.validated_at = self.trainer.global_step

    # -- what the runner calls before anything is built
    @classmethod
    def family_of(cls, model: dict, consumed: dict[str, Any]) -> str | None:
        """The family whose parts this stage trains, from its raw ``model:`` and the planned
        stages it consumes (by name): by default the first consumed stage's."""
        return next((p.family for p in consumed.values() if p.family), None)

    @classmethod
    def model_schema(cls, kind: StageKind, family: str | None, model: dict | None = None) -> type:
        """The dataclass ``model:`` (raw: ``model``) is validated against, and hashed from, for ``family``."""
        return kind.model_schema

    @classmethod
    def check_family(cls, family: str | None, consumed: dict[str, Any], where: str) -> None:
        """Refuse, before anything runs, a stage whose family cannot do what it is asked."""

    @classmethod
    def check_trainer(cls, model: Any, trainer: TrainerConfig, where: str) -> None:
        """Refuse trainer settings that the stage's model settings contradict (``where``:
        ``stages.<name>``); by default none."""

    @classmethod
    def check_model(cls, model: Any, key: str) -> None:
        """Refuse, before anything is written, a validated ``model:`` (under ``key``) that
        building the stage's model would refuse: what ``occtrain validate`` shares with
        ``run``. By default nothing beyond the schema."""

    @classmethod
    def check_against_consumed(cls, model: Any, consumed: Mapping[str, Any], key: str) -> None:
        """Refuse a validated ``model:`` that cannot work with what the stage consumes (the
        consumed stages' planned configs, by name, each with ``model_cfg``): a check
        ``occtrain validate`` can make before those stages have trained. Nothing by default."""

    @classmethod
    def camera_input(cls, model: Any) -> bool:
        """Whether a stage of this kind with the validated ``model:`` reads the camera
        images (its batches then carry them): by default the kind's ``reads_cameras``."""
        return cls.reads_cameras

    @classmethod
    def evaluate_export(cls, request: EvalRequest) -> EvalResult:
        """Score an export of this kind (``occtrain eval``); kinds with ``evaluable`` implement it."""
        raise NotImplementedError

    @classmethod
    def driver(cls, request: EvalRequest) -> StageDriver:
        """The export's planner for closed-loop driving (``occtrain drive``); kinds with
        ``drivable`` implement it. ``request.data_root`` is unused: the frames come as driven."""
        raise NotImplementedError

    @classmethod
    def check_consumes(cls, kind: str, consumed: dict[str, str], where: str) -> None:
        """Refuse a recipe whose ``consumes:`` (stage name -> kind) this kind cannot read."""
        lo, hi = cls.consumes_count
        if not lo <= len(consumed) <= hi:
            n = f"exactly {lo}" if lo == hi else f"{lo} to {hi}"
            what = f" ({' or '.join(cls.consumes_kinds)})" if cls.consumes_kinds else ""
            raise ConfigError(f"{where}: a {kind} stage consumes {n} earlier stage(s){what}, got {len(consumed)}")
        for name, other in consumed.items():
            if other not in cls.consumes_kinds:
                raise ConfigError(
                    f"{where}: a {kind} stage cannot consume '{name}', a {other} stage; it reads "
                    f"{' or '.join(cls.consumes_kinds)}"
                )

    def require_tasks(self, tasks: Iterable[str], instead: str = "") -> None:
        """Refuse, before any training, a stage whose tasks need sidecar files the dataset
        lacks (a plain Occ3D release has occupancy and ego poses only). ``instead``: what
        else the user can do (default: drop the task by its weight)."""
        for task, why in lacking_tasks(self.ctx.data.root, tasks).items():
            instead = instead or f"set stages.{self.ctx.spec.name}.model.tasks.weights.{task}=0"
            raise ConfigError(f"task {task} {why} ({self.ctx.data.root}); add the sidecar or {instead}")

    def entries(self, split: str) -> tuple[str, ...] | None:
        """The shard entries this stage reads on ``split`` ("train", "val"); None: all of them."""
        return None

    def monitored(self, kind: StageKind) -> tuple[str | None, str]:
        """The validation metric that picks ``best.ckpt`` and whether higher is better: the
        kind's, unless the stage knows better once built (a family's planner names its own)."""
        return kind.monitor, kind.mode

    def split_items(self) -> int | None:
        """How many items the val split holds for what this stage validates, where that is not
        the number of its val shards' samples (None: it is): a final validation's provenance
        says how many of them it saw."""
        return None

    def compiled_blocks(self) -> list[nn.Module]:
        """The modules ``trainer.compile`` compiles for training steps, each on its own
        (``models.compiling``); none by default."""
        return []

    def report(self) -> StageReport:
        """Summary, extra metrics and samples, asked for after the final validation."""
        return StageReport(summary=f"{count_parameters(self) / 1e6:.2f}M params")

    def prepare_export(self) -> None:
        """Called on every rank before rank zero's :meth:`export`: a sharded stage gathers
        its full weights here (a collective). Nothing by default."""

    @abstractmethod
    def export(self, path: Path) -> Path:
        """Write what later stages consume to ``path`` (safetensors + JSON); returns it."""

    # -- shared behaviour
    def step_seed(self, step: int) -> int:
        """The seed of training step ``step``: the same on every rank and after a resume."""
        return self.ctx.data.seed * 1_000_003 + step

    # Module.state_dict is overloaded on its destination; a stage's is always a fresh dict.
    def state_dict(self, *args: Any, **kwargs: Any) -> dict[str, Any]:  # type: ignore[override]
        return {k: v for k, v in super().state_dict(*args, **kwargs).items() if not k.startswith(self.frozen_prefixes)}

    def load_state_dict(self, state_dict: Mapping[str, Any], strict: bool = True, assign: bool = False) -> Any:
        """Strict except for :attr:`frozen_prefixes`: a missing or unexpected key is an error naming it."""
        missing, unexpected = super().load_state_dict(state_dict, strict=False)
        self._check_keys(missing, unexpected)

    def check_checkpoint_keys(self, keys: Iterable[str]) -> None:
        """The same strict check for a checkpoint loaded another way (a sharded one, by
        Lightning's strategy): ``keys`` are its state dict's."""
        keys, expected = set(keys), set(self.state_dict().keys())
        self._check_keys(sorted(expected - keys), sorted(keys - expected))

    def _check_keys(self, missing: list[str], unexpected: list[str]) -> None:
        check_loaded_keys(
            missing,
            unexpected,
            self.frozen_prefixes,
            f"checkpoint of stage '{self.ctx.spec.name}'",
            f"run with --restart {self.ctx.spec.name}",
        )
