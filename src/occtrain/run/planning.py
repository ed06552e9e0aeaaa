"""A recipe read into planned stages: its file and overrides loaded, its plugins imported,
each stage's kind, family, model and trainer sections checked, and what it consumes."""

from __future__ import annotations

import hashlib
import importlib
import inspect
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from occtrain.config import load_config, to_container
from occtrain.config.groups import DataConfig, TrainerConfig, check_seed
from occtrain.config.loading import read_resolved, validate_section
from occtrain.config.recipe import STAGE_DATA_KEYS, RecipeConfig, StageSpec, check_name
from occtrain.core.registry import get_family
from occtrain.errors import ConfigError
from occtrain.report.compare import check_table
from occtrain.stages import Stage, StageKind, get_kind, kind_names

#: Trainer keys that change how often things are written, or how the same steps are
#: computed (``compile``: the same losses to float tolerance), not what is learned: a done
#: stage is not refused for them, and a stopped one resumes under them.
OPERATIONAL_KEYS = ("log_every_n_steps", "ckpt_every_n_steps", "loggers", "compile")


@dataclass
class PlannedStage:
    spec: StageSpec
    kind: StageKind
    model_cfg: Any
    trainer: TrainerConfig
    config: dict  # resolved, hashed
    config_hash: str
    data: Any = None  # the recipe's DataConfig with the stage's loader keys applied
    #: The family whose parts the stage trains (None: none, e.g. a vision stage).
    family: str | None = None
    #: Its batches carry the camera images (``Stage.camera_input``).
    reads_cameras: bool = False


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, dict):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: d}


def changed_keys(old: dict, new: dict) -> list[str]:
    """Dotted keys whose values differ between two resolved stage configs."""
    a, b = _flatten(old), _flatten(new)
    return sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))


def plan_stages(recipe: RecipeConfig, source: str) -> list[PlannedStage]:
    """Validate every stage (kind, names, handoffs, model config) and hash its resolved config."""
    planned: list[PlannedStage] = []
    names: list[str] = []
    data = to_container(recipe.data)
    for i, spec in enumerate(recipe.stages):
        kind, where = _stage_kind(spec, i, source)
        if spec.name in names:
            raise ConfigError(f"stage name '{spec.name}' is used twice in {source}")
        _check_consumes(spec, names, [s.name for s in recipe.stages], where)
        consumed = {dep: planned[names.index(dep)] for dep in spec.consumes}
        kind.module.check_consumes(spec.kind, {dep: p.spec.kind for dep, p in consumed.items()}, where)
        family, model_cfg = _model_config(kind, spec, consumed, f"stages[{i}].model", source, where)
        kind.module.check_model(model_cfg, f"stages.{spec.name}.model")
        kind.module.check_against_consumed(model_cfg, consumed, f"stages.{spec.name}.model")
        check_model_counts(model_cfg, f"stages.{spec.name}.model", source)
        wrong = sorted(set(spec.data or {}) - set(STAGE_DATA_KEYS))
        if wrong:
            raise ConfigError(
                f"stages[{i}].data.{wrong[0]} in {source}: a stage sets only {', '.join(STAGE_DATA_KEYS)}; the dataset "
                "is the recipe's"
            )
        stage_data = validate_section(DataConfig, {**data, **(spec.data or {})}, f"stages[{i}].data", source)
        trainer = validate_section(
            TrainerConfig, {**to_container(recipe.trainer), **(spec.trainer or {})}, f"stages[{i}].trainer", source
        )
        if trainer.max_steps <= 0:
            key = (
                f"stages.{spec.name}.trainer.max_steps" if "max_steps" in (spec.trainer or {}) else "trainer.max_steps"
            )
            raise ConfigError(
                f"{key} is {trainer.max_steps} in {source}: a stage trains for a positive number of optimizer steps "
                "(training streams data without end, so there is no 'until the data runs out')"
            )
        kind.module.check_trainer(model_cfg, trainer, f"stages.{spec.name}")
        for section, value, own in (
            ("trainer", trainer, spec.trainer),
            ("data", stage_data, spec.data),
            ("optim", spec.optim, None),
        ):
            check_ranges(section, value, spec.name, own, source)
        trainer_dict = {k: v for k, v in to_container(trainer).items() if k not in OPERATIONAL_KEYS}
        config = {
            "kind": spec.kind,
            "consumes": {dep: planned[names.index(dep)].config_hash for dep in spec.consumes},
            "freeze": list(spec.freeze),
            "model": to_container(model_cfg),
            "optim": to_container(spec.optim),
            "trainer": trainer_dict,
            "data": to_container(stage_data),
        }
        digest = hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()[:16]
        cameras = kind.module.camera_input(model_cfg)
        planned.append(PlannedStage(spec, kind, model_cfg, trainer, config, digest, stage_data, family, cameras))
        names.append(spec.name)
    if not planned:
        raise ConfigError(f"{source} has no stages")
    return planned


