"""``occtrain table``: a run's comparison table printed and rewritten (``report.compare``)."""

from __future__ import annotations

from pathlib import Path


def table(run_dir: str | Path) -> Path:
    """Print the run's comparison table, noting the stages not done yet; the table file."""
    from occtrain.progress import console
    from occtrain.report.compare import load_run_table, show_table

    rows, manifest = load_run_table(run_dir)
    pending = [
        r.stage for r in rows.rows if r.stage not in manifest.stages or manifest.stages[r.stage].status != "done"
    ]
    if pending:
        console.print(f"[yellow]note[/]: not done yet, shown as –: {', '.join(dict.fromkeys(pending))}")
    out = show_table(run_dir, rows, manifest)
    console.print(f"table -> {out}")
    return out
