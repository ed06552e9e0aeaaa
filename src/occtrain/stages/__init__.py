"""Stage kinds: each a :class:`~occtrain.stages.stage.Stage` (a LightningModule) registered by name.

``BUILTIN_KINDS`` is the one list of the kinds occtrain ships; each imports its module on
first use, so a recipe of tokenizer stages never pays for importing transformers. Plugins
register more with :func:`register` (``override=True`` to replace a kind, built-in or not).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from occtrain.stages.stage import Stage, StageContext, StageReport

#: Built-in kinds and the module that registers each.
BUILTIN_KINDS = {
    "tokenizer": "occtrain.stages.tokenizer",
    "pretrain": "occtrain.stages.pretrain_instruct",
    "instruct": "occtrain.stages.pretrain_instruct",
    "planner": "occtrain.stages.planner",
    "dagger": "occtrain.stages.planner",
    "distill": "occtrain.stages.distill",
    "vision": "occtrain.stages.vision",
}


@dataclass(frozen=True)
class StageKind:
    """A registered kind: its name, the schema of its ``model:`` section and its Stage class."""

    name: str
    model_schema: type
    data_kind: str  # "frames" or "clips"
    module: type[Stage]
    #: Validation metric that picks ``best.ckpt``, and whether higher is better.
    monitor: str | None = None
    mode: str = "max"

    def build(self, ctx: StageContext) -> Stage:
        return self.module(ctx)


_KINDS: dict[str, StageKind] = {}


def register(kind: StageKind, override: bool = False) -> StageKind:
    """Add a stage kind. A name that another module registered (a built-in kind included,
    imported or not) is refused unless ``override``; the same module registering again is
    harmless. The rules are the family registry's (``core.registry.claim``)."""
    from occtrain.core import registry

    if _KINDS.get(kind.name) is kind:
        return kind
    origin = registry.registrant()
    held_by = registry.holder("stage kind", kind.name, kind.name in _KINDS, BUILTIN_KINDS.get(kind.name))
    if registry.claim("stage kind", kind.name, origin, override, held_by):
        registry.take("stage kind", kind.name, origin, held_by)
        _KINDS[kind.name] = kind
    return kind


def get_kind(name: str) -> StageKind | None:
    """The registered kind, importing a built-in kind's module on first use."""
    if name not in _KINDS and name in BUILTIN_KINDS:
        importlib.import_module(BUILTIN_KINDS[name])
    return _KINDS.get(name)


def kind_names() -> list[str]:
    return sorted(set(_KINDS) | set(BUILTIN_KINDS))


__all__ = ["BUILTIN_KINDS", "Stage", "StageContext", "StageKind", "StageReport", "get_kind", "kind_names", "register"]
