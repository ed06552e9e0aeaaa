"""A plugin that registers a stage kind under a built-in kind's name without saying it
overrides it: refused in one line naming both registrations (before the built-in kind's
own module is even imported)."""

from occtrain.stages import StageKind, register

register(StageKind(name="pretrain", model_schema=dict, data_kind="frames", module=object))