def _stage_kind(spec: StageSpec, i: int, source: str) -> tuple[StageKind, str]:
    """The registered kind of the recipe's ``i``-th stage (its name and kind checked first),
    and how errors name the stage."""
    for key in ("name", "kind"):
        if OmegaConf.is_missing(spec, key):
            raise ConfigError(
                f"stages[{i}] in {source} has no '{key}:'; every stage needs a name and a kind "
                f"({', '.join(kind_names())})"
            )
    check_name(spec.name, f"stages[{i}].name", source, "a stage")
    where = f"stages[{i}] ('{spec.name}') in {source}"
    kind = get_kind(spec.kind)
    if kind is None:
        raise ConfigError(f"unknown stage kind '{spec.kind}' for {where}; kinds are {', '.join(kind_names())}")
    if not (inspect.isclass(kind.module) and issubclass(kind.module, Stage)) or inspect.isabstract(kind.module):
        raise ConfigError(
            f"stage kind '{spec.kind}' of {where} is registered with {kind.module!r}, "
            "which is not a concrete occtrain.stages.Stage (it must subclass Stage and implement export)"
        )
    return kind, where


def _check_consumes(spec: StageSpec, earlier: list[str], every: list[str], where: str) -> None:
    """A stage consumes the exports of stages that run before it."""
    for dep in spec.consumes:
        if dep == spec.name:
            raise ConfigError(f"{where} consumes itself; a stage consumes the exports of earlier stages")
        if dep not in earlier:
            later = " (it runs later)" if dep in every else ""
            raise ConfigError(f"{where} consumes '{dep}', which is not an earlier stage{later}")


#: Settings whose type alone lets through values that fail late, deep in Lightning or
#: torch: the least each may be, per section (``None``: any finite number).
_LEAST: dict[str, dict[str, float | None]] = {
    "trainer": {
        "devices": 1,
        "num_nodes": 1,
        "val_check_interval": 1,
        "log_every_n_steps": 1,
        "ckpt_every_n_steps": 1,
        "accumulate_grad_batches": 1,
        "limit_val_batches": -1,
        "gradient_clip_val": 0,
    },
    "data": {
        "batch_size": 1,
        "num_workers": 0,
        "shuffle_buffer": -1,
        "samples_per_shard": 1,
        "history": 0,
        "future": 0,
    },
    "optim": {"lr": 0, "weight_decay": 0, "warmup_steps": 0, "min_lr_ratio": 0, "eps": 0},
}
#: Seeds per section (dotted below it): numpy takes 0 to 2**32 - 1 and raises deep in
#: Lightning's seeding, the synthesis or a loader otherwise.
_SEEDS: dict[str, tuple[str, ...]] = {"trainer": ("seed",), "data": ("seed", "synth.seed")}


#: Counts in a stage's ``model:`` that size a batch or a loop, whichever kinds have them:
#: the least each may be. Out of range they fail late and raw (``val_batch_size: 0``:
#: ``range() arg 3 must not be zero`` once validation generates) or do nothing at all
#: (a negative one validates no item). A planner's ``max_new_text_tokens`` of 0 keeps its
#: world model's own (a world model stage asks for at least 1 itself).
_MODEL_LEAST = {"val_batch_size": 1, "prior_batches": 0, "max_new_text_tokens": 0, "generate_batches": -1}


def check_model_counts(model: Any, key: str, source: str) -> None:
    """Refuse a ``model:`` count out of range (``_MODEL_LEAST``) in one line naming its key."""
    for name, least in _MODEL_LEAST.items():
        value = getattr(model, name, None)
        if isinstance(value, int) and value < least:
            raise ConfigError(f"{key}.{name} is {value} in {source}: it must be at least {least}")


def check_ranges(section: str, cfg: Any, stage: str, own: dict | None, source: str) -> None:
    """Refuse a value out of its range (``batch_size: 0``, ``lr: -1``, ``lr: nan``,
    ``val_check_interval: 0``) in one line naming its key, before anything is written."""
    for name, least in _LEAST[section].items():
        value = getattr(cfg, name)
        if section == "trainer" and name == "devices" and value == -1:  # Lightning's "every device"
            continue
        if isinstance(value, float) and not math.isfinite(value) or (least is not None and value < least):
            key = (
                f"stages.{stage}.{section}.{name}" if section == "optim" or name in (own or {}) else f"{section}.{name}"
            )
            wanted = (
                "a finite number" if isinstance(value, float) and not math.isfinite(value) else f"at least {least:g}"
            )
            if name == "devices":
                wanted += ", or -1 for every device"
            raise ConfigError(f"{key} is {value} in {source}: it must be {wanted}")
    for name in _SEEDS.get(section, ()):
        seed = cfg
        for part in name.split("."):
            seed = getattr(seed, part)
        key = f"stages.{stage}.{section}.{name}" if name in (own or {}) else f"{section}.{name}"
        check_seed(seed, key, f" in {source}")
    if section == "optim" and (
        len(cfg.betas) != 2 or not all(0 <= b < 1 for b in cfg.betas) or cfg.schedule not in ("cosine", "constant")
    ):
        key = "schedule" if cfg.schedule not in ("cosine", "constant") else "betas"
        raise ConfigError(
            f"stages.{stage}.optim.{key} is {getattr(cfg, key)} in {source}: schedule is cosine or constant, betas two "
            "numbers in [0, 1)"
        )


