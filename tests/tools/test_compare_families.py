"""tools/compare_families.py: each family's numbers come from the stage the table names,
beside that family's own baselines; a stage whose evaluation is missing or older than its
export is scored again; tokens per frame come from the world model's export."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from conftest import load_tool
from occtrain.formats.metrics_file import Provenance, write_metrics


@pytest.fixture()
def tool():
    return load_tool("compare_families")


def _stage(
    run: Path, name: str, export: dict | None = None, scores: dict | None = None, stale: bool = False, world: str = ""
) -> None:
    """A stage with an export and, with ``scores``, a whole-split eval (on ``world``, a
    version, with its provenance; without one, as evals before provenance wrote them)."""
    stage = run / name
    (stage / "export").mkdir(parents=True)
    (stage / "export" / "config.json").write_text(json.dumps(export or {}))
    if scores is not None:
        out = stage / "eval" / "val" / "metrics.json"
        out.parent.mkdir(parents=True)
        if world:
            provenance = Provenance("occtrain eval", "val", {"qa": [4, 4]}, "abc", world, f"occtrain world {world}")
            write_metrics(out, scores, provenance)
        else:
            out.write_text(json.dumps(scores))
        if stale:
            os.utime(out, (1, 1))


def _vocab(**kw) -> dict:
    return {"vocab": {"scene_hw": [10, 10], "patch": 0, "codebook_sizes": [128], "extra": [], **kw}, "world": {}}


def test_each_cell_reads_its_stage_beside_the_familys_own_baseline(tool, tmp_path, monkeypatch):
    run = tmp_path / "sparseoccvla"
    forecast = {f"forecast_occworld_mIoU_{h}": v for h, v in (("1s", 3.0), ("2s", 2.0), ("3s", 1.0))}
    copy = {f"baseline_copy_forecast_occworld_mIoU_{h}": v for h, v in (("1s", 30.0), ("2s", 20.0), ("3s", 10.0))}
    world = {
        **forecast,
        **copy,
        "qa_overall": 55.0,
        "baseline_prior_qa_overall": 44.0,
        "caption_CIDEr": 0.7,
        "baseline_typical_caption_CIDEr": 0.8,
    }
    extra = [f"<global_{j}>" for j in range(12)] + ["<ego>"]
    _stage(run, "stage3", _vocab(scene_hw=[64, 1], patch=1, codebook_sizes=[], extra=extra), world, world="v4")
    _stage(
        run,
        "planner",
        {},
        {"plan_L2_stp3_avg": 1.5, "plan_collision_stp3_avg": 0.25, "constant_velocity_L2_stp3_avg": 0.5},
        stale=True,
    )
    manifest = {
        "stages": {"stage3": {"metrics": {"train_step_s": 0.5, "train_peak_rss_mb": 900.0}}, "planner": {"metrics": {}}}
    }
    (run / "manifest.json").write_text(json.dumps(manifest))
    scored = []
    monkeypatch.setattr(tool, "_cli", lambda *args: scored.append(args))
    family = next(f for f in tool.FAMILIES if f.showcase.recipe == "sparseoccvla")

    r = tool.row(family, tmp_path)

    # stage3's evaluation is newer than its export; the planner's is older, and records no provenance.
    assert scored == [("eval", str(run / "planner"))]
    assert r["tokens_per_frame"] == "64 + 12 global"
    table = tool.markdown([r])
    assert "3.0 / 2.0 / 1.0 vs 30.0 / 20.0 / 10.0 (stage3)" in table
    assert "1.50 m vs 0.50 m; 0.25 % (planner)" in table
    assert "55.0 % vs 44.0 % (stage3)" in table and "0.700 vs 0.800 (stage3)" in table
    assert "stage3 500 ms / 900 MB; planner - ms / - MB" in table
    # The planner's eval was (in this test) scored before evals recorded their world: the table says so.
    assert table.startswith("# Four families on one world\n\nWorld: unrecorded, v4 (")
    # Each family's line says what produced its numbers (no seed recorded in this manifest: "?").
    line = "- SparseOccVLA: recipe sparseoccvla, training seed ?, code ?, world occtrain world v4 [abc], scored "
    assert line in table


def test_tokens_per_frame_follow_each_layout(tool, tmp_path):
    _stage(tmp_path, "codes", _vocab(codebook_sizes=[128, 128]))
    _stage(tmp_path, "patches", _vocab(patch=2))
    _stage(tmp_path, "images", {"vocab": {"image": True}, "world": {"occvla": {"image_tokens": [3, 4]}}})
    assert tool._tokens_per_frame(tmp_path / "codes") == "200"
    assert tool._tokens_per_frame(tmp_path / "patches") == "25"
    assert tool._tokens_per_frame(tmp_path / "images") == "72 image (6 cameras x 3 x 4)"
