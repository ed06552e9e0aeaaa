"""A recipe's comparison table: each row a stage's final metrics beside a paper's figures.

``occtrain run`` prints it and writes ``RUN_DIR/table.md`` once every stage is done;
``occtrain table RUN_DIR`` does both again from the run's saved recipe (``pipeline.yaml``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from occtrain.config import load_config
from occtrain.config.recipe import ComparisonTable, RecipeConfig
from occtrain.errors import ConfigError
from occtrain.formats.io import atomic_write_text
from occtrain.formats.manifest import Manifest
from occtrain.progress import print_wide

TABLE_FILE = "table.md"
#: A cell with no figure: the stage did not log the metric, is not done, or the paper did not report it.
NO_FIGURE = "–"
LABEL_HEADER = "variant"


@dataclass
class Row:
    """One variant's figures, in the table's column order; None where there is none."""

    label: str
    ours: list[float | None]  # scaled
    paper: list[float | None]


def check_table(table: ComparisonTable | None, stages: list[str], source: str) -> None:
    """Refuse, in one line naming the key, a table this recipe cannot fill."""
    if table is None:
        return
    for key, entries in (("columns", table.columns), ("rows", table.rows)):
        if not entries:
            raise ConfigError(f"table.{key} in {source} is empty; a table needs at least one column and one row")
    names: list[str] = []
    for i, col in enumerate(table.columns):
        for key in ("name", "metric"):
            if OmegaConf.is_missing(col, key):
                raise ConfigError(f"table.columns[{i}] in {source} has no '{key}:'; a column needs a name and a metric")
        if col.digits < 0:
            raise ConfigError(f"table.columns[{i}].digits in {source} is {col.digits}; decimals are 0 or more")
        if col.name in names:
            raise ConfigError(f"table.columns[{i}].name in {source}: '{col.name}' names two columns")
        names.append(col.name)
    for i, row in enumerate(table.rows):
        if OmegaConf.is_missing(row, "stage"):
            raise ConfigError(f"table.rows[{i}] in {source} has no 'stage:'; stages are {', '.join(stages)}")
        if row.stage not in stages:
            raise ConfigError(
                f"table.rows[{i}].stage in {source}: '{row.stage}' is not a stage of this recipe; stages are "
                f"{', '.join(stages)}"
            )
        for key in row.paper:
            if key not in names:
                raise ConfigError(
                    f"table.rows[{i}].paper.{key} in {source}: '{key}' is not a column; columns are {', '.join(names)}"
                )


def _number(value: Any) -> float | None:
    # JSON holds an undefined metric as null; NaN says no more than a missing one.
    if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
        return None
    return float(value)


def build_table(table: ComparisonTable, results: Manifest | Mapping[str, Mapping[str, Any]]) -> list[Row]:
    """The figures of each ``table.rows`` entry: ours (scaled) and the paper's.

    ``results`` is a run's manifest (only its done stages count) or stage name -> final metrics.
    """
    if isinstance(results, Manifest):
        results = {name: e.metrics for name, e in results.stages.items() if e.status == "done"}
    rows = []
    for row in table.rows:
        metrics = results.get(row.stage) or {}
        ours = [_number(metrics.get(c.metric)) for c in table.columns]
        rows.append(
            Row(
                row.label or row.stage,
                [None if v is None else v * c.scale for v, c in zip(ours, table.columns)],
                [_number(row.paper.get(c.name)) for c in table.columns],
            )
        )
    return rows


def _cells(table: ComparisonTable, rows: list[Row]) -> tuple[list[str], list[list[str]]]:
    """Header and body as text, shared by the markdown and the terminal table: the label, ours
    per column, then the paper's per column that some row reports."""
    cols = list(table.columns)
    reported = [j for j in range(len(cols)) if any(r.paper[j] is not None for r in rows)]

    def fmt(value: float | None, digits: int) -> str:
        return NO_FIGURE if value is None else f"{value:.{digits}f}"

    header = [LABEL_HEADER, *(c.name for c in cols), *(f"paper {cols[j].name}" for j in reported)]
    body = [
        [
            r.label,
            *(fmt(v, c.digits) for v, c in zip(r.ours, cols)),
            *(fmt(r.paper[j], cols[j].digits) for j in reported),
        ]
        for r in rows
    ]
    return header, body


def to_markdown(table: ComparisonTable, rows: list[Row]) -> str:
    """The table in GitHub markdown, its title above in bold and its note below."""
    header, body = _cells(table, rows)

    def line(cells: list[str]) -> str:
        return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"

    out = [f"**{table.title}**", ""] if table.title else []
    out += [line(header), "|---|" + "---:|" * (len(header) - 1), *(line(cells) for cells in body)]
    if table.note.strip():
        out += ["", table.note.strip()]
    return "\n".join(out) + "\n"


def print_table(table: ComparisonTable, rows: list[Row], console: Any = None) -> None:
    """Print the table with rich, on stdout unless ``console`` is given: it is a run's result."""
    from rich.console import Console
    from rich.table import Table
    from rich.text import Text

    header, body = _cells(table, rows)
    # Text, not str: a label like "ours [base]" is not rich markup.
    view = Table(title=Text(table.title) if table.title else None)
    view.add_column(Text(header[0]))
    for name in header[1:]:
        view.add_column(Text(name), justify="right")
    for cells in body:
        view.add_row(*map(Text, cells))
    console = console or Console(soft_wrap=True)
    print_wide(view, console)
    if table.note.strip():
        console.print(Text(table.note.strip()), soft_wrap=True)


def show_table(run_dir: str | Path, table: ComparisonTable, manifest: Manifest) -> Path:
    """Print the run's table and write it to ``RUN_DIR/table.md`` (atomically); returns that path."""
    rows = build_table(table, manifest)
    print_table(table, rows)
    return atomic_write_text(Path(run_dir) / TABLE_FILE, to_markdown(table, rows))


def load_run_table(run_dir: str | Path) -> tuple[ComparisonTable, Manifest]:
    """The table of a run's saved recipe and the run's manifest; a run without one is a ConfigError."""
    pipeline = Path(run_dir) / "pipeline.yaml"
    if not pipeline.is_file():
        raise ConfigError(
            f"{run_dir}: no pipeline.yaml, so not a run directory; pass runs/<name> as written by `occtrain run`"
        )
    recipe = load_config(RecipeConfig, pipeline)
    if recipe.table is None:
        raise ConfigError(
            f"{pipeline} has no table: section; add one to the recipe and run it again (done stages are skipped)"
        )
    check_table(recipe.table, [s.name for s in recipe.stages], str(pipeline))
    return recipe.table, Manifest.load(Path(run_dir), writable=False)
