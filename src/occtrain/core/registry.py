"""The registry of paper families and of the scene-tokenizer architectures they bring.

A family registers one :class:`FamilySpec`: its scene tokenizers, and when it has a world
model a :class:`WorldSpec` (its model class, task settings and tasks, what the model is
built over, how its scene encoder is made, its planner and evaluation hooks). Stages,
the engine, ``occtrain eval`` and the dashboard look families up here by name and never
import one. The families shipped with occtrain are found by walking the
``occtrain.families`` package; a plugin registers through the ``occtrain.families`` entry
point group (its value: a module that calls :func:`register_family` when imported), or a
recipe's ``plugins:`` list.

A name (a family, a stage kind, a tokenizer architecture) belongs to the module that
registered it first: another module registering it is refused in one line unless it says
``override=True``, and then every command says so in a note. A plugin that fails while
being imported is one line too (:func:`load_plugin`), whatever it raised.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import TYPE_CHECKING, Any

from torch import nn

from occtrain.core.protocols import (
    EvalHook,
    Planner,
    PlannerContext,
    PlannerSettings,
    Scorer,
    WorldEngine,
)
from occtrain.core.sample_inputs import SampleInput
from occtrain.core.shared_tasks import TaskConfig, TaskSpec
from occtrain.errors import ConfigError, OcctrainError, cause_line

if TYPE_CHECKING:  # imported where it is checked: the world model imports the registry's neighbours
    from occtrain.core.lm_world_model import LMWorldModel
    from occtrain.core.published import PaperFigure

#: The package whose sub-packages are the families shipped with occtrain.
BUILTIN_PACKAGE = "occtrain.families"
#: The entry-point group through which an installed package adds a family.
ENTRY_POINT_GROUP = "occtrain.families"


#: ``(consumed exports by stage kind, the world model's settings) -> its scene encoder``
#: (a torch module that is a ``core.protocols.SceneEncoder``: the engine freezes it), at
#: pretraining (None: the world model reads no scene).
SceneEncoderBuilder = Callable[[dict[str, Path], object], nn.Module | None]
#: ``(a world-model export, its config.json) -> the scene encoder it holds``.
SceneEncoderLoader = Callable[[Path, dict[str, object]], nn.Module | None]
#: ``(the planner stage's context, its frozen world model or None) -> the planner it trains``.
PlannerBuilder = Callable[[PlannerContext, WorldEngine | None], Planner]
#: ``(a planner export, its frozen world model, the dataset root, a cache folder) -> the
#: trained planner`` (eval mode).
PlannerLoader = Callable[[Path, WorldEngine, str, Path], Planner]
#: An operation of the Python API: ``(engine, **its own keyword arguments) -> its answer``.
Operation = Callable[..., object]


@dataclass(frozen=True)
class TokenizerArch:
    """A scene-tokenizer architecture: ``model.arch`` name, config dataclass, model class.

    Most read occupancy (``model(semantics)`` in training). One that reads the cameras
    (``reads_cameras``) is called as ``model(batch, index, teacher)`` with the frames batch
    (images and calibration beside the labels it learns), the dataset index (other frames
    of the clip) and the frozen encoder of a consumed stage of a kind in ``teachers`` (a
    feature-distillation teacher, None when the recipe gives none; the model's
    ``attach_teacher(width)`` is called first, before its optimizer is made).
    """

    name: str
    config: type
    model: type
    reads_cameras: bool = False
    #: Stage kinds a tokenizer stage of this architecture may consume as its teacher.
    teachers: tuple[str, ...] = ()


@dataclass(frozen=True)
class WorldSpec:
    """What a family with a world model brings to the shared world-model stage kinds."""

    #: Its class: a ``core.lm_world_model.LMWorldModel`` (``create``, ``from_export``,
    #: ``vocab_layout``, ``export_config``).
    model: type[LMWorldModel]
    #: Its task settings (extends ``core.shared_tasks.TaskConfig``) and tasks by name.
    task_config: type[TaskConfig]
    tasks: Mapping[str, TaskSpec]
    #: Stage kind ("pretrain", "instruct") -> the task weights a stage that names none trains.
    default_tasks: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    #: Its world model's own settings (``model.<family>`` of a pretrain stage), or None.
    world_config: type | None = None
    #: Fixed words of its prompts, added to the text its BPE tokenizer trains on.
    prompt_words: tuple[str, ...] = ()
    #: Stage kinds a pretrain stage of this family consumes, besides none (its inputs).
    inputs: tuple[str, ...] = ("tokenizer",)
    #: ``(exports by kind, world settings) -> SceneEncoder | None`` at pretraining, and
    #: ``(export dir, export config) -> SceneEncoder | None`` when an export is loaded.
    scene_encoder: SceneEncoderBuilder | None = None
    load_scene_encoder: SceneEncoderLoader | None = None
    #: It reads the cameras through a vision stage's frozen encoder.
    reads_cameras: bool = False
    #: The per-sample inputs its prompt parts read by name (``PromptInputs.read``): the
    #: engine encodes or reads them as each declares, and knows none of them itself.
    sample_inputs: tuple[SampleInput, ...] = ()
    #: Family-level scoring classes (``core.protocols.EvalHook``), made per evaluator.
    eval_hooks: tuple[type, ...] = ()
    #: What its planner stage trains; None: the family has no planner.
    planner: PlannerBuilder | None = None
    #: The planner's settings (``model.head`` of a planner stage), a dataclass.
    planner_config: type[PlannerSettings] | None = None
    #: A trained planner back from its export, for ``occtrain eval``, ``drive`` and a
    #: ``dagger`` stage (None: its planner stages are not scored by eval).
    load_planner: PlannerLoader | None = None
    #: Operations of the Python API (``occtrain.load``), name -> ``(engine, **kwargs) -> result``.
    operations: Mapping[str, Operation] = field(default_factory=dict)


@dataclass(frozen=True)
class Showcase:
    """Where the four-family comparison (``tools/compare_families.py``) reads a family's
    headline numbers: its shipped recipe (``recipes/<recipe>.yaml``) and the stage of that
    recipe behind each number (None: the family has none)."""

    recipe: str
    #: The world-model stage whose export says how many tokens a frame takes.
    world: str
    #: A stage that forecasts occupancy.
    forecast: str | None = None
    #: The stage whose plans are scored (a planner, or a world model that plans), and the
    #: metric prefix of the plans the family ends with.
    plan: str | None = None
    plan_metric: str = "plan"
    qa: str | None = None
    caption: str | None = None
    #: What the LLM reads of a scene, in a few words.
    note: str = ""


@dataclass(frozen=True)
class FamilySpec:
    """What one paper family contributes to the shared stage kinds."""

    name: str
    #: The paper, as README's table names it.
    paper: str
    tokenizers: tuple[TokenizerArch, ...] = ()
    #: Its world model, if it has one.
    world: WorldSpec | None = None
    #: The paper's published figures (``core.published.PaperFigure``), shown beside a run's metrics.
    paper_figures: tuple[PaperFigure, ...] = ()
    #: Its row of the four-family comparison, if it has one.
    showcase: Showcase | None = None


_FAMILIES: dict[str, FamilySpec] = {}
_TOKENIZERS: dict[str, tuple[TokenizerArch, str]] = {}
_loaded = False
#: The module that registered each name, by (what it names, name): "family", "stage kind", ...
_ORIGINS: dict[tuple[str, str], str] = {}
#: Names a plugin registered with override=True, and the module whose registration it replaced.
_OVERRIDDEN: dict[tuple[str, str], str] = {}


def _check(spec: FamilySpec) -> None:
    """Refuse, in one line, a family whose parts do not fit the seams they plug into."""
    where = f"family '{spec.name}'"
    for arch in spec.tokenizers:
        if not hasattr(arch.config, "validate") or not inspect.isclass(arch.model):
            raise ConfigError(
                f"{where}: tokenizer '{arch.name}' needs a config dataclass with validate() and a model class"
            )
    world = spec.world
    if world is None:
        return
    from occtrain.core.lm_world_model import LMWorldModel

    if not (inspect.isclass(world.model) and issubclass(world.model, LMWorldModel)):
        raise ConfigError(
            f"{where}: its world model {world.model!r} is not an occtrain.core.lm_world_model.LMWorldModel"
        )
    if not (inspect.isclass(world.task_config) and issubclass(world.task_config, TaskConfig)):
        raise ConfigError(
            f"{where}: its task settings {world.task_config!r} do not extend occtrain.core.shared_tasks.TaskConfig"
        )
    for name, task in world.tasks.items():
        if not isinstance(task, TaskSpec) or not callable(task.build):
            raise ConfigError(f"{where}: task '{name}' is not a TaskSpec with a builder")
        for make in scorer_factories(task):
            if not isinstance(make(), Scorer):
                raise ConfigError(
                    f"{where}: the scorer of task '{name}' does not implement occtrain.core.protocols.Scorer"
                )
    for hook in world.eval_hooks:
        if not isinstance(hook(), EvalHook):
            raise ConfigError(f"{where}: {hook!r} does not implement occtrain.core.protocols.EvalHook")
    for kind, weights in world.default_tasks.items():
        unknown = set(weights) - set(world.tasks)
        if unknown:
            raise ConfigError(f"{where}: default {kind} task '{sorted(unknown)[0]}' is not one of its tasks")
    for given in world.sample_inputs:
        if not isinstance(given, SampleInput):
            raise ConfigError(f"{where}: its input {given!r} is not an occtrain.core.sample_inputs.SampleInput")
    names = [i.name for i in world.sample_inputs]
    if len(set(names)) != len(names):
        raise ConfigError(f"{where}: two of its sample_inputs share a name ({names})")
    if any(i.reads_cameras for i in world.sample_inputs) and not world.reads_cameras:
        raise ConfigError(f"{where}: an input reads the cameras, so the world spec needs reads_cameras=True")
    if world.scene_encoder is not None and world.load_scene_encoder is None:
        raise ConfigError(
            f"{where}: a scene encoder built at pretraining needs load_scene_encoder to come back from an export"
        )
    if world.planner is not None and world.planner_config is None:
        raise ConfigError(f"{where}: its planner needs a planner_config dataclass (model.head of a planner stage)")
    if world.planner_config is not None and not (
        inspect.isclass(world.planner_config) and issubclass(world.planner_config, PlannerSettings)
    ):
        raise ConfigError(
            f"{where}: its planner_config {world.planner_config!r} does not extend "
            "occtrain.core.protocols.PlannerSettings"
        )


def scorer_factories(task: TaskSpec) -> tuple[Callable[[], Any], ...]:
    """The scorer factories of a task (none, one or several)."""
    if task.scorer is None:
        return ()
    return tuple(task.scorer) if isinstance(task.scorer, (tuple, list)) else (task.scorer,)


def registrant(up: int = 1) -> str:
    """The module whose code called the register function that calls this (``up`` frames
    above that function): whom a registration belongs to."""
    return sys._getframe(up + 1).f_globals.get("__name__", "an unnamed module")


def _shipped(module: str) -> bool:
    return module == "occtrain" or module.startswith("occtrain.")


def _describe(module: str) -> str:
    return f"{module} (shipped with occtrain)" if _shipped(module) else f"plugin {module}"


def holder(what: str, name: str, registered: bool, shipped_by: str | None = None) -> str | None:
    """The module that holds ``name`` (a ``what``: "family", "stage kind"), None when free.
    ``shipped_by``: the module of occtrain that registers it when first used (a stage kind
    whose module is not imported yet)."""
    if not registered:
        return shipped_by
    return _ORIGINS.get((what, name)) or shipped_by or "an earlier registration"


def claim(what: str, name: str, origin: str, override: bool, held_by: str | None) -> bool:
    """Whether module ``origin`` may register ``name``, which ``held_by`` holds.

    Refused, in one line naming both registrations, when another module holds it and
    ``override`` is not given. False: skip the registration, it is the shipped module that
    a plugin has already overridden (imported after the plugin)."""
    if held_by is None or held_by == origin:
        return True  # a new name, or the same module registering again (imported twice)
    if _OVERRIDDEN.get((what, name)) == origin:
        return False
    if not override:
        raise ConfigError(
            f"{what} '{name}' of {_describe(origin)} is already registered by {_describe(held_by)}; "
            f"register it with override=True to replace it"
        )
    return True


def take(what: str, name: str, origin: str, held_by: str | None) -> None:
    """Record that ``origin`` holds ``name`` now (after :func:`claim` allowed it), with a
    note when that overrides another module's registration."""
    _ORIGINS[(what, name)] = origin
    if held_by is not None and held_by != origin:
        _OVERRIDDEN[(what, name)] = held_by
        _note(f"{_describe(origin)} overrides the {what} '{name}' of {_describe(held_by)}")


