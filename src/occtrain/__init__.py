"""occtrain: multi-stage training for occupancy-language-action driving world models.

``occtrain.load(export_dir)`` gives a trained world model with its family's operations
(see ``occtrain.api``); the command line is ``occtrain`` (``occtrain.cli``)."""

from __future__ import annotations

import importlib
from typing import Any

from occtrain.version import __version__

__all__ = ["__version__", "load"]


def __getattr__(name: str) -> Any:
    # Lazy: ``import occtrain`` stays cheap for the CLI, which loads torch only when it needs it.
    if name == "load":
        return importlib.import_module("occtrain.api").load
    raise AttributeError(f"module 'occtrain' has no attribute '{name}'")
