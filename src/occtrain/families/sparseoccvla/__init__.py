"""SparseOccVLA (seeds/004): sparse occupancy queries bridging occupancy and a VLM. Its
published figures are registered for the dashboard."""

from __future__ import annotations

from occtrain.core.registry import FamilySpec, register_family
from occtrain.families.sparseoccvla.paper import PAPER_FIGURES

SPARSEOCCVLA = register_family(FamilySpec(name="sparseoccvla", paper="SparseOccVLA", paper_figures=PAPER_FIGURES))

__all__ = ["SPARSEOCCVLA"]
