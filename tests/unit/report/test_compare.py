"""A recipe's ``table:``: validation in one line, the markdown, and the real CLI end to end."""

from __future__ import annotations

import json

import pytest

from conftest import run_cli, write_hand_dataset
from occtrain.config.recipe import ComparisonTable, TableColumn, TableRow
from occtrain.errors import ConfigError
from occtrain.formats.manifest import Manifest, StageEntry
from occtrain.report.compare import build_table, print_table, to_markdown
from occtrain.run.planning import load_recipe

STAGES = """
stages:
  - {name: first, kind: probe, optim: {lr: 0.2}, trainer: {max_steps: 8}}
  - {name: second, kind: probe, consumes: [first], optim: {lr: 0.2}, trainer: {max_steps: 2}}
"""

TABLE = """
table:
  title: Probe vs paper
  note: Accuracy over the val split's subsampled voxels (%).
  columns:
    - {name: acc, metric: val/acc, scale: 100, digits: 1}
    - {name: loss, metric: val/loss}
  rows:
    - {stage: first, label: probe (first), paper: {acc: 97.5}}
    - {stage: second}
"""


def write_recipe(tmp_path, table: str, data: str = "data") -> str:
    path = tmp_path / "probe.yaml"
    path.write_text(
        f"name: probe\nplugins: [plugins.probe_stage]\nruns_root: {tmp_path / 'runs'}\n"
        f"data: {{root: {data}, batch_size: 2, samples_per_shard: 4, history: 1, future: 1}}\n"
        "trainer: {val_check_interval: 2, limit_val_batches: 1, log_every_n_steps: 1}\n" + STAGES + table
    )
    return str(path)


@pytest.mark.parametrize(
    "table, message",
    [
        (
            "table: {columns: [{name: acc, metric: val/acc}], rows: [{stage: first}, {stage: foo}]}",
            "table.rows[1].stage in {path}: 'foo' is not a stage of this recipe; stages are first, second",
        ),
        (
            "table: {columns: [{name: acc, metric: val/acc}], rows: [{stage: first, paper: {mIoU: 3}}]}",
            "table.rows[0].paper.mIoU in {path}: 'mIoU' is not a column; columns are acc",
        ),
        (
            "table: {columns: [], rows: [{stage: first}]}",
            "table.columns in {path} is empty; a table needs at least one column and one row",
        ),
        (
            "table: {columns: [{name: acc, metric: val/acc}]}",
            "table.rows in {path} is empty; a table needs at least one column and one row",
        ),
        (
            "table: {columns: [{name: acc}], rows: [{stage: first}]}",
            "table.columns[0] in {path} has no 'metric:'; a column needs a name and a metric",
        ),
        (
            "table: {columns: [{name: acc, metric: a}, {name: acc, metric: b}], rows: [{stage: first}]}",
            "table.columns[1].name in {path}: 'acc' names two columns",
        ),
        (
            "table: {columns: [{name: acc, metric: a, digits: -1}], rows: [{stage: first}]}",
            "table.columns[0].digits in {path} is -1; decimals are 0 or more",
        ),
        ("table: {colums: [], rows: []}", "unknown key 'table.colums' in {path}; did you mean 'columns'?"),
    ],
)
def test_a_bad_table_is_refused_in_one_line_naming_the_key(tmp_path, table, message):
    path = write_recipe(tmp_path, table)
    with pytest.raises(ConfigError) as err:
        load_recipe(path)
    assert str(err.value) == message.format(path=path)


def test_a_recipe_without_a_table_has_none(tmp_path):
    recipe, _ = load_recipe(write_recipe(tmp_path, ""))
    assert recipe.table is None


HAND = ComparisonTable(
    title="Tokenizer ablation",
    note="OccWorld convention: every voxel, no mask.\n",
    columns=[
        TableColumn("IoU", "val/occworld_IoU"),
        TableColumn("mIoU", "val/occworld_mIoU"),
        TableColumn("params (M)", "params", scale=1e-6, digits=1),
    ],
    rows=[
        TableRow("occllama", label="OccLLaMA | ours [base]", paper={"IoU": 65.11, "mIoU": 75.2}),
        TableRow("vqvae", paper={"IoU": 62.29, "mIoU": None}),
        TableRow("absent"),
    ],
)

