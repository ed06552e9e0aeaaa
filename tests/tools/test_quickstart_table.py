"""tools/quickstart_table.py: the quickstart's seeds table comes from the runs' eval files,
states their world, mixes no worlds."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from conftest import REPO


@pytest.fixture(scope="module")
def tool():
    spec = importlib.util.spec_from_file_location("quickstart_table", REPO / "tools" / "quickstart_table.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def _run(root: Path, qa: float, world: str = "v4", seed: int = 0) -> Path:
    (root / "manifest.json").parent.mkdir(parents=True)
    entry = {"code_version": "0.1.0+abc1234", "config": {"trainer": {"seed": seed}}, "wall_time_s": 100.0 + seed}
    manifest = {"stages": {"instruct": entry}}
    (root / "manifest.json").write_text(json.dumps(manifest))
    out = root / "instruct" / "eval" / "val"
    out.mkdir(parents=True)
    (out / "metrics.json").write_text(json.dumps({"qa_overall": qa, "baseline_prior_qa_overall": 43.2}))
    (out / "world.json").write_text(json.dumps({"world": "k", "world_version": world}))
    return root


def test_seeds_side_by_side_with_mean_spread_baseline_and_world(tool, tmp_path):
    runs = [_run(tmp_path / f"s{i}", qa, seed=i) for i, qa in enumerate((50.0, 60.0, 55.0))]
    table = tool.table(runs)
    assert table.startswith("World v4; whole val split")
    assert f"- run 2: `{runs[2]}`, training seed 2, code 0.1.0+abc1234, data key k, scored " in table
    row = next(line for line in table.splitlines() if "NuScenes-QA accuracy" in line and line.startswith("| instruct"))
    assert "| 50.0 / 60.0 / 55.0 | 55.0 (50.0 to 60.0) | commonest answer per type 43.2 |" in row
    assert "forecast" not in table  # a stage no run scored has no row
    assert "| instruct | 100 / 101 / 102 | 101 |" in table and "| all stages | 100 / 101 / 102 | 101 |" in table


def test_runs_scored_on_different_worlds_are_refused(tool, tmp_path):
    runs = [_run(tmp_path / "a", 50.0, "v3"), _run(tmp_path / "b", 51.0, "v4")]
    with pytest.raises(SystemExit, match="different worlds"):
        tool.table(runs)


def test_not_a_run_directory_is_one_line(tool, tmp_path, capsys):
    assert tool.main([str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip() == f"error: not a run directory (no manifest.json): {tmp_path}"
