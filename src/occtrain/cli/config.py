"""``occtrain config show | reference``: configs resolved, and every key a recipe may set."""

from __future__ import annotations

import argparse


def _cmd_config_show(args: argparse.Namespace) -> int:
    from occtrain.config import load_config, schema_for, to_yaml

    cfg: object = load_config(schema_for(args.file, args.group), args.file, args.overrides)
    print(to_yaml(cfg), end="")
    return 0


def _cmd_config_reference(args: argparse.Namespace) -> int:
    from occtrain.stages.registered_schemas import config_reference

    print(config_reference(), end="")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    config = sub.add_parser("config", help="inspect configs").add_subparsers(dest="action", required=True)
    show = config.add_parser("show", help="print a config file resolved with overrides")
    show.add_argument("file")
    show.add_argument("overrides", nargs="*", help="key=value overrides, e.g. trainer.max_steps=10")
    show.add_argument("--group", help="config group of FILE (default: its directory name)")
    show.set_defaults(func=_cmd_config_show)
    reference = config.add_parser("reference", help="every key a recipe may set, with type, default and doc (Markdown)")
    reference.set_defaults(func=_cmd_config_reference)
