"""SparseOccVLA's published figures (arXiv:2601.06474), for the dashboard (see ``core.published``)."""

from __future__ import annotations

from occtrain.core.published import CAMERA, PLAN_CONVENTION, PaperFigure, horizons

#: The paper's forecast frames (Sec. 4.1): no camera mask, a scene's first 5 and last 7 frames left out.
TRIMMED = "no camera mask (stated); first 5 and last 7 frames of each scene excluded"
CAPTIONS = "OmniDrive-nuScenes captions (pycocoevalcap; the paper's table gives fractions, shown x100)"


def _figures() -> list[PaperFigure]:
    # Table 1 (right) forecasting from cameras, Table 2 planning, Table 1 (left) captions, Table 5 NuScenes-QA.
    f = horizons(
        "val/forecast_trimmed/occworld_mIoU_{h}",
        (15.86, 13.54, 11.72, 13.71),
        paper="SparseOccVLA",
        where="Table 1 right, 600 queries",
        setting=CAMERA,
        convention=TRIMMED,
    )
    plan = dict(paper="SparseOccVLA", setting=CAMERA, convention=PLAN_CONVENTION)
    f += horizons("val/plan/L2_{h}", (0.14, 0.22, 0.32, 0.23), where="Table 2, SparseOccVLA", **plan)
    f += horizons("val/plan/collision_{h}", (0.03, 0.12, 0.41, 0.19), where="Table 2, SparseOccVLA", **plan)
    for key, value in (("CIDEr", 0.796), ("METEOR", 0.388), ("ROUGE_L", 0.337)):
        f.append(
            PaperFigure(f"val/caption_{key}", value, "SparseOccVLA", "Table 1 left, 600 queries", CAMERA, CAPTIONS)
        )
    f.append(PaperFigure("val/qa/overall", 60.8, "SparseOccVLA", "Table 5", CAMERA, "NuScenes-QA accuracy (%)"))
    return f


PAPER_FIGURES: tuple[PaperFigure, ...] = tuple(_figures())
