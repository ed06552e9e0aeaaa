"""A trained planner back from its export, over the frozen world model it reads: what
``occtrain eval`` and ``occtrain drive`` score, what a ``dagger`` stage fine-tunes, and
what its rollout workers drive. Each family rebuilds its own (``WorldSpec.load_planner``)."""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

from occtrain.core.protocols import Planner
from occtrain.core.registry import get_world
from occtrain.engine.export import load_world_model
from occtrain.engine.world_engine import WorldModelEngine
from occtrain.errors import ConfigError
from occtrain.formats.exports import read_config


class PlannerRequest(Protocol):
    """Where the planner and its world model are, and the dataset whose inputs it caches
    (``stages.EvalRequest`` is one)."""

    @property
    def export(self) -> Path: ...
    @property
    def consumed(self) -> list[Path]: ...
    @property
    def data_root(self) -> str: ...
    @property
    def cache_dir(self) -> Path | None: ...


def load_planner(request: PlannerRequest, what: str) -> tuple[Planner, WorldModelEngine]:
    """The planner of ``request.export`` over the world model of ``request.consumed[0]``,
    both in eval mode (``what``: the command asking, for the error a family that cannot
    rebuild its planner gets)."""
    family = read_config(request.consumed[0]).get("family", "")
    world = get_world(family)
    if world.load_planner is None:  # refused before the world model is loaded
        raise ConfigError(
            f"{request.export}: {what} cannot rebuild a '{family}' planner; its validation metrics are in metrics.json"
        )
    if request.cache_dir is None:  # every request for a planner names its stage's cache
        raise ValueError(f"{request.export}: a planner is rebuilt with the cache folder of its stage")
    teacher = load_world_model(request.consumed[0]).eval()
    return world.load_planner(request.export, teacher, request.data_root, request.cache_dir), teacher


__all__ = ["PlannerRequest", "load_planner"]
