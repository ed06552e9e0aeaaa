"""The papers' published figures (real nuScenes / Occ3D-nuScenes), keyed by occtrain's metric names.

Each family lists its paper's numbers (``FamilySpec.paper_figures``, in its ``paper.py``),
each read off a table of one of the four papers (linked from the README); ``where`` names the table and row.
They are what the methods reach on real data with full-size models: the dashboard shows
them beside a run's metrics for orientation, never as a target for the synthetic world.

Metric names are matched by their word sets, so ``val/forecast/occworld_mIoU_1s`` and
``val/occworld_forecast_mIoU_1s`` are the same key: a name is lower-cased, split on ``/ _ - .``,
and the words in :data:`NEUTRAL_WORDS` are dropped. The canonical names used here:

- tokenizer reconstruction: ``val/occworld_mIoU``, ``val/occworld_IoU``
- forecasting: ``val/forecast/occworld_{mIoU,IoU}_{1s,2s,3s,avg}``
- planning: ``val/plan/{L2,collision}_{stp3,uniad}_{1s,2s,3s,avg}``; none of the papers names
  its planning convention, so their figures carry no convention word and sit beside both
- NuScenes-QA accuracy: ``val/qa/overall``, ``val/qa/{H0,H1}``, ``val/qa/<type>``, ``val/qa/<type>_<H0|H1>``
- meta-action accuracy: ``val/meta_action/{acc,speed_acc,direction_acc,mean}`` (``acc`` is "overall")

Left out on purpose: caption figures (OccLLaMA's Nu-X, Occ-LLM's DriveLM, SparseOccVLA's
OmniDrive), whose benchmarks are different text tasks from occtrain's chain-of-thought narration.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from occtrain.metrics.conventions import OCC3D, OCCWORLD, STP3, UNIAD

#: Words that do not change what a metric measures ("val/qa/overall" is "val/qa_acc").
NEUTRAL_WORDS = frozenset(
    {
        "val",
        "test",
        "plan",
        "planning",
        "by",
        "type",
        "hop",
        "overall",
        "all",
        "acc",
        "accuracy",
        # occtrain's planning variants (OccLLaMA's M0-M3 ways of planning) all measure the same thing
        "direct",
        "alternate",
        "cot",
    }
)
#: Words naming a metric convention: a paper figure without one matches each of them.
CONVENTION_WORDS = frozenset({OCC3D, OCCWORLD, STP3, UNIAD})
REAL_DATA = "paper, real nuScenes"

GT_OCC = "ground-truth occupancy input"
CAMERA = "camera input"
PLAN_CONVENTION = "L2/collision convention not named in the paper"
OCCWORLD_SETTING = "OccWorld's setting (compared with OccWorld's own figures); camera mask not stated"


@dataclass(frozen=True)
class PaperFigure:
    """One published number: which paper, where in it, under which setting and convention."""

    metric: str
    value: float
    paper: str
    where: str
    setting: str
    convention: str


def metric_words(name: str) -> frozenset[str]:
    """The word set a metric name is matched by."""
    return frozenset(w for w in re.split(r"[/_\-.\s]+", name.lower()) if w and w not in NEUTRAL_WORDS)


def horizons(metric: str, values: tuple[float, float, float, float], **info: str) -> list[PaperFigure]:
    """Figures at 1 s, 2 s, 3 s and their average; ``metric`` has a ``{h}`` slot."""
    return [PaperFigure(metric.format(h=h), v, **info) for h, v in zip(("1s", "2s", "3s", "avg"), values)]


def qa_types(paper: str, where: str, setting: str, rows: dict[str, tuple[float, float, float]]) -> list[PaperFigure]:
    info = dict(paper=paper, where=where, setting=setting, convention="NuScenes-QA exact-match accuracy (%)")
    out = []
    for qtype, (h0, h1, both) in rows.items():
        out += [PaperFigure(f"val/qa/{qtype}_H0", h0, **info), PaperFigure(f"val/qa/{qtype}_H1", h1, **info)]
        out.append(PaperFigure(f"val/qa/{qtype}", both, **info))
    return out


def all_figures() -> tuple[PaperFigure, ...]:
    """Every registered family's published figures."""
    from occtrain.core.registry import families

    return tuple(fig for family in families().values() for fig in family.paper_figures)


def figures_for(metric: str) -> list[PaperFigure]:
    """The published figures comparable with ``metric`` (same words; a convention-less figure
    also matches a name that adds a convention word)."""
    words = metric_words(metric)
    bare = words - CONVENTION_WORDS
    out = []
    for fig in all_figures():
        key = metric_words(fig.metric)
        if key == words or (not key & CONVENTION_WORDS and key == bare):
            out.append(fig)
    return out
