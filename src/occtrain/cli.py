"""The ``occtrain`` command: argument parsing only; the work happens in the library."""

from __future__ import annotations

import argparse
import re
import sys
from typing import Any

from occtrain.errors import ConfigError, OcctrainError
from occtrain.version import __version__


def _cmd_config_show(args: argparse.Namespace) -> int:
    from occtrain.config import load_config, schema_for, to_yaml

    cfg: object = load_config(schema_for(args.file, args.group), args.file, args.overrides)
    print(to_yaml(cfg), end="")
    return 0


def _cmd_config_reference(args: argparse.Namespace) -> int:
    from occtrain.stages.registered_schemas import config_reference

    print(config_reference(), end="")
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    if args.dry_run:
        return _cmd_validate(args)
    from occtrain.run.runner import is_rank_zero, run

    run_dir = run(args.recipe, args.overrides, run_dir=args.run_dir, only=args.only, restart=args.restart)
    if is_rank_zero():
        print(f"run directory: {run_dir}")
    return 0


def _cmd_validate(args: argparse.Namespace) -> int:
    from occtrain.formats.manifest import Manifest
    from occtrain.run.checks import check_run

    check = check_run(args.recipe, args.overrides, run_dir=args.run_dir, only=args.only, restart=args.restart)
    manifest = Manifest.load(check.run_dir, writable=False)
    n = len(check.planned)
    print(f"{args.recipe}: ok, {n} stage{'' if n == 1 else 's'}; nothing was written")
    for p in check.planned:
        entry = manifest.stages.get(p.spec.name)
        status = "to retrain" if p.spec.name in check.restarted else entry.status if entry else "pending"
        family = f", {p.family}" if p.family else ""
        consumes = f", consumes {', '.join(p.spec.consumes)}" if p.spec.consumes else ""
        print(f"  {p.spec.name:12s} {p.spec.kind}{family}: {p.trainer.max_steps} steps{consumes} [{status}]")
    print(check.data)
    print(f"run directory: {check.run_dir}")
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from occtrain.commands.evaluate import eval_metrics_file, evaluate, print_metrics

    tasks = [t.strip() for t in args.tasks.split(",") if t.strip()] if args.tasks else None
    metrics = evaluate(
        args.stage_dir,
        args.split,
        tasks,
        args.save_predictions,
        args.samples,
        args.batch_size,
        args.data,
        args.blank_cameras,
    )
    where = (f" of {args.data}" if args.data else "") + (", its cameras blanked" if args.blank_cameras else "")
    print_metrics(metrics, f"{args.stage_dir} on {args.split}{where}")
    print(f"metrics -> {eval_metrics_file(args.stage_dir, args.split, args.data, blank_cameras=args.blank_cameras)}")
    return 0


def _cmd_drive(args: argparse.Namespace) -> int:
    from occtrain.commands.drive import drive, drive_dir, print_summary

    summary = drive(args.stage_dir, args.scenes, args.seed, args.seconds, args.workers, args.save_videos)
    print_summary(summary, f"{args.stage_dir}: {args.scenes} routes of {args.seconds:g} s (seed {args.seed})")
    print(f"results -> {drive_dir(args.stage_dir, args.seed, args.seconds)}")
    return 0


def _cmd_plan_memory(args: argparse.Namespace) -> int:
    from occtrain.commands.memory_plan import format_plans, plan_recipe

    plans = plan_recipe(args.recipe, args.overrides, args.gpus, args.seq_len, args.checkpointing, args.gpu_memory)
    print(format_plans(plans, args.seq_len, args.gpu_memory, args.checkpointing))
    return 0


def _cmd_table(args: argparse.Namespace) -> int:
    from occtrain.progress import console
    from occtrain.report.compare import load_run_table, show_table

    table, manifest = load_run_table(args.run_dir)
    pending = [
        r.stage for r in table.rows if r.stage not in manifest.stages or manifest.stages[r.stage].status != "done"
    ]
    if pending:
        console.print(f"[yellow]note[/]: not done yet, shown as –: {', '.join(dict.fromkeys(pending))}")
    console.print(f"table -> {show_table(args.run_dir, table, manifest)}")
    return 0


