"""The run dashboard: ``RUN_DIR/dashboard.html``, one self-contained page (no network, no CDN).

What it reads from a run directory (the layout ``formats.manifest`` and docs/recipes.md describe):

- ``manifest.json`` (status, attempts, wall time, metrics, code version per stage) and ``pipeline.yaml``;
- ``<stage>/logs/csv/metrics.csv``: Lightning's CSVLogger file (columns ``step``, ``epoch``,
  ``train/...``, ``val/...``, ``lr-...``; each row sets only some of them), drawn as curves vs step;
- ``<stage>/metrics.json``: the stage's final metrics (name -> number), tabled by the convention
  their names carry (occ3d, occworld, stp3, uniad) with the papers' published figures beside them;
- ``<stage>/samples/index.json`` with PNGs beside it, written by stages through :func:`write_samples`::

      {"images": [{"file": "sample_0.png", "caption": "val scene-0001 frame 4: ..."}],
       "texts":  [{"task": "qa" | "cot" | ..., "prompt": "...", "prediction": "...", "reference": "..."}]}

  :func:`bev_comparison` makes the usual picture for it: labelled ground truth / reconstruction /
  forecast panels in the Occ3D colours.

Anything a stage lacks (not run, failed, no log) is shown as such; only a missing run directory or
manifest is an error.
"""

from __future__ import annotations

import time
from pathlib import Path

from occtrain.dashboard.samples import bev_comparison, read_samples, write_samples
from occtrain.formats.io import atomic_write_text, check_output

DASHBOARD_FILE = "dashboard.html"

__all__ = ["DASHBOARD_FILE", "bev_comparison", "read_samples", "write_dashboard", "write_samples"]


def write_dashboard(run_dir: Path, out: Path | None = None) -> Path:
    """Write the dashboard of ``run_dir`` (to ``run_dir/dashboard.html`` unless ``out``); returns its path."""
    from occtrain.dashboard.page import render_page
    from occtrain.dashboard.run_view import load_run, read_data

    run = load_run(Path(run_dir))
    out = Path(out) if out is not None else Path(run_dir) / DASHBOARD_FILE
    # Before the page is drawn: a run's figures take a while, and counting its dataset
    # keeps what it counted in the run directory, which a refused --out must leave alone.
    check_output(out, "--out")
    run.data = read_data(run.run_dir, run.pipeline_yaml)
    return atomic_write_text(out, render_page(run, generated=time.time()))
