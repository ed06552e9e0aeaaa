"""``occtrain data synth | shards | show | stats | check | import | export``: datasets synthesized,
sharded, drawn, measured, checked, imported from the public releases and exported as them (the
bodies in ``commands.data_*``)."""

from __future__ import annotations

import argparse

from occtrain.cli import data_import


def _cmd_synth(args: argparse.Namespace) -> int:
    from occtrain.commands.data_synth import synth

    synth(args.out, args.scenes, args.val_scenes, args.frames, args.seed, args.workers, args.cameras)
    return 0


def _cmd_shards(args: argparse.Namespace) -> int:
    from occtrain.commands.data_shards import shards

    kinds = None if args.kinds is None else [k.strip() for k in args.kinds.split(",") if k.strip()]
    shards(args.dataset, args.out, args.samples_per_shard, args.history, args.future, kinds, args.rebuild)
    return 0


def _cmd_show(args: argparse.Namespace) -> int:
    from occtrain.commands.data_show import show

    out = show(
        args.path,
        args.out,
        scene=args.scene,
        index=args.index,
        frames=args.frames,
        scale=args.scale,
        overwrite=args.overwrite,
    )
    print(out)
    return 0


def _cmd_stats(args: argparse.Namespace) -> int:
    from occtrain.commands.data_stats import show_stats

    show_stats(args.root, args.split, args.frames, args.json, args.chart)
    return 0


def _cmd_check(args: argparse.Namespace) -> int:
    from occtrain.commands.data_check import check

    return check(args.path)


def _register_synth(data: argparse._SubParsersAction) -> None:
    p = data.add_parser("synth", help="write the synthetic driving world in the Occ3D layout")
    p.add_argument("--out", required=True, help="dataset directory to create")
    p.add_argument("--scenes", type=int, default=4, help="train scenes (default 4)")
    p.add_argument("--val-scenes", type=int, default=2, help="val scenes (default 2)")
    p.add_argument("--frames", type=int, default=40, help="frames per scene at 2 Hz (default 40)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--cameras",
        default="72x128",
        metavar="HxW",
        help="the six cameras' image size, height x width pixels (default 72x128; 0x0: no cameras)",
    )
    p.add_argument(
        "--workers", type=int, default=None, help="processes writing scenes (default: one per core from 100 frames)"
    )
    p.set_defaults(func=_cmd_synth)


def register(sub: argparse._SubParsersAction) -> None:
    data = sub.add_parser("data", help="synthesize, shard, show and check datasets").add_subparsers(
        dest="action", required=True
    )
    _register_synth(data)

    p = data.add_parser("shards", help="write webdataset shards from a dataset")
    p.add_argument("dataset")
    p.add_argument("--out", required=True)
    p.add_argument("--samples-per-shard", type=int, default=64)
    p.add_argument(
        "--kinds",
        help="comma-separated: frames, clips (default: both, or frames alone when no scene is long enough for a clip)",
    )
    p.add_argument("--history", type=int, default=4, help="history frames per clip")
    p.add_argument("--future", type=int, default=6, help="future frames per clip")
    p.add_argument(
        "--rebuild",
        action="store_true",
        help="replace the shards --out holds (of another layout, a copy or an earlier state of the dataset); "
        "the old ones stay usable until the new ones are complete",
    )
    p.set_defaults(func=_cmd_shards)

    p = data.add_parser("show", help="bird's-eye picture of a frame (or a strip of frames)")
    p.add_argument("path", help="dataset root or a labels.npz file")
    p.add_argument("--out", default="bev.png")
    p.add_argument("--scene", help="scene name (default: the first scene)")
    p.add_argument("--index", type=int, default=0, help="frame index in the scene")
    p.add_argument("--frames", type=int, default=1, help="consecutive frames to draw side by side")
    p.add_argument("--scale", type=int, default=3, help="pixels per voxel")
    p.add_argument("--overwrite", action="store_true", help="replace --out when it exists")
    p.set_defaults(func=_cmd_show)

    p = data.add_parser(
        "stats", help="a dataset's voxel statistics beside Occ3D-nuScenes' (occupancy, masks, layers, class shares)"
    )
    p.add_argument("root", help="dataset root (annotations.json + gts/), real or synthesized")
    p.add_argument("--split", default="val", choices=("train", "val"))
    p.add_argument(
        "--frames", type=int, default=100, help="frames counted, spread evenly over the split (default 100; -1: all)"
    )
    p.add_argument("--json", metavar="FILE", help="also write the statistics and the reference figures as JSON")
    p.add_argument("--chart", metavar="PNG", help="also draw the class shares beside the reference as a bar chart")
    p.set_defaults(func=_cmd_stats)

    p = data.add_parser("check", help="validate a dataset or shard directory")
    p.add_argument("path")
    p.set_defaults(func=_cmd_check)
    data_import.register(data)