def _cmd_data_synth(args: argparse.Namespace) -> int:
    from occtrain.config import SynthConfig
    from occtrain.config.groups import check_seed
    from occtrain.data.synthesize import synthesize

    check_seed(args.seed, "--seed")  # named as the user typed it; check_synth_config would say data.synth.seed
    cfg = SynthConfig(
        train_scenes=args.scenes, val_scenes=args.val_scenes, frames_per_scene=args.frames, seed=args.seed
    )
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers {args.workers}: give at least 1 process")
    synthesize(args.out, cfg, workers=args.workers)
    return 0


def _cmd_data_shards(args: argparse.Namespace) -> int:
    from occtrain.data.shards import no_clips_note, write_shards
    from occtrain.formats.io import check_output
    from occtrain.progress import console

    check_output(args.out, "--out", kind="dir")  # an unwritable --out fails now, not after minutes of sharding
    kinds = None if args.kinds is None else [k.strip() for k in args.kinds.split(",") if k.strip()]
    index = write_shards(
        args.dataset, args.out, args.samples_per_shard, args.history, args.future, kinds, rebuild=args.rebuild
    )
    if "clips" in index.get("missing", {}):
        console.print(f"note: {no_clips_note(index['missing']['clips'])}", markup=False)
    for kind, splits in index["kinds"].items():
        for split, entries in splits.items():
            n = sum(e["samples"] for e in entries)
            console.print(f"{kind:6s} {split:5s}: {n:5d} samples in {len(entries)} shards")
    console.print(f"shards -> {args.out}")
    return 0


def _cmd_data_show(args: argparse.Namespace) -> int:
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


