"""OccLLaMA's published figures (arXiv:2409.03272), for the dashboard (see ``core.published``)."""

from __future__ import annotations

from occtrain.core.published import GT_OCC, OCCWORLD_SETTING, PLAN_CONVENTION, PaperFigure, horizons


def _figures() -> list[PaperFigure]:
    f: list[PaperFigure] = []
    occllama = dict(paper="OccLLaMA", setting=GT_OCC, convention=OCCWORLD_SETTING)
    # Table II: tokenizer reconstruction and forecasting, Ours-O and the baselines it lists.
    f += [
        PaperFigure("val/occworld_mIoU", 75.20, where="Table II, Ours (Recon.)", **occllama),
        PaperFigure("val/occworld_IoU", 63.76, where="Table II, Ours (Recon.)", **occllama),
        PaperFigure("val/occworld_mIoU", 66.38, where="Table II, OccWorld-O tokenizer (Recon.)", **occllama),
        PaperFigure("val/occworld_IoU", 62.29, where="Table II, OccWorld-O tokenizer (Recon.)", **occllama),
    ]
    f += horizons("val/forecast/occworld_mIoU_{h}", (25.05, 19.49, 15.26, 19.93), where="Table II, Ours-O", **occllama)
    f += horizons("val/forecast/occworld_IoU_{h}", (34.56, 28.53, 24.41, 29.17), where="Table II, Ours-O", **occllama)
    f += horizons(
        "val/forecast/occworld_mIoU_{h}", (14.91, 10.54, 8.52, 11.33), where="Table II, Copy&Paste baseline", **occllama
    )
    f += horizons(
        "val/forecast/occworld_IoU_{h}", (24.47, 19.77, 17.31, 20.52), where="Table II, Copy&Paste baseline", **occllama
    )
    # Table III: planning, Ours-O.
    plan = dict(paper="OccLLaMA", setting=GT_OCC, convention=PLAN_CONVENTION)
    f += horizons("val/plan/L2_{h}", (0.25, 0.64, 1.50, 0.80), where="Table III, Ours-O", **plan)
    f += horizons("val/plan/collision_{h}", (0.03, 0.37, 0.96, 0.45), where="Table III, Ours-O", **plan)
    # Table I: NuScenes-QA by hop.
    qa = dict(paper="OccLLaMA", setting=GT_OCC, convention="NuScenes-QA exact-match accuracy (%)")
    f += [
        PaperFigure("val/qa/H0", 55.3, where="Table I, Ours", **qa),
        PaperFigure("val/qa/H1", 51.9, where="Table I, Ours", **qa),
        PaperFigure("val/qa/overall", 53.0, where="Table I, Ours", **qa),
    ]
    return f


PAPER_FIGURES: tuple[PaperFigure, ...] = tuple(_figures())
