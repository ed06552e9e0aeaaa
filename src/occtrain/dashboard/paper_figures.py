"""The papers' published figures (real nuScenes / Occ3D-nuScenes), keyed by occtrain's metric names.

Every number below was read off a table of a seed paper (../shared/seeds/); ``where`` names the
table and row. They are what the methods reach on real data with full-size models: the dashboard
shows them beside a run's metrics for orientation, never as a target for the synthetic world.

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

#: Words that do not change what a metric measures ("val/qa/overall" is "val/qa_acc").
NEUTRAL_WORDS = frozenset({
    "val", "test", "plan", "planning", "by", "type", "hop", "overall", "all", "acc", "accuracy",
    # occtrain's planning variants (OccLLaMA's M0-M3 ways of planning) all measure the same thing
    "direct", "alternate", "cot",
})
#: Words naming a metric convention: a paper figure without one matches each of them.
CONVENTION_WORDS = frozenset({"occ3d", "occworld", "stp3", "uniad"})
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


def _horizons(metric: str, values: tuple[float, float, float, float], **info: str) -> list[PaperFigure]:
    """Figures at 1 s, 2 s, 3 s and their average; ``metric`` has a ``{h}`` slot."""
    return [PaperFigure(metric.format(h=h), v, **info) for h, v in zip(("1s", "2s", "3s", "avg"), values)]


def _qa_types(paper: str, where: str, setting: str, rows: dict[str, tuple[float, float, float]]) -> list[PaperFigure]:
    info = dict(paper=paper, where=where, setting=setting, convention="NuScenes-QA exact-match accuracy (%)")
    out = []
    for qtype, (h0, h1, both) in rows.items():
        out += [PaperFigure(f"val/qa/{qtype}_H0", h0, **info), PaperFigure(f"val/qa/{qtype}_H1", h1, **info)]
        out.append(PaperFigure(f"val/qa/{qtype}", both, **info))
    return out


def _table() -> list[PaperFigure]:
    f: list[PaperFigure] = []
    occllama = dict(paper="OccLLaMA", setting=GT_OCC, convention=OCCWORLD_SETTING)
    # OccLLaMA Table II: tokenizer reconstruction and forecasting, Ours-O and the baselines it lists.
    f += [
        PaperFigure("val/occworld_mIoU", 75.20, where="Table II, Ours (Recon.)", **occllama),
        PaperFigure("val/occworld_IoU", 63.76, where="Table II, Ours (Recon.)", **occllama),
        PaperFigure("val/occworld_mIoU", 66.38, where="Table II, OccWorld-O tokenizer (Recon.)", **occllama),
        PaperFigure("val/occworld_IoU", 62.29, where="Table II, OccWorld-O tokenizer (Recon.)", **occllama),
    ]
    f += _horizons("val/forecast/occworld_mIoU_{h}", (25.05, 19.49, 15.26, 19.93), where="Table II, Ours-O", **occllama)
    f += _horizons("val/forecast/occworld_IoU_{h}", (34.56, 28.53, 24.41, 29.17), where="Table II, Ours-O", **occllama)
    f += _horizons("val/forecast/occworld_mIoU_{h}", (14.91, 10.54, 8.52, 11.33), where="Table II, Copy&Paste baseline", **occllama)
    f += _horizons("val/forecast/occworld_IoU_{h}", (24.47, 19.77, 17.31, 20.52), where="Table II, Copy&Paste baseline", **occllama)
    # OccLLaMA Table III: planning, Ours-O.
    plan = dict(paper="OccLLaMA", setting=GT_OCC, convention=PLAN_CONVENTION)
    f += _horizons("val/plan/L2_{h}", (0.25, 0.64, 1.50, 0.80), where="Table III, Ours-O", **plan)
    f += _horizons("val/plan/collision_{h}", (0.03, 0.37, 0.96, 0.45), where="Table III, Ours-O", **plan)
    # OccLLaMA Table I: NuScenes-QA by hop.
    qa = dict(paper="OccLLaMA", setting=GT_OCC, convention="NuScenes-QA exact-match accuracy (%)")
    f += [
        PaperFigure("val/qa/H0", 55.3, where="Table I, Ours", **qa),
        PaperFigure("val/qa/H1", 51.9, where="Table I, Ours", **qa),
        PaperFigure("val/qa/overall", 53.0, where="Table I, Ours", **qa),
    ]

    # Occ-LLM Table III (MS-VAE reconstruction) and Table I (forecasting and planning, occupancy input).
    occllm = dict(paper="Occ-LLM", setting=GT_OCC, convention=OCCWORLD_SETTING)
    f += [
        PaperFigure("val/occworld_mIoU", 71.08, where="Table III, MS-VAE (+Motion Separation)", **occllm),
        PaperFigure("val/occworld_IoU", 62.74, where="Table III, MS-VAE (+Motion Separation)", **occllm),
    ]
    f += _horizons("val/forecast/occworld_IoU_{h}", (36.65, 32.14, 28.77, 32.52), where="Table I, Ours (Occ.)", **occllm)
    f += _horizons("val/forecast/occworld_mIoU_{h}", (24.02, 21.65, 17.29, 20.99), where="Table I, Ours (Occ.)", **occllm)
    f += _horizons("val/plan/L2_{h}", (0.12, 0.24, 0.49, 0.28), paper="Occ-LLM", where="Table I, Ours (Occ.)", setting=GT_OCC, convention=PLAN_CONVENTION)

    # OccVLA: Table 1 planning, Table 3 NuScenes-QA (its own row and OccLLaMA's as it lists it), Table 4 meta actions.
    f += _horizons("val/plan/L2_{h}", (0.18, 0.26, 0.40, 0.28), paper="OccVLA", where="Table 1, Ours", setting=CAMERA, convention=PLAN_CONVENTION)
    f += _qa_types(
        "OccVLA", "Table 3, Ours (3B)", CAMERA,
        {"exist": (87.4, 81.7, 84.3), "count": (22.6, 21.2, 21.9), "object": (73.6, 51.2, 54.5),
         "status": (62.6, 57.9, 59.5), "comparison": (79.2, 66.0, 67.2)},
    )
    f.append(PaperFigure("val/qa/overall", 59.5, "OccVLA", "Table 3, Ours (3B)", CAMERA, "NuScenes-QA exact-match accuracy (%)"))
    f += _qa_types(
        "OccLLaMA", "OccVLA Table 3, row OccLLaMA3.1", GT_OCC,
        {"exist": (82.9, 79.2, 80.9), "count": (19.2, 19.2, 19.2), "object": (64.8, 43.1, 46.3),
         "status": (51.0, 46.1, 47.8), "comparison": (76.5, 65.6, 66.6)},
    )
    meta = dict(paper="OccVLA", setting=CAMERA, convention="meta-action accuracy (%) on OccVLA's own nuScenes annotations")
    f += [
        PaperFigure("val/meta_action/speed_acc", 54.83, where="Table 4, with occupancy, Speed", **meta),
        PaperFigure("val/meta_action/direction_acc", 77.95, where="Table 4, with occupancy, 'Trajectory' (directional action)", **meta),
        PaperFigure("val/meta_action/mean", 66.39, where="Table 4, with occupancy, Avg. of speed and trajectory", **meta),
        PaperFigure("val/meta_action/acc", 43.08, where="Table 4, with occupancy, Overall", **meta),
    ]

    # SparseOccVLA: Table 1 (right) forecasting from cameras, Table 2 planning, Table 5 NuScenes-QA.
    sparse_fc = "no camera mask (stated); first 5 and last 7 frames of each scene excluded"
    f += _horizons("val/forecast/occworld_mIoU_{h}", (15.86, 13.54, 11.72, 13.71), paper="SparseOccVLA", where="Table 1 right, 600 queries", setting=CAMERA, convention=sparse_fc)
    sp = dict(paper="SparseOccVLA", setting=CAMERA, convention=PLAN_CONVENTION)
    f += _horizons("val/plan/L2_{h}", (0.14, 0.22, 0.32, 0.23), where="Table 2, SparseOccVLA", **sp)
    f += _horizons("val/plan/collision_{h}", (0.03, 0.12, 0.41, 0.19), where="Table 2, SparseOccVLA", **sp)
    f.append(PaperFigure("val/qa/overall", 60.8, "SparseOccVLA", "Table 5", CAMERA, "NuScenes-QA accuracy (%)"))
    return f


PAPER_FIGURES: tuple[PaperFigure, ...] = tuple(_table())


def figures_for(metric: str) -> list[PaperFigure]:
    """The published figures comparable with ``metric`` (same words; a convention-less figure
    also matches a name that adds a convention word)."""
    words = metric_words(metric)
    bare = words - CONVENTION_WORDS
    out = []
    for fig in PAPER_FIGURES:
        key = metric_words(fig.metric)
        if key == words or (not key & CONVENTION_WORDS and key == bare):
            out.append(fig)
    return out