def _cmd_data_stats(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from occtrain.data.stats import CLASS_FACTOR, class_chart, class_rows, dataset_stats, rows
    from occtrain.formats.io import atomic_write_bytes, atomic_write_json, check_output, png_bytes
    from occtrain.progress import console

    # The tables are the command's result: stdout, where a pipe takes them whole (a pipe
    # has no width, and rich would wrap them at 80 columns).
    result = Console(width=None if sys.stdout.isatty() else 160)

    for path, flag in ((args.json, "--json"), (args.chart, "--chart")):
        if path:
            check_output(path, flag)  # before the counting, which reads every frame asked for
    stats = dataset_stats(args.root, args.split, args.frames)
    world = f", synthetic world {stats.world}" if stats.world else ""
    table = Table(title=f"{args.root}{world}: {args.split}, {stats.frames} frames (means over frames)")
    for column in ("statistic", "this dataset", "Occ3D-nuScenes (one frame)", "target", "met"):
        table.add_column(column, justify="left" if column == "statistic" else "right")
    for row in rows(stats):
        table.add_row(*row)
    result.print(table)
    classes = Table(title="class shares of the occupied voxels (all counted frames together)")
    for column in ("class", "this dataset", "Occ3D-nuScenes train", "ratio", f"within {CLASS_FACTOR:g}x"):
        classes.add_column(column, justify="left" if column == "class" else "right")
    for row in class_rows(stats):
        classes.add_row(*row)
    result.print(classes)
    present = stats.targets()["all_classes_present"]
    result.print(
        "every class present: "
        f"{'yes' if present else 'no: ' + ', '.join(n for n, v in stats.class_shares.items() if v == 0)}"
    )
    if args.json:
        console.print(f"statistics -> {atomic_write_json(args.json, stats.to_json())}")
    if args.chart:
        console.print(f"chart -> {atomic_write_bytes(args.chart, png_bytes(class_chart(stats)))}")
    return 0


def _cmd_data_check(args: argparse.Namespace) -> int:
    from occtrain.commands.data_check import check_dataset, check_shards, looks_like_shards

    problems = check_shards(args.path) if looks_like_shards(args.path) else check_dataset(args.path)
    for p in problems:
        print(p)
    what = "shards" if looks_like_shards(args.path) else "dataset"
    if problems:
        print(f"{len(problems)} problem(s) in {what} {args.path}", file=sys.stderr)
        return 1
    print(f"{what} {args.path}: ok")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="occtrain", description=__doc__)
    parser.add_argument("--version", action="version", version=f"occtrain {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_run_commands(sub)
    _add_data_commands(sub)

    from occtrain.commands.dashboard import register as register_dashboard
    from occtrain.commands.report import register as register_report
    from occtrain.commands.score import register as register_score

    register_score(sub)
    register_report(sub)
    register_dashboard(sub)
    return parser


def _add_run_commands(sub: Any) -> None:
    """``run`` and ``validate``, then the commands that read a run (``_add_run_readers``)."""
    p = sub.add_parser("run", help="run a recipe's stages in order (skips done stages, resumes cut-off ones)")
    p.add_argument("recipe", help="recipe YAML, e.g. recipes/quickstart.yaml")
    p.add_argument("overrides", nargs="*", help="key=value overrides, e.g. trainer.max_steps=10 trainer.devices=2")
    p.add_argument("--run-dir", help="run directory (default: runs/<recipe name>)")
    p.add_argument("--only", metavar="STAGE", help="run just this stage (its inputs must be done)")
    p.add_argument("--restart", metavar="STAGE", help="retrain this stage and every stage after it")
    p.add_argument(
        "--dry-run", action="store_true", help="check everything `run` checks first, then stop (as `occtrain validate`)"
    )
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser(
        "validate",
        help="check a recipe end to end (schema, kinds, families, handoffs, ranges, run directory, data) "
        "without writing anything",
    )
    p.add_argument("recipe", help="recipe YAML, e.g. recipes/quickstart.yaml")
    p.add_argument("overrides", nargs="*", help="key=value overrides, as for run")
    p.add_argument("--run-dir", help="run directory (default: runs/<recipe name>)")
    p.add_argument("--only", metavar="STAGE", help="as for run")
    p.add_argument("--restart", metavar="STAGE", help="as for run")
    p.set_defaults(func=_cmd_validate)
    _add_run_readers(sub)
    _add_drive(sub)


def _add_drive(sub: Any) -> None:
    """``drive``."""
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


def _add_eval(sub: Any) -> None:
    p = sub.add_parser(
        "eval",
        help="score a stage's export on a split: a tokenizer's reconstruction, a world model's generations "
        "(the papers' metrics)",
    )
    p.add_argument("stage_dir", help="RUN_DIR/STAGE")
    p.add_argument("--split", default="val")
    p.add_argument(
        "--tasks",
        default="",
        help="comma-separated tasks of the model's family, e.g. forecasting,qa (default: those the stage trained on)",
    )
    p.add_argument(
        "--save-predictions",
        metavar="DIR",
        help="also write predictions in the formats `occtrain score` reads (a DIR with an earlier eval's is refused)",
    )
    p.add_argument(
        "--samples",
        type=int,
        default=-1,
        help="score a fixed seeded subset of N items per task (default -1: every question, chain of thought and plan)",
    )
    p.add_argument("--batch-size", type=int, default=16, help="clips generated together in one batch (default 16)")
    p.add_argument(
        "--data", metavar="DIR", help="score on this dataset instead of the run's (e.g. a world from another seed)"
    )
    p.add_argument(
        "--blank-cameras",
        action="store_true",
        help="score with every camera image black (a view of the dataset made once in the run's cache): a stage "
        "that learned from its cameras scores lower",
    )
    p.set_defaults(func=_cmd_eval)


def _add_run_readers(sub: Any) -> None:
    """``eval``, ``plan-memory``, ``table`` and ``config``."""
    _add_eval(sub)
    p = sub.add_parser(
        "plan-memory",
        help="memory per GPU of a recipe's LLM stages under DDP and sharding, from model configs alone "
        "(nothing downloaded or trained)",
    )
    p.add_argument("recipe", help="recipe YAML, e.g. recipes/scale/occllama_llama8b.yaml")
    p.add_argument("overrides", nargs="*", help="key=value overrides, as for run (e.g. trainer.precision=bf16-mixed)")
    p.add_argument("--gpus", type=int, default=8, help="ranks to shard over (default 8, the papers' machines)")
    p.add_argument("--seq-len", type=int, default=2048, help="tokens per training sequence (default 2048)")
    p.add_argument(
        "--gpu-memory", type=float, metavar="GIB", help="say whether each strategy fits a GPU of this many GiB"
    )
    p.add_argument("--checkpointing", action="store_true", help="with activation checkpointing of the decoder layers")
    p.set_defaults(func=_cmd_plan_memory)

    p = sub.add_parser(
        "table", help="print a run's comparison table (the recipe's table:) and rewrite RUN_DIR/table.md"
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run directory, e.g. runs/tokenizer_ablation")
    p.set_defaults(func=_cmd_table)

    config = sub.add_parser("config", help="inspect configs").add_subparsers(dest="action", required=True)
    show = config.add_parser("show", help="print a config file resolved with overrides")
    show.add_argument("file")
    show.add_argument("overrides", nargs="*", help="key=value overrides, e.g. trainer.max_steps=10")
    show.add_argument("--group", help="config group of FILE (default: its directory name)")
    show.set_defaults(func=_cmd_config_show)
    reference = config.add_parser("reference", help="every key a recipe may set, with type, default and doc (Markdown)")
    reference.set_defaults(func=_cmd_config_reference)


def _add_data_commands(sub: Any) -> None:
    """``data synth | shards | show | stats | check``."""
    data = sub.add_parser("data", help="synthesize, shard, show and check datasets").add_subparsers(
        dest="action", required=True
    )
    p = data.add_parser("synth", help="write the synthetic driving world in the Occ3D layout")
    p.add_argument("--out", required=True, help="dataset directory to create")
    p.add_argument("--scenes", type=int, default=4, help="train scenes (default 4)")
    p.add_argument("--val-scenes", type=int, default=2, help="val scenes (default 2)")
    p.add_argument("--frames", type=int, default=40, help="frames per scene at 2 Hz (default 40)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--workers", type=int, default=None, help="processes writing scenes (default: one per core from 100 frames)"
    )
    p.set_defaults(func=_cmd_data_synth)

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
    p.set_defaults(func=_cmd_data_shards)

    p = data.add_parser("show", help="bird's-eye picture of a frame (or a strip of frames)")
    p.add_argument("path", help="dataset root or a labels.npz file")
    p.add_argument("--out", default="bev.png")
    p.add_argument("--scene", help="scene name (default: the first scene)")
    p.add_argument("--index", type=int, default=0, help="frame index in the scene")
    p.add_argument("--frames", type=int, default=1, help="consecutive frames to draw side by side")
    p.add_argument("--scale", type=int, default=3, help="pixels per voxel")
    p.add_argument("--overwrite", action="store_true", help="replace --out when it exists")
    p.set_defaults(func=_cmd_data_show)

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
    p.set_defaults(func=_cmd_data_stats)

    p = data.add_parser("check", help="validate a dataset or shard directory")
    p.add_argument("path")
    p.set_defaults(func=_cmd_data_check)


_WORKER_ERROR = re.compile(r"^occtrain\.errors\.\w+Error: (.*)$", re.MULTILINE)


def _one_line(err: OcctrainError) -> str:
    """The user-facing line of an error, also when it crossed a DataLoader worker."""
    # The message alone: a library that appends context to an exception's args (webdataset
    # adds its stream and url) would otherwise print as a tuple.
    text = err.args[0] if err.args and isinstance(err.args[0], str) else str(err)
    found = _WORKER_ERROR.findall(text)
    return found[-1] if found else text.splitlines()[0] if text else type(err).__name__


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    # Overrides may come after options too (`run R --only x a.b=1`): argparse's positional
    # list stops at the first option, so the rest arrive as extras.
    args, extra = parser.parse_known_args(argv)
    if extra:
        if not hasattr(args, "overrides") or any(e.startswith("-") for e in extra):
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        args.overrides = [*(args.overrides or []), *extra]
    from occtrain.run.control import Interrupted

    try:
        return int(args.func(args) or 0)
    except Interrupted as stop:
        print(f"interrupted: {stop}", file=sys.stderr)
        return stop.exit_code
    except OcctrainError as err:
        print(f"error: {_one_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