def _model_config(
    kind: StageKind, spec: StageSpec, consumed: dict, key: str, source: str, where: str
) -> tuple[str | None, Any]:
    """The stage's family and its ``model:`` validated against the schema for that family
    (only the chosen family's settings: registering another family changes no hash)."""
    raw = to_container(spec.model) if spec.model is not None else {}
    raw = raw if isinstance(raw, dict) else {}
    family = kind.module.family_of(raw, consumed)
    named = raw.get("family")
    if named and named != family:
        get_family(str(named), f"{key}.family in {source}")  # a typo is named as one
        raise ConfigError(
            f"{key}.family in {source} is '{named}', but the stage tunes the consumed '{family}' world model; leave it "
            "out"
        )
    kind.module.check_family(family, consumed, where)
    return family, validate_section(kind.module.model_schema(kind, family, raw), spec.model or {}, key, source)


#: A dotted Python module name: what ``plugins:`` lists.
PLUGIN_NAME = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*")


def load_plugins(modules: list[str], source: str) -> None:
    """Import the recipe's plugin modules, which register their stage kinds and families;
    whatever one raises is one line naming it (``core.registry.load_plugin``)."""
    from functools import partial

    from occtrain.core.registry import load_plugin

    for name in modules:
        if not PLUGIN_NAME.fullmatch(str(name)):
            # importlib would take a path for a relative import, or a file name for a package
            # and its module, and say so in its own terms.
            raise ConfigError(
                f"plugin '{name}' in {source}: a plugin is a Python module name (e.g. my_package.occtrain_plugin), "
                "importable on sys.path"
            )
        load_plugin(partial(importlib.import_module, name), f"plugin '{name}' in {source}", name)


def _stage_names(path: str | Path) -> list[str]:
    """Stage names of a recipe file as written, with those of the recipe it extends (for
    addressing stages in overrides)."""
    stages = read_resolved(path, RecipeConfig).get("stages") or []
    return [str(s.get("name")) for s in stages if isinstance(s, dict)] if isinstance(stages, list) else []


def stage_override(item: str, names: list[str], source: str) -> str:
    """``stages.<name>.key=v`` and ``stages.<i>.key=v`` -> ``stages[<i>].key=v``; others unchanged."""
    key = item.split("=", 1)[0].strip()
    parts = key.split(".")
    if parts[0] != "stages" or len(parts) < 3:
        return item
    ref = parts[1]
    if ref.isdigit() and int(ref) < len(names):
        index = int(ref)
    elif ref in names:
        index = names.index(ref)
    else:
        forms = "stages.<name>.<key>=, stages.<index>.<key>= or stages[<index>].<key>="
        raise ConfigError(
            f"override '{item}': {source} has no stage '{ref}' (stages: {', '.join(names) or 'none'}); address one as "
            f"{forms}"
        )
    return f"stages[{index}].{'.'.join(parts[2:])}={item.split('=', 1)[1]}" if "=" in item else item


def shadowed_overrides(recipe: RecipeConfig, overrides: list[str]) -> list[str]:
    """One note per command-line ``trainer.<key>=`` that some stage's own ``trainer:`` overrides."""
    notes = []
    for item in overrides:
        key = item.split("=", 1)[0].strip()
        if not key.startswith("trainer.") or "=" not in item:
            continue
        sub = key.split(".", 1)[1]
        own = [s.name for s in recipe.stages if sub in (s.trainer or {})]
        if own:
            notes.append(
                f"{key}={item.split('=', 1)[1]} applies to every stage except {', '.join(own)}, which set their own "
                f"(override one with stages.{own[0]}.trainer.{sub}=...)"
            )
    return notes


def load_recipe(path: str | Path, overrides: list[str] | None = None) -> tuple[RecipeConfig, list[PlannedStage]]:
    """The recipe with its overrides, and its stages planned and validated."""
    overrides = list(overrides or [])
    if any(o.startswith("stages.") for o in overrides):
        names = _stage_names(path)
        overrides = [stage_override(o, names, str(path)) for o in overrides]
    recipe = load_config(RecipeConfig, path, overrides)
    if OmegaConf.is_missing(recipe, "name"):
        raise ConfigError(f"{path} has no 'name:'; a recipe names its run (the run directory is <runs_root>/<name>)")
    check_name(recipe.name, "name", str(path), "a run")
    load_plugins(list(recipe.plugins), str(path))
    planned = plan_stages(recipe, str(path))
    check_table(recipe.table, [p.spec.name for p in planned], str(path))
    return recipe, planned