def _note(text: str) -> None:
    from rich.markup import escape

    from occtrain.progress import console
    from occtrain.ranks import is_rank_zero

    if is_rank_zero():  # every rank registers; one note is enough
        console.print(f"[yellow]note[/]: {escape(text)}")


def register_family(spec: FamilySpec, override: bool = False) -> FamilySpec:
    """Add a family (a plugin may register its own). A family or tokenizer arch name that
    another module registered is refused unless ``override``; the same module (or the very
    same spec) registering again is harmless."""
    origin = registrant()
    if not _loaded and not _shipped(origin):
        _discover()  # a plugin's names are checked against every shipped (and installed) one
    if _FAMILIES.get(spec.name) is spec:
        return spec
    _check(spec)
    family_holder = holder("family", spec.name, spec.name in _FAMILIES)
    if not claim("family", spec.name, origin, override, family_holder):
        return spec
    # Another family's arch is a clash of its own; one of the family it replaces goes with it.
    arch_holders = {
        a.name: holder("family", _TOKENIZERS[a.name][1], True)
        for a in spec.tokenizers
        if a.name in _TOKENIZERS and _TOKENIZERS[a.name][1] != spec.name
    }
    for name, held_by in arch_holders.items():
        claim("tokenizer arch", name, origin, override, held_by)
    take("family", spec.name, origin, family_holder)
    for name, held_by in arch_holders.items():
        take("tokenizer arch", name, origin, held_by)
    for name in [n for n, (_, family) in _TOKENIZERS.items() if family == spec.name]:
        del _TOKENIZERS[name]
    for arch in spec.tokenizers:
        _TOKENIZERS[arch.name] = (arch, spec.name)
    _FAMILIES[spec.name] = spec
    return spec


