"""``occtrain plan-memory``: memory per GPU of a recipe's LLM stages (``commands.plan_memory``)."""

from __future__ import annotations

import argparse


def _cmd_plan_memory(args: argparse.Namespace) -> int:
    from occtrain.commands.plan_memory import format_plans, plan_recipe

    plans = plan_recipe(args.recipe, args.overrides, args.gpus, args.seq_len, args.checkpointing, args.gpu_memory)
    print(format_plans(plans, args.seq_len, args.gpu_memory, args.checkpointing))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
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
