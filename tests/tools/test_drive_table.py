"""tools/drive_table.py: every stage's drive beside the baselines of the same routes, and
whether open-loop L2 orders the drivers as the driving score does."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import load_tool
from occtrain.errors import DataError


@pytest.fixture()
def tool():
    return load_tool("drive_table")


def _drive(run: Path, stage: str, l2: float, score: float, routes: int = 2, **timing) -> Path:
    out = run / stage / "drive" / "seed1000-20s"
    out.mkdir(parents=True)
    drivers = {
        stage: {"open_loop_L2_stp3_avg": l2, "driving_score": score, "collisions": 0.5},
        "expert": {"open_loop_L2_stp3_avg": 0.0, "driving_score": 100.0},
        "constant_velocity": {"open_loop_L2_stp3_avg": 1.2, "driving_score": 20.0},
        "stand_still": {"open_loop_L2_stp3_avg": 5.0, "driving_score": 0.0},
    }
    summary = {
        "stage": stage,
        "routes": routes,
        "seed": 1000,
        "seconds": 20,
        "drivers": drivers,
        "conventions": {"driving_score": "CARLA", "pdm_score": "NAVSIM"},
        **timing,
    }
    (out / "summary.json").write_text(json.dumps(summary))
    manifest = {"name": run.name, "stages": {stage: {"code_version": "0.1.0+abc", "config": {"trainer": {"seed": 3}}}}}
    (run / "manifest.json").write_text(json.dumps(manifest))
    return run / stage


def test_the_table_puts_each_stage_beside_the_routes_baselines(tool, tmp_path):
    stages = [
        _drive(tmp_path / "a", "planner", 0.4, 60.0, wall_s=252.4, workers=2, resumed=0),
        _drive(tmp_path / "b", "instruct", 0.9, 80.0, wall_s=30.0, workers=1, resumed=3),
    ]
    table = tool.markdown(tool.summaries(stages, 2, 1000, 20.0, drive=False))
    rows = [line for line in table.split("Open-loop L2")[0].splitlines() if line.startswith("| ")][1:]
    assert [r.split(" | ")[0] for r in rows] == [
        "| a/planner (seed 3)",
        "| b/instruct (seed 3)",
        "| expert",
        "| constant_velocity",
        "| stand_still",
    ]
    assert rows[0].startswith("| a/planner (seed 3) | - | - | 0.40 | - | 60.0 |")  # who planned: not recorded here
    assert "recipe a, training seed 3, code 0.1.0+abc, data the routes of seed 1000" in table
    assert str(tmp_path) not in table  # runs are named by recipe and seed, never by a path here
    # How long a drive took is told only when it was one whole drive, not a resumed one.
    assert "(driven in 4 min 12 s by 2 workers)" in table and "driven in 0 min 30 s" not in table
    # L2 order: expert, a, b, cv, still; driving-score order: expert, b, a, cv, still: one pair of ten swapped.
    assert "Kendall's tau 0.80 over 5 drivers" in table
    assert "1 of 10 pairs are ordered the other way round closed loop:" in table
    assert "| a/planner (seed 3) | b/instruct (seed 3) | 0.50 | 20.0 |" in table
    assert "Constant acceleration drives exactly as" not in table  # no such baseline here


def test_constant_acceleration_driving_as_constant_velocity_is_said(tool, tmp_path):
    stage = _drive(tmp_path / "a", "planner", 0.4, 60.0)
    summary = json.loads((stage / "drive" / "seed1000-20s" / "summary.json").read_text())
    cv = summary["drivers"]["constant_velocity"]
    summary["drivers"]["constant_acceleration"] = cv | {"open_loop_L2_stp3_avg": 0.8}
    (stage / "drive" / "seed1000-20s" / "summary.json").write_text(json.dumps(summary))
    table = tool.markdown(tool.summaries([stage], 2, 1000, 20.0, drive=False))
    assert "Constant acceleration drives exactly as constant velocity closed loop" in table
    summary["drivers"]["constant_acceleration"]["driving_score"] = 21.0
    (stage / "drive" / "seed1000-20s" / "summary.json").write_text(json.dumps(summary))
    table = tool.markdown(tool.summaries([stage], 2, 1000, 20.0, drive=False))
    assert "Constant acceleration drives exactly as" not in table


def test_stages_driven_on_other_routes_are_refused(tool, tmp_path):
    stages = [_drive(tmp_path / "a", "planner", 0.4, 60.0), _drive(tmp_path / "b", "planner", 0.9, 80.0, routes=3)]
    with pytest.raises(DataError, match="different routes"):
        tool.markdown(tool.summaries(stages, 2, 1000, 20.0, drive=False))


def test_a_missing_drive_is_said_without_driving(tool, tmp_path, monkeypatch, capsys):
    with pytest.raises(DataError, match="summary.json is missing"):
        tool.summaries([tmp_path / "run" / "planner"], 2, 1000, 20.0, drive=False)
    monkeypatch.setattr("sys.argv", ["drive_table.py", str(tmp_path / "run" / "planner"), "--no-drive"])
    assert tool.main() == 2  # one line and exit 2, as occtrain's commands (it was SystemExit's 1)
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "summary.json is missing" in err


def test_many_swapped_pairs_are_counted_and_the_widest_shown(tool):
    # Seven drivers whose L2 order is the driving score's reversed: all 21 pairs disagree.
    table = [(f"d{i}", {"open_loop_L2_stp3_avg": 0.1 * i, "driving_score": 10.0 * i}) for i in range(7)]
    swaps = tool.swapped_pairs(table)
    assert len(swaps) == 21 and swaps[0].score_gap == 60.0 and (swaps[0].closer, swaps[0].drives_better) == ("d0", "d6")
    text = tool.swaps_table(swaps, 21)
    assert text.startswith("21 of 21 pairs are ordered the other way round closed loop; the 5 with the widest")
    assert len([line for line in text.splitlines() if line.startswith("| d")]) == tool.WIDEST_SWAPS