def load_plugin(load: Callable[[], Any], what: str, module: str) -> Any:
    """``load()`` (an import of plugin ``module``, named ``what`` in messages) with anything
    it raises as one line: a plugin's traceback is its author's to read, not each command's."""
    try:
        return load()
    except ImportError as err:
        if _missing(err, module):
            raise ConfigError(
                f"{what} cannot be imported ({cause_line(err)}); is it installed or on PYTHONPATH?"
            ) from None
        raise ConfigError(f"{what} failed while being imported: {cause_line(err)}") from None
    except OcctrainError as err:  # already one line for the user (a name another module holds)
        raise ConfigError(f"{what}: {(str(err).splitlines() or [type(err).__name__])[0]}") from None
    except (Exception, SystemExit) as err:  # SystemExit: a plugin's sys.exit() would end the command silently
        raise ConfigError(f"{what} failed while being imported: {cause_line(err)}") from None


def _missing(err: ImportError, module: str) -> bool:
    """Whether the plugin module itself (or a package above it) is what cannot be found,
    rather than something it imports."""
    name = getattr(err, "name", None) or ""
    return isinstance(err, ModuleNotFoundError) and (module == name or module.startswith(name + "."))


def _discover() -> None:
    """Import the shipped families (each sub-package of ``occtrain.families``), then the
    modules that installed packages name in the ``occtrain.families`` entry-point group."""
    global _loaded
    if _loaded:
        return
    _loaded = True
    package = importlib.import_module(BUILTIN_PACKAGE)
    for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda i: i.name):
        if info.ispkg:
            importlib.import_module(f"{BUILTIN_PACKAGE}.{info.name}")
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        load_plugin(ep.load, f"the {ENTRY_POINT_GROUP} entry point '{ep.name}' ({ep.value})", ep.module)


