"""The configuration reference: every key a recipe may set, read off the registered schemas
(the recipe's, each stage kind's ``model:``, each family's task, world and planner settings,
each tokenizer architecture's). ``occtrain config reference`` prints it; the documentation
site renders it as its configuration page (``docs/hooks.py``)."""

from __future__ import annotations

from occtrain.config.recipe import RecipeConfig
from occtrain.config.reference import KeyDoc, markdown_table, reference_rows
from occtrain.core import registry
from occtrain.stages import get_kind, kind_names


def _section(title: str, intro: str, rows: list[KeyDoc]) -> str:
    return f"## {title}\n\n{intro}\n\n{markdown_table(rows)}\n"


def config_reference() -> str:
    """The whole reference as Markdown."""
    parts = [
        "# Configuration reference\n\n"
        "Every key a recipe may set, with its type, its default and what it sets, generated from the "
        "dataclass schemas that validate recipes (`occtrain config reference` prints the same). A "
        "`required` default must be given; `[]` marks a list of sections. A stage's `model:` is checked "
        "against its kind's schema, extended by the family (`model.family`) or tokenizer architecture "
        "(`model.arch`) it names.\n",
        _section(
            "Recipe",
            "What `occtrain run RECIPE` reads; `configs/data/*.yaml` and `configs/trainer/*.yaml` "
            "hold its `data:` and `trainer:` sections.",
            reference_rows(RecipeConfig),
        ),
    ]
    for name in kind_names():
        kind = get_kind(name)
        if kind is not None:
            parts.append(
                _section(
                    f"`model:` of the `{name}` kind",
                    f"What a stage of kind `{name}` reads under `model:`.",
                    reference_rows(kind.model_schema, "model."),
                )
            )
    for name, family in sorted(registry.world_families().items()):
        world = family.world
        assert world is not None  # world_families() holds only families with one
        rows = reference_rows(world.task_config, "model.tasks.")
        if world.world_config is not None:
            rows += reference_rows(world.world_config, f"model.{name}.")
        if world.planner_config is not None:
            rows += reference_rows(world.planner_config, "model.head.")
        parts.append(
            _section(
                f"Family `{name}`",
                f"{family.paper}: what a world-model stage with `model.family: {name}` "
                "adds (its tasks, its world model, its planner head).",
                rows,
            )
        )
    for name, arch in sorted(registry.tokenizer_archs().items()):
        parts.append(
            _section(
                f"Tokenizer `{name}`",
                f"What a `tokenizer` stage with `model.arch: {name}` adds.",
                reference_rows(arch.config, f"model.{name}."),
            )
        )
    return "\n".join(parts)