HAND_MARKDOWN = """\
**Tokenizer ablation**

| variant | IoU | mIoU | params (M) | paper IoU | paper mIoU |
|---|---:|---:|---:|---:|---:|
| OccLLaMA \\| ours [base] | 41.23 | 20.00 | 1.2 | 65.11 | 75.20 |
| vqvae | 38.50 | – | 2.0 | 62.29 | – |
| absent | – | – | – | – | – |

OccWorld convention: every voxel, no mask.
"""


def test_markdown_shows_ours_then_the_papers_with_scale_digits_and_dashes():
    # vqvae logged no mIoU, 'absent' never ran; no row has a paper params figure, so no such column.
    metrics = {
        "occllama": {"val/occworld_IoU": 41.234, "val/occworld_mIoU": 19.996, "params": 1_234_567},
        "vqvae": {"val/occworld_IoU": 38.5, "val/occworld_mIoU": None, "params": 2e6},
    }
    assert to_markdown(HAND, build_table(HAND, metrics)) == HAND_MARKDOWN


def test_from_a_manifest_only_done_stages_count(tmp_path):
    manifest = Manifest(
        tmp_path / "manifest.json",
        stages={
            "occllama": StageEntry("tokenizer", "done", metrics={"val/occworld_IoU": 41.234}),
            "vqvae": StageEntry("tokenizer", "failed", metrics={"val/occworld_IoU": 38.5}),
        },
    )
    rows = build_table(HAND, manifest)
    assert [r.ours[0] for r in rows] == [41.234, None, None]


def test_the_printed_table_is_not_squeezed_off_a_terminal(monkeypatch, capsys):
    monkeypatch.setenv("COLUMNS", "30")
    print_table(HAND, build_table(HAND, {}))
    lines = capsys.readouterr().out.splitlines()
    assert "paper mIoU" in lines[2] and "OccLLaMA | ours [base]" in lines[4] and "75.20" in lines[4]
    assert lines[-1] == "OccWorld convention: every voxel, no mask."


def test_a_run_writes_the_table_only_when_every_stage_is_done(tmp_path, capsys):
    from occtrain.run.runner import _write_table

    recipe, _ = load_recipe(write_recipe(tmp_path, TABLE))
    manifest = Manifest(
        tmp_path / "manifest.json",
        stages={
            "first": StageEntry("probe", "done", metrics={"val/acc": 0.5}),
            "second": StageEntry("probe", "failed"),
        },
    )
    (tmp_path / "table.md").write_text("stale: second was retrained since\n")
    _write_table(tmp_path, recipe, manifest)
    assert not (tmp_path / "table.md").exists() and "Probe vs paper" not in capsys.readouterr().out
    manifest.stages["second"] = StageEntry("probe", "done", metrics={"val/acc": 0.25})
    _write_table(tmp_path, recipe, manifest)
    assert "| second | 25.0 | – | – |" in (tmp_path / "table.md").read_text()
    assert "Probe vs paper" in capsys.readouterr().out


@pytest.mark.slow
def test_a_run_prints_and_writes_its_table_and_occtrain_table_rewrites_it(tmp_path):
    data = write_hand_dataset(tmp_path / "ds", train=1, val=1, frames=4)
    run_dir = tmp_path / "run"
    res = run_cli("run", write_recipe(tmp_path, TABLE, str(data)), "--run-dir", str(run_dir))
    assert res.returncode == 0, res.stderr[-2000:]
    metrics = json.loads((run_dir / "manifest.json").read_text())["stages"]
    acc = [f"{100 * metrics[s]['metrics']['val/acc']:.1f}" for s in ("first", "second")]
    table_md = (run_dir / "table.md").read_text()
    assert table_md.splitlines()[2:6] == [
        "| variant | acc | loss | paper acc |",
        "|---|---:|---:|---:|",
        f"| probe (first) | {acc[0]} | – | 97.5 |",
        f"| second | {acc[1]} | – | – |",
    ]
    for text in ("Probe vs paper", "paper acc", "probe (first)", acc[0], "97.5", "Accuracy over the val split"):
        assert text in res.stdout
    assert "Comparison with the paper" in (run_dir / "dashboard.html").read_text()

    (run_dir / "table.md").unlink()
    again = run_cli("table", str(run_dir))
    assert again.returncode == 0, again.stderr
    assert "probe (first)" in again.stdout and (run_dir / "table.md").read_text() == table_md

    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "pipeline.yaml").write_text("name: plain\n")
    for target, says in (("plain", "has no table: section"), ("nowhere", "not a run directory")):
        res = run_cli("table", str(tmp_path / target))
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1 and says in res.stderr, res.stderr
