"""OccVLA's published figures (arXiv:2509.05578), for the dashboard (see ``core.published``): its own,
and OccLLaMA's NuScenes-QA row as OccVLA's Table 3 lists it."""

from __future__ import annotations

from occtrain.core.published import CAMERA, GT_OCC, PLAN_CONVENTION, PaperFigure, horizons, qa_types


def _figures() -> list[PaperFigure]:
    # Table 1 planning, Table 3 NuScenes-QA, Table 4 meta actions.
    f = horizons(
        "val/plan/L2_{h}",
        (0.18, 0.26, 0.40, 0.28),
        paper="OccVLA",
        where="Table 1, Ours",
        setting=CAMERA,
        convention=PLAN_CONVENTION,
    )
    f += qa_types(
        "OccVLA",
        "Table 3, Ours (3B)",
        CAMERA,
        {
            "exist": (87.4, 81.7, 84.3),
            "count": (22.6, 21.2, 21.9),
            "object": (73.6, 51.2, 54.5),
            "status": (62.6, 57.9, 59.5),
            "comparison": (79.2, 66.0, 67.2),
        },
    )
    f.append(
        PaperFigure(
            "val/qa/overall", 59.5, "OccVLA", "Table 3, Ours (3B)", CAMERA, "NuScenes-QA exact-match accuracy (%)"
        )
    )
    f += qa_types(
        "OccLLaMA",
        "OccVLA Table 3, row OccLLaMA3.1",
        GT_OCC,
        {
            "exist": (82.9, 79.2, 80.9),
            "count": (19.2, 19.2, 19.2),
            "object": (64.8, 43.1, 46.3),
            "status": (51.0, 46.1, 47.8),
            "comparison": (76.5, 65.6, 66.6),
        },
    )
    meta = dict(
        paper="OccVLA", setting=CAMERA, convention="meta-action accuracy (%) on OccVLA's own nuScenes annotations"
    )
    f += [
        PaperFigure("val/meta_action/speed_acc", 54.83, where="Table 4, with occupancy, Speed", **meta),
        PaperFigure(
            "val/meta_action/direction_acc",
            77.95,
            where="Table 4, with occupancy, 'Trajectory' (directional action)",
            **meta,
        ),
        PaperFigure(
            "val/meta_action/mean", 66.39, where="Table 4, with occupancy, Avg. of speed and trajectory", **meta
        ),
        PaperFigure("val/meta_action/acc", 43.08, where="Table 4, with occupancy, Overall", **meta),
    ]
    return f


PAPER_FIGURES: tuple[PaperFigure, ...] = tuple(_figures())
