"""``occtrain eval``: a stage's export scored on a split (``commands.evaluate``)."""

from __future__ import annotations

import argparse


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


def register(sub: argparse._SubParsersAction) -> None:
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
