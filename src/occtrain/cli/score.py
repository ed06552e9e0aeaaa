"""``occtrain score {occupancy,forecast,planning,captions,qa}``: its arguments; the
scoring is ``commands.score``'s, loaded with the first score, not with the parser."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

from occtrain.formats.io import check_output
from occtrain.metrics.conventions import CONVENTIONS, FORECAST_FILE, FORECAST_HORIZONS, horizon_label


def _cmd_occupancy(args: argparse.Namespace) -> int:
    from occtrain.commands import score

    result = score.score_occupancy(
        Path(args.pred), Path(args.gt), args.convention, not args.no_mask, args.split, args.allow_missing
    )
    score.emit(result, args.out)
    return 0


def _cmd_forecast(args: argparse.Namespace) -> int:
    from occtrain.commands import score

    score.emit(score.score_forecast(Path(args.pred), Path(args.gt)), args.out)
    return 0


def _cmd_planning(args: argparse.Namespace) -> int:
    from occtrain.commands import score

    score.emit(score.score_planning(Path(args.pred), Path(args.gt), args.allow_missing), args.out)
    return 0


def _cmd_captions(args: argparse.Namespace) -> int:
    from occtrain.commands import score

    score.emit(score.score_captions(Path(args.pred), Path(args.ref), args.allow_missing), args.out)
    return 0


def _cmd_qa(args: argparse.Namespace) -> int:
    from occtrain.commands import score

    score.emit(score.score_qa(Path(args.pred), Path(args.questions)), args.out)
    return 0


def _out_checked_first(cmd: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """``cmd`` with its ``--out`` checked before it scores (minutes on a whole release)."""

    def checked(args: argparse.Namespace) -> int:
        if args.out:
            check_output(args.out, "--out")
        return cmd(args)

    return checked


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``occtrain score {occupancy,forecast,planning,captions,qa}``."""
    score = subparsers.add_parser("score", help="score your own predictions with the papers' metric conventions")
    sub = score.add_subparsers(dest="what", required=True, metavar="WHAT")
    _add_occupancy_scores(sub)
    _add_plan_and_text_scores(sub)


def _add_score(sub: argparse._SubParsersAction, name: str, summary: str, func: Any, pred_help: str) -> Any:
    p = sub.add_parser(name, help=summary)
    p.add_argument("--pred", required=True, help=pred_help)
    p.set_defaults(func=_out_checked_first(func))
    return p


def _add_out(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", metavar="FILE", help="also write the JSON result to FILE (atomically)")


def _add_occupancy_scores(sub: argparse._SubParsersAction) -> None:
    """``score occupancy`` and ``score forecast``."""
    add, out = partial(_add_score, sub), _add_out
    p = add(
        "occupancy",
        "semantic occupancy mIoU/IoU (Occ3D convention by default)",
        _cmd_occupancy,
        "directory of <scene>/<token>/labels.npz with 'semantics'",
    )
    p.add_argument(
        "--gt", required=True, help="dataset root (annotations.json + gts/) or a plain <scene>/<token>/labels.npz tree"
    )
    p.add_argument(
        "--split", choices=("train", "val"), help="score one split of a dataset root (default: every sample)"
    )
    p.add_argument(
        "--convention",
        choices=CONVENTIONS,
        default="occ3d",
        help="occ3d (default) or occworld (all voxels, absent class = 100)",
    )
    p.add_argument("--no-mask", action="store_true", help="occ3d: count every voxel, not only mask_camera ones")
    p.add_argument(
        "--allow-missing", action="store_true", help="score the samples that have a prediction, skip the rest"
    )
    out(p)

    p = add(
        "forecast",
        f"occupancy forecasting mIoU/IoU at {', '.join(horizon_label(h) for h in FORECAST_HORIZONS)} (OccWorld "
        "convention)",
        _cmd_forecast,
        f"directory of <scene>/<token>/{FORECAST_FILE} with 'semantics' (T, 200, 200, 16)",
    )
    p.add_argument("--gt", required=True, help="dataset root: its scene order gives the future frames")
    out(p)


def _add_plan_and_text_scores(sub: argparse._SubParsersAction) -> None:
    """``score planning``, ``score captions`` and ``score qa``."""
    add, out = partial(_add_score, sub), _add_out
    p = add(
        "planning",
        "planning L2 and collision rate, ST-P3 and UniAD conventions",
        _cmd_planning,
        "JSON {sample_token: [[x, y] x 6]}",
    )
    p.add_argument(
        "--gt",
        required=True,
        help='JSON {sample_token: {"traj": [[x, y] x 6], "mask": [0/1 x 6], "agents": [[[x, y, l, w, yaw], ...] x 6]}}',
    )
    p.add_argument(
        "--allow-missing", action="store_true", help="score the samples that have a prediction, skip the rest"
    )
    out(p)

    p = add(
        "captions",
        "BLEU-1..4, METEOR, ROUGE-L, CIDEr-D (pycocoevalcap; needs Java)",
        _cmd_captions,
        'JSON {id: "caption"}',
    )
    p.add_argument("--ref", required=True, help='JSON {id: ["reference", ...]}')
    p.add_argument("--allow-missing", action="store_true", help="score the ids that have a caption, skip the rest")
    out(p)

    p = add(
        "qa",
        "NuScenes-QA exact-match accuracy, by type and by hop",
        _cmd_qa,
        "JSON list of answer strings, in the order of the questions file",
    )
    p.add_argument("--questions", required=True, help='NuScenes-QA JSON {"questions": [...]}')
    out(p)
