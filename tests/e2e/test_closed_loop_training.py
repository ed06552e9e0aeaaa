"""Closed-loop training through the real CLI: ``recipes/closed_loop.yaml`` over a copy of
the tiny quickstart run trains its dagger stage alone (the quickstart's stages done, the
same configs), drives each round's routes, aggregates the labelled frames as a dataset in
the stage directory, resumes bit for bit after a kill -9 during a round's driving, and its
export is scored and driven as the planner's."""

from __future__ import annotations

import json
import os
import shutil
import signal
import time
from pathlib import Path

import pytest

from conftest import run_cli, start_cli
from quickstart_run import export_tensors, shared_quickstart_run, tiny_overrides

pytestmark = pytest.mark.slow

#: Two rounds of two 3 s routes, driven in two worker processes, and two steps each; the
#: planning head trained on the logged meta action (the tiny instruct model generates none
#: that parses), so its loss moves.
DAGGER = [
    "stages[3].model.train_meta=ground_truth",
    "stages[5].trainer.max_steps=4",
    "stages[5].trainer.val_check_interval=2",
    "stages[5].trainer.limit_val_batches=1",
    "stages[5].model.rounds=2",
    "stages[5].model.steps_per_round=2",
    "stages[5].model.routes_per_round=2",
    "stages[5].model.workers=2",
    "stages[5].model.seconds=3",
    "stages[5].model.aggregate_share=0.5",
    "stages[5].model.max_new_text_tokens=32",
]


def _args(quickstart: Path, run_dir: Path, restart: bool = True) -> list[str]:
    """The closed-loop recipe over a copy of the quickstart run, its planner retrained (with
    the stages after it) on the logged meta action; without ``restart``, a rerun."""
    return [
        "run",
        "recipes/closed_loop.yaml",
        *tiny_overrides(quickstart.parent / "data", steps=5),
        *DAGGER,
        "--run-dir",
        str(run_dir),
        *(["--restart", "planner"] if restart else []),
    ]


def _copy(quickstart: Path, to: Path) -> Path:
    shutil.copytree(quickstart, to, ignore=shutil.ignore_patterns(".lock"))
    return to


@pytest.fixture(scope="module")
def closed_loop(tmp_path_factory) -> tuple[Path, Path]:
    quickstart = shared_quickstart_run(tmp_path_factory)
    run_dir = _copy(quickstart, tmp_path_factory.mktemp("closed_loop") / "run")
    res = run_cli(*_args(quickstart, run_dir))
    assert res.returncode == 0, res.stderr[-3000:]
    return quickstart, run_dir


def test_the_stage_trains_alone_over_the_quickstart_and_aggregates_a_dataset(closed_loop):
    quickstart, run_dir = closed_loop
    stages = json.loads((run_dir / "manifest.json").read_text())["stages"]
    assert stages["closed_loop"]["status"] == "done"
    # The quickstart's stages before the planner were done with the same configs: not retrained.
    before = json.loads((quickstart / "manifest.json").read_text())["stages"]
    for name in ("tokenizer", "pretrain", "instruct"):
        assert stages[name]["config_hash"] == before[name]["config_hash"] and stages[name]["attempts"] == 1
    stage = run_dir / "closed_loop"
    routes = sorted((stage / "dagger" / "routes").glob("*.json"))
    scenes = ["round00-route00", "round00-route01", "round01-route00", "round01-route01"]
    assert [r.stem for r in routes] == scenes
    records = [json.loads(r.read_text()) for r in routes]
    assert [r["beta"] for r in records] == [0.5, 0.5, 0.25, 0.25]
    # Each round's routes were driven by that round's weights, in the workers that loaded them.
    assert records[0]["policy"] == records[1]["policy"] != records[2]["policy"] == records[3]["policy"]
    assert records[0]["route_seed"] != records[1]["route_seed"]
    assert all(r["frames"] == r["policy_frames"] + r["expert_frames"] == 6 for r in records)
    assert not list((stage / "dagger" / "policies").glob("*"))  # the weights handed to the workers are gone
    # The aggregate is a dataset: every frame's labels on disk, its future the expert's plan.
    from occtrain.data.layout import DatasetIndex

    index = DatasetIndex.open(stage / "dagger" / "frames")
    assert index.splits["train"] == scenes
    for scene in index.splits["train"]:
        frames = index.frames(scene)
        assert len(frames) == 6 and all(len(f["ego_future"]) == 6 and all(f["ego_future_mask"]) for f in frames)
        assert all(index.labels_path(scene, f["token"]).is_file() for f in frames)
    metrics = stages["closed_loop"]["metrics"]
    for r in (0, 1):
        assert {f"round{r}_rollout_driving_score", f"round{r}_rollout_collisions"} <= metrics.keys()
    assert "val/head_L2_stp3_avg" in metrics  # the quickstart's head reads the road, no meta action
    # It learned from what it drove into: its weights left the consumed planner's.
    import torch

    before, after = export_tensors(run_dir / "planner"), export_tensors(stage)
    assert before.keys() == after.keys() and any(not torch.equal(before[k], after[k]) for k in before)


def test_a_kill_during_a_rounds_driving_resumes_bit_exact(closed_loop, tmp_path):
    import torch

    quickstart, reference = closed_loop
    run_dir = _copy(quickstart, tmp_path / "run")
    args = _args(quickstart, run_dir)
    proc = start_cli(*args, session=True)
    driving = run_dir / "closed_loop" / "dagger" / "frames" / "gts" / "round01-route00"
    deadline = time.time() + 600
    while not driving.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, "the stage ended before round 1 was driven"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (run_dir / "closed_loop" / "dagger" / "routes" / "round01-route00.json").exists()
    res = run_cli(*_args(quickstart, run_dir, restart=False))
    assert res.returncode == 0, res.stderr[-3000:]
    ref, got = export_tensors(reference / "closed_loop"), export_tensors(run_dir / "closed_loop")
    assert ref.keys() == got.keys() and all(torch.equal(ref[k], got[k]) for k in ref)
    for name in ("round00-route00", "round00-route01", "round01-route00", "round01-route01"):
        theirs = json.loads((reference / "closed_loop" / "dagger" / "routes" / f"{name}.json").read_text())
        ours = json.loads((run_dir / "closed_loop" / "dagger" / "routes" / f"{name}.json").read_text())
        assert {k: v for k, v in ours.items() if k != "wall_s"} == {k: v for k, v in theirs.items() if k != "wall_s"}


def test_its_export_is_scored_and_driven_as_the_planners(closed_loop):
    _, run_dir = closed_loop
    res = run_cli("eval", str(run_dir / "closed_loop"))
    assert res.returncode == 0, res.stderr[-3000:]
    from occtrain.formats.metrics_file import read_metrics

    scored = read_metrics(run_dir / "closed_loop" / "eval" / "val" / "metrics.json").metrics
    assert "head_L2_stp3_avg" in scored and "constant_acceleration_L2_stp3_avg" in scored
    res = run_cli("drive", str(run_dir / "closed_loop"), "--scenes", "1", "--seconds", "3")
    assert res.returncode == 0, res.stderr[-3000:]
    summary = json.loads((run_dir / "closed_loop" / "drive" / "seed1000-3s" / "summary.json").read_text())
    assert "closed_loop" in summary["drivers"] and "expert" in summary["drivers"]
