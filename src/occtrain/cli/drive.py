"""``occtrain drive``: a stage's planner driven closed loop (``commands.drive``)."""

from __future__ import annotations

import argparse


def _cmd_drive(args: argparse.Namespace) -> int:
    from occtrain.commands.drive import drive, drive_dir, print_summary

    summary = drive(args.stage_dir, args.scenes, args.seed, args.seconds, args.workers, args.save_videos)
    print_summary(summary, f"{args.stage_dir}: {args.scenes} routes of {args.seconds:g} s (seed {args.seed})")
    print(f"results -> {drive_dir(args.stage_dir, args.seed, args.seconds)}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "drive",
        help="drive a stage's planner closed loop in the synthetic world (reactive traffic) beside the expert, "
        "constant velocity, constant acceleration and standing still; CARLA driving score and NAVSIM PDM score",
    )
    p.add_argument("stage_dir", help="RUN_DIR/STAGE (a pretrain, instruct or planner stage)")
    p.add_argument("--scenes", type=int, default=8, help="routes to drive (default 8)")
    p.add_argument(
        "--seed", type=int, default=1000, help="seed the routes are drawn from (default 1000: no training world's)"
    )
    p.add_argument("--seconds", type=float, default=20.0, help="length of each episode (default 20, at most 40)")
    p.add_argument("--workers", type=int, default=1, help="episodes driven side by side in processes (default 1)")
    p.add_argument("--save-videos", metavar="DIR", help="also write a bird's-eye GIF of every episode")
    p.set_defaults(func=_cmd_drive)