def families() -> dict[str, FamilySpec]:
    """Every registered family by name."""
    _discover()
    return dict(_FAMILIES)


def world_families() -> dict[str, FamilySpec]:
    """The registered families that have a world model."""
    return {n: f for n, f in families().items() if f.world is not None}


def get_family(name: str, key: str = "model.family") -> FamilySpec:
    """The registration of family ``name``; one line naming ``key`` when there is none."""
    _discover()
    if name not in _FAMILIES:
        raise ConfigError(f"{key}: unknown model family '{name}'; families are {', '.join(sorted(_FAMILIES))}")
    return _FAMILIES[name]


def get_world(name: str, key: str = "model.family") -> WorldSpec:
    """The world spec of family ``name``; one line naming ``key`` when it has none."""
    spec = get_family(name, key)
    if spec.world is None:
        raise ConfigError(
            f"{key}: family '{name}' has no world model; use one of {', '.join(sorted(world_families()))}"
        )
    return spec.world


def tokenizer_archs() -> dict[str, TokenizerArch]:
    """Every registered scene-tokenizer architecture by ``model.arch`` name."""
    _discover()
    return {name: arch for name, (arch, _) in _TOKENIZERS.items()}


def tokenizer_family(arch: str) -> str:
    _discover()
    if arch not in _TOKENIZERS:
        raise ConfigError(f"model.arch: '{arch}' is not a tokenizer; use one of {', '.join(_TOKENIZERS)}")
    return _TOKENIZERS[arch][1]


def tokenizer_arch(name: str) -> TokenizerArch:
    """The registered architecture ``model.arch: name`` names, or a one-line refusal."""
    archs = tokenizer_archs()
    if name not in archs:
        raise ConfigError(f"model.arch: '{name}' is not a tokenizer; use one of {', '.join(archs)}")
    return archs[name]
