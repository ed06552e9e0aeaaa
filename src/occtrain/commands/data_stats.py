"""``occtrain data stats``: a dataset's voxel statistics beside Occ3D-nuScenes', as tables
on stdout (where a pipe takes them whole), with the JSON and the class chart on request."""

from __future__ import annotations

import sys

from rich.console import Console
from rich.table import Table

from occtrain.data.stats import CLASS_FACTOR, class_chart, class_rows, dataset_stats, rows
from occtrain.formats.io import atomic_write_bytes, atomic_write_json, check_output, png_bytes
from occtrain.progress import console


def show_stats(root: str, split: str, frames: int, json_out: str | None = None, chart: str | None = None) -> None:
    # The tables are the command's result: stdout, where a pipe takes them whole (a pipe
    # has no width, and rich would wrap them at 80 columns).
    result = Console(width=None if sys.stdout.isatty() else 160)

    for path, flag in ((json_out, "--json"), (chart, "--chart")):
        if path:
            check_output(path, flag)  # before the counting, which reads every frame asked for
    stats = dataset_stats(root, split, frames)
    world = f", synthetic world {stats.world}" if stats.world else ""
    table = Table(title=f"{root}{world}: {split}, {stats.frames} frames (means over frames)")
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
    if json_out:
        console.print(f"statistics -> {atomic_write_json(json_out, stats.to_json())}")
    if chart:
        console.print(f"chart -> {atomic_write_bytes(chart, png_bytes(class_chart(stats)))}")
