"""Occ-LLM's published figures (arXiv:2502.06419), for the dashboard (see ``core.published``)."""

from __future__ import annotations

from occtrain.core.published import GT_OCC, OCCWORLD_SETTING, PLAN_CONVENTION, PaperFigure, horizons


def _figures() -> list[PaperFigure]:
    # Table III (MS-VAE reconstruction) and Table I (forecasting and planning, occupancy input).
    occllm = dict(paper="Occ-LLM", setting=GT_OCC, convention=OCCWORLD_SETTING)
    f = [
        PaperFigure("val/occworld_mIoU", 71.08, where="Table III, MS-VAE (+Motion Separation)", **occllm),
        PaperFigure("val/occworld_IoU", 62.74, where="Table III, MS-VAE (+Motion Separation)", **occllm),
    ]
    f += horizons("val/forecast/occworld_IoU_{h}", (36.65, 32.14, 28.77, 32.52), where="Table I, Ours (Occ.)", **occllm)
    f += horizons(
        "val/forecast/occworld_mIoU_{h}", (24.02, 21.65, 17.29, 20.99), where="Table I, Ours (Occ.)", **occllm
    )
    f += horizons(
        "val/plan/L2_{h}",
        (0.12, 0.24, 0.49, 0.28),
        paper="Occ-LLM",
        where="Table I, Ours (Occ.)",
        setting=GT_OCC,
        convention=PLAN_CONVENTION,
    )
    return f


PAPER_FIGURES: tuple[PaperFigure, ...] = tuple(_figures())
