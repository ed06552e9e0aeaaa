"""The command line: every command registers its own arguments the same way, in its own
module of ``occtrain.cli``, and parsing loads none of the libraries the bodies need."""

from __future__ import annotations

import argparse
import pkgutil
import subprocess
import sys

import occtrain.cli as cli


def _leaves(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> dict[tuple[str, ...], object]:
    """Every runnable command path (``data synth``, ``score qa``, ...) with the body it runs."""
    found: dict[tuple[str, ...], object] = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                found |= _leaves(child, (*path, name))
    if path and not found:
        found[path] = parser.get_default("func")
    return found


def test_each_cli_module_registers_its_commands_and_the_parser_lists_them_all():
    modules = {m.name for m in pkgutil.iter_modules(cli.__path__)}
    # data_import.py registers `data import` and `data export` under cli/data.py's group.
    assert {c.__name__.rsplit(".", 1)[1] for c in cli.COMMANDS} | {"data_import"} == modules
    assert "data_import" not in {c.__name__.rsplit(".", 1)[1] for c in cli.COMMANDS}
    assert all(callable(c.register) for c in cli.COMMANDS)
    leaves = _leaves(cli.build_parser())
    assert {"run", "validate", "eval", "drive", "report", "dashboard"} <= {p[0] for p in leaves}
    assert (
        ("data", "synth") in leaves
        and ("data", "import", "nuscenes") in leaves
        and ("score", "qa") in leaves
        and ("config", "reference") in leaves
    )
    # Each runnable command names its body, in the module that registered it.
    for path, func in leaves.items():
        assert callable(func) and func.__module__.startswith("occtrain.cli."), (path, func)


def test_parsing_loads_neither_torch_nor_lightning():
    code = (
        "import sys, occtrain.cli as c; c.build_parser().parse_args(['eval', 'runs/x/y']); "
        "print(sorted(m for m in ('torch', 'lightning', 'transformers') if m in sys.modules))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "[]"
