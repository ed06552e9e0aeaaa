"""The five-stage quickstart recipe through the real CLI, shrunk to seconds per stage.

One module-scoped run feeds several checks: every stage done and exported, ``occtrain
eval`` agreeing with ``occtrain score`` on the saved predictions, and the dashboard. The
kill -9 and bf16 runs are ``test_pipeline_faults``'s.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO, run_cli
from family_contract import check_contract
from occtrain.formats.metrics_file import read_metrics
from occtrain.stages.phases import PHASES
from quickstart_run import STAGES, shared_quickstart_run, tiny_overrides

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory) -> Path:
    return shared_quickstart_run(tmp_path_factory)


def test_every_stage_is_done_and_exported(pipeline):
    manifest = json.loads((pipeline / "manifest.json").read_text())
    assert [s for s in manifest["stages"]] == list(STAGES)
    for name in STAGES:
        entry = manifest["stages"][name]
        assert entry["status"] == "done" and entry["attempts"] == 1
        assert (pipeline / name / "export" / "model.safetensors").is_file()
        final = read_metrics(pipeline / name / "metrics.json")
        recorded = {k: float("nan") if v is None else v for k, v in entry["metrics"].items()}  # JSON's null
        assert final.metrics == pytest.approx(recorded, nan_ok=True)
        # What the numbers were measured on: this attempt, this world, so many items of the split.
        provenance = final.provenance
        assert provenance is not None and provenance.by == "validation at the end of training"
        assert provenance.stage.config_hash == entry["config_hash"] and provenance.stage.attempt == 1
        assert provenance.world_name.startswith("occtrain world v") and provenance.code_version == entry["code_version"]
        validated, held = provenance.coverage["validation"]
        assert 0 < validated <= held
        if name in ("pretrain", "instruct", "distill"):  # generation on val_samples=4 items per task: a subset
            assert provenance.subset and all(n <= 4 for n, _ in provenance.coverage.values() if n != validated)
    # World-model exports hold a Hugging Face directory (the quickstart fine-tunes fully:
    # no adapter; the LoRA export is checked on recipes/occllama.yaml below).
    for name in ("pretrain", "instruct", "distill"):
        llm = pipeline / name / "export" / "llm"
        assert json.loads((llm / "config.json").read_text())["model_type"] == "llama"
        assert (llm / "generation_config.json").is_file() and (llm / "tokenizer.json").is_file()
        assert not (llm / "adapter").exists()
    # Every stage's throughput; the world models' in tokens and model FLOPs too (issue 46).
    for name in STAGES:
        metrics = manifest["stages"][name]["metrics"]
        # (No train_step_s: every step of the tiny run writes a checkpoint, and a step time
        # leaves those intervals out; the rates time each step's own work.)
        assert metrics["train_samples_per_s"] > 0, name
        has_tokens = name in ("pretrain", "instruct", "distill")
        assert ("train_tokens_per_s" in metrics) == has_tokens, name
        # The language models' FLOPs by formula; the tokenizer's and the planner's counted
        # by torch on their first step that computes anything (the tiny planner's first
        # steps may hold no clip with a meta action).
        assert ("train_mfu" in metrics) >= (has_tokens or name == "tokenizer"), name
        assert ("train_mfu" in metrics) <= (has_tokens or name in ("tokenizer", "planner")), name
        if "train_mfu" in metrics:  # (the tiny planner head's MFU rounds to 0 in the manifest; its FLOPs do not)
            assert metrics["train_model_flops_per_s"] > 0 and 0 <= metrics["train_mfu"] < 1, name
        if has_tokens:
            assert metrics["train_tokens_per_s"] > metrics["train_samples_per_s"]
        # Where the stage's time went (issue 75): every step computed forward and backward,
        # validated once at its end and wrote a checkpoint a step.
        phases = {k: v for k, v in metrics.items() if k.endswith("_phase_s")}
        assert set(phases) == {f"{p}_phase_s" for p in PHASES}, name
        assert all(phases[f"{p}_phase_s"] > 0 for p in ("forward", "backward", "validation", "checkpoints", "export"))
    distill = manifest["stages"]["distill"]["metrics"]
    assert distill["student_params"] < distill["teacher_params"]
    assert "val/teacher_tokens_per_s" in distill and "val/student_tokens_per_s" in distill
    planner = manifest["stages"]["planner"]["metrics"]
    assert "val/constant_velocity_L2_uniad_avg" in planner and "val/head_L2_uniad_avg" in planner
    from occtrain.models.planning_heads import load_planning_head

    assert load_planning_head(pipeline / "planner" / "export").steps == 6
    assert (pipeline / "dashboard.html").stat().st_size > 10_000
    # The four world-model stages read one tokenizer on one world: one scene cache between them.
    assert len(list((pipeline / "cache").glob("scenes-*.safetensors"))) == 1
    assert not list(pipeline.glob("*/cache/scene*"))


def test_the_occllama_recipe_runs(pipeline, tmp_path):
    """recipes/occllama.yaml (tokenizer -> pretrain -> instruct) end to end, shrunk, on the
    pipeline's world (the same data settings: its shards are reused, not made again)."""
    run_dir = tmp_path / "run"
    res = run_cli(
        "run",
        "recipes/occllama.yaml",
        *tiny_overrides(pipeline.parent / "data", stages=3),
        "--run-dir",
        str(run_dir),
    )
    assert res.returncode == 0, res.stderr[-3000:]
    stages = json.loads((run_dir / "manifest.json").read_text())["stages"]
    assert list(stages) == ["tokenizer", "pretrain", "instruct"] and all(s["status"] == "done" for s in stages.values())
    assert "val/qa_overall" in stages["instruct"]["metrics"]
    # The paper's instruction tuning is LoRA: the export holds the peft adapter beside the base.
    assert (run_dir / "instruct" / "export" / "llm" / "adapter" / "adapter_config.json").is_file()
    assert not (run_dir / "pretrain" / "export" / "llm" / "adapter").exists()


def test_eval_and_score_agree(pipeline, tmp_path):
    preds = tmp_path / "preds"
    res = run_cli(
        "eval", str(pipeline / "instruct"), "--tasks", "planning,qa,cot_planning", "--save-predictions", str(preds)
    )
    assert res.returncode == 0, res.stderr[-3000:]
    metrics = json.loads((pipeline / "instruct" / "eval" / "val" / "metrics.json").read_text())
    # Two tasks plan on every clip; the baselines still count each clip once.
    assert (
        metrics["baseline_constant_velocity_samples"] == metrics["plan_direct_samples"] == metrics["plan_cot_samples"]
    )

    planning = run_cli(
        "score", "planning", "--pred", str(preds / "planning_pred.json"), "--gt", str(preds / "planning_gt.json")
    )
    assert planning.returncode == 0, planning.stderr
    scored = json.loads(planning.stdout)
    for conv in ("stp3", "uniad"):
        for h in ("1s", "2s", "3s", "avg"):
            assert scored[f"L2_{conv}"][h] == pytest.approx(
                metrics[f"plan_direct_L2_{conv}_{h}"], rel=1e-6, nan_ok=True
            )

    qa = run_cli("score", "qa", "--pred", str(preds / "qa_pred.json"), "--questions", str(preds / "qa_questions.json"))
    assert qa.returncode == 0, qa.stderr
    assert json.loads(qa.stdout)["overall"] == pytest.approx(metrics["qa_overall"])

    provenance = read_metrics(pipeline / "instruct" / "eval" / "val" / "metrics.json").provenance
    assert provenance is not None and provenance.by == "occtrain eval" and not provenance.subset
    assert set(provenance.coverage) == {"planning", "qa", "cot_planning"}
    assert provenance.coverage["qa"][0] == metrics["qa_questions"]
    # A later eval of one task keeps what the earlier one wrote for the others.
    one_by_one = tmp_path / "one_by_one"
    again = run_cli(
        "eval", str(pipeline / "instruct"), "--tasks", "qa", "--batch-size", "1", "--save-predictions", str(one_by_one)
    )
    assert again.returncode == 0, again.stderr[-3000:]
    merged = json.loads((pipeline / "instruct" / "eval" / "val" / "metrics.json").read_text())
    assert merged["plan_direct_L2_stp3_avg"] == metrics["plan_direct_L2_stp3_avg"]
    assert merged["qa_overall"] == pytest.approx(metrics["qa_overall"])
    # Batch size does not change answers: every answer, not only the accuracy.
    assert json.loads((one_by_one / "qa_pred.json").read_text()) == json.loads((preds / "qa_pred.json").read_text())

    # A subset is recorded as one, and the report calls it one.
    subset = run_cli("eval", str(pipeline / "instruct"), "--tasks", "qa", "--samples", "2")
    assert subset.returncode == 0, subset.stderr[-3000:]
    provenance = read_metrics(pipeline / "instruct" / "eval" / "val" / "metrics.json").provenance
    assert provenance is not None and provenance.coverage["qa"] == [2, metrics["qa_questions"]]
    page = run_cli("report", str(pipeline))
    assert page.returncode == 0, page.stderr
    header = page.stdout.splitlines()[0]
    assert "a subset of the val split (" in header and f"qa 2 of {metrics['qa_questions']:.0f})" in header
    assert "scored on the whole val split (`occtrain eval`)" not in page.stdout


def test_evals_of_other_subsets_keep_each_number_with_its_items(pipeline):
    """The plan of a forecast scored on 4 clips, then constant velocity re-scored on 1: the
    file keeps each number with the items it was scored on, and the report refuses to set
    them side by side as if they were scored on the same samples."""
    metrics_file = pipeline / "pretrain" / "eval" / "val" / "metrics.json"
    res = run_cli("eval", str(pipeline / "pretrain"), "--samples", "4")
    assert res.returncode == 0, res.stderr[-3000:]
    first = read_metrics(metrics_file)
    assert first.provenance is not None
    plan = first.provenance.sample_set("plan_alternate_L2_stp3_avg")
    velocity = first.provenance.sample_set("baseline_constant_velocity_L2_stp3_avg")
    assert plan is not None and velocity is not None and plan.digest == velocity.digest and plan.items == 4
    assert run_cli("report", str(pipeline)).returncode == 0

    res = run_cli("eval", str(pipeline / "pretrain"), "--tasks", "planning", "--samples", "1")
    assert res.returncode == 0, res.stderr[-3000:]
    merged = read_metrics(metrics_file)
    assert merged.provenance is not None
    kept = merged.provenance.sample_set("plan_alternate_L2_stp3_avg")
    rescored = merged.provenance.sample_set("baseline_constant_velocity_L2_stp3_avg")
    assert kept is not None and kept.digest == plan.digest
    np.testing.assert_equal(merged.metrics["plan_alternate_L2_stp3_avg"], first.metrics["plan_alternate_L2_stp3_avg"])
    assert rescored is not None and rescored.items == 1 and rescored.digest != plan.digest
    page = run_cli("report", str(pipeline))
    assert page.returncode == 2 and page.stderr.count("\n") == 1, page.stderr
    assert "plan_alternate_L2_stp3_avg (forecasting 4 of " in page.stderr
    assert "would stand beside constant acceleration" in page.stderr
    assert "scored on other items (planning 1 of " in page.stderr
    allowed = run_cli("report", str(pipeline), "--allow-mixed")
    assert allowed.returncode == 0, allowed.stderr
    row = next(line for line in allowed.stdout.splitlines() if "plan `plan_alternate`: L2 avg" in line)
    assert "constant velocity" in row and "(on other items: planning 1 of " in row


def test_eval_asks_every_question_and_scores_another_world(pipeline, tmp_path):
    from occtrain.data.layout import DatasetIndex

    asked = len(DatasetIndex.open(pipeline.parent / "data").questions("val"))
    res = run_cli("eval", str(pipeline / "instruct"), "--tasks", "qa,cot_planning")
    assert res.returncode == 0, res.stderr[-3000:]
    metrics = json.loads((pipeline / "instruct" / "eval" / "val" / "metrics.json").read_text())
    assert metrics["qa_questions"] == asked and metrics["baseline_prior_qa_questions"] == asked
    assert "samples" in res.stderr and "meta_parsed_fraction" in res.stderr  # the table goes to the console (stderr)

    # The same model on worlds synthesized from other seeds, in folders of one name: each has
    # its own eval directory and scene cache, keyed by its content (never the other's).
    from occtrain.commands.evaluate import eval_metrics_file
    from occtrain.config import SynthConfig
    from occtrain.data.synthesize import synthesize

    scored = {}
    for seed in (5, 6):
        other = tmp_path / str(seed) / "world"
        synthesize(other, SynthConfig(train_scenes=1, val_scenes=1, frames_per_scene=13, seed=seed), verbose=False)
        res = run_cli("eval", str(pipeline / "instruct"), "--tasks", "qa", "--data", str(other))
        assert res.returncode == 0, res.stderr[-3000:]
        out = eval_metrics_file(pipeline / "instruct", "val", other)
        assert f"metrics -> {out}" in res.stdout and out.parent.parent.name.startswith("world-")
        scored[seed] = out.read_bytes()
        assert json.loads(scored[seed])["qa_questions"] == len(DatasetIndex.open(other).questions("val"))
    first, second = (eval_metrics_file(pipeline / "instruct", "val", tmp_path / str(seed) / "world") for seed in (5, 6))
    assert first != second and first.read_bytes() == scored[5]  # seed 6's eval wrote beside it, not over it

    # A distilled stage's eval times student and teacher as its training validation does.
    res = run_cli("eval", str(pipeline / "distill"), "--tasks", "qa")
    assert res.returncode == 0, res.stderr[-3000:]
    distilled = json.loads((pipeline / "distill" / "eval" / "val" / "metrics.json").read_text())
    trained = json.loads((pipeline / "distill" / "metrics.json").read_text())
    assert distilled["speedup"] > 0 and trained["val/speedup"] > 0


def test_the_vision_recipe_runs_and_hands_over_a_hugging_face_tower(tmp_path):
    """recipes/vision.yaml on a tiny world with cameras: trained, scored beside the prior,
    and exported as a directory plain transformers loads."""
    import torch
    from transformers import SiglipVisionModel

    from occtrain.models.camera_encoder import load_vision_encoder

    run_dir = tmp_path / "run"
    res = run_cli(
        "run",
        "recipes/vision.yaml",
        f"data.root={tmp_path / 'data'}",
        "data.synth.train_scenes=1",
        "data.synth.val_scenes=1",
        "data.synth.frames_per_scene=4",
        "data.samples_per_shard=4",
        "data.history=1",
        "data.future=1",
        "stages.vision.trainer.max_steps=6",
        "stages.vision.trainer.val_check_interval=6",
        "stages.vision.model.prior_batches=2",
        "--run-dir",
        str(run_dir),
    )
    assert res.returncode == 0, res.stderr[-3000:]
    metrics = json.loads((run_dir / "vision" / "metrics.json").read_text())
    for key in (
        "val/pixel_mIoU",
        "val/baseline_prior_pixel_mIoU",
        "val/depth_absrel",
        "val/baseline_prior_depth_absrel",
    ):
        assert metrics[key] is not None and metrics[key] >= 0, key
    tower = SiglipVisionModel.from_pretrained(run_dir / "vision" / "export" / "vision")
    encoder = load_vision_encoder(run_dir / "vision" / "export")
    images = torch.randint(0, 255, (1, 6, 72, 128, 3), dtype=torch.uint8)
    tokens, grid = encoder(images)
    assert grid == (9, 16) and tokens.shape == (1, 6 * 9 * 16, tower.config.hidden_size)


def test_the_readme_python_api_example_runs_as_printed(pipeline, capsys):
    """README's Python API block, run as printed with its two paths pointed at this run."""
    import re

    text = (REPO / "README.md").read_text()
    section = text[text.index("### The Python API") :]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert "occtrain.load(" in code
    code = code.replace("runs/quickstart/instruct/export", str(pipeline / "instruct" / "export"))
    code = code.replace("data/quickstart", str(pipeline.parent / "data"))
    names: dict = {}
    exec(compile(code, "README.md", "exec"), names)
    printed = capsys.readouterr().out.splitlines()
    assert printed[0] == "['answer', 'plan', 'forecast', 'chain_of_thought', 'meta_action', 'scene_summary']"
    model, clip = names["model"], names["clip"]
    assert model.plan(clip).shape == (6, 2) and model.forecast(clip).shape[1:] == (200, 200, 16)
    assert isinstance(model.answer(clip, "Are there any cars?"), str)


def test_drive_puts_the_planner_behind_the_wheel_and_resumes(pipeline, tmp_path):
    # 3 s: the first 2 s are the logged history the planner's clips read (4 frames), the
    # last second the planner drives.
    videos = tmp_path / "videos"
    args = ("drive", str(pipeline / "planner"), "--scenes", "1", "--seconds", "3", "--save-videos", str(videos))
    res = run_cli(*args)
    assert res.returncode == 0, res.stderr[-3000:]
    out = pipeline / "planner" / "drive" / "seed1000-3s"
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["drivers"]) == [
        "planner",
        "expert",
        "constant_velocity",
        "constant_acceleration",
        "stand_still",
    ]
    assert summary["drivers"]["expert"]["driving_score"] >= 95.0
    assert summary["drivers"]["stand_still"]["route_completion"] < summary["drivers"]["expert"]["route_completion"]
    assert "CARLA" in summary["conventions"]["driving_score"] and "NAVSIM" in summary["conventions"]["pdm_score"]
    assert summary["wall_s"] > 0 and summary["workers"] == 1 and summary["resumed"] == 0
    manifest = json.loads((pipeline / "manifest.json").read_text())["stages"]["planner"]
    assert summary["provenance"]["stage"]["config_hash"] == manifest["config_hash"]
    assert summary["provenance"]["code_version"] == manifest["code_version"]
    assert sorted(p.name for p in videos.iterdir()) == [
        f"{d}-000.gif" for d in ("constant_acceleration", "constant_velocity", "expert", "planner", "stand_still")
    ]
    # Who drove the 6 planning frames: the expert the history, the stage (or its fallback) the rest.
    history = json.loads((pipeline / "instruct" / "export" / "config.json").read_text())["tasks"]["context_frames"]
    drivers = summary["drivers"]
    assert all(drivers[d]["planning_frames"] == 6 for d in drivers)
    assert drivers["planner"]["expert_share"] == pytest.approx(100 * history / 6)
    assert drivers["planner"]["planned_share"] + drivers["planner"]["fell_back_share"] == pytest.approx(
        100 * (6 - history) / 6
    )
    # Every driver gets the stage's start: the rules plan once the expert drove the history.
    assert drivers["expert"]["expert_share"] == 100 and summary["expert_start_frames"] == history
    for rule in ("constant_velocity", "constant_acceleration", "stand_still"):
        assert drivers[rule]["expert_share"] == pytest.approx(100 * history / 6)
        assert drivers[rule]["planned_share"] == pytest.approx(100 * (6 - history) / 6)
    dashboard = (pipeline / "dashboard.html").read_text()
    assert "Closed-loop driving (1 routes of 3 s, seed1000-3s)" in dashboard and "data:image/gif;base64," in dashboard
    # A killed drive resumes: the missing episode is driven again, to the same scores. Its
    # other episodes were driven by another checkout: the summary names both codes.
    episode = out / "episodes" / "planner-000.json"
    first = json.loads(episode.read_text())
    episode.unlink()
    elsewhere = out / "episodes" / "expert-000.json"
    elsewhere.write_text(json.dumps(json.loads(elsewhere.read_text()) | {"code_version": "0.0.9+elsewhere"}))
    again = run_cli(*args[:-2])
    assert again.returncode == 0, again.stderr[-3000:]
    assert json.loads(episode.read_text())["scores"] == first["scores"]
    codes = json.loads((out / "summary.json").read_text())["provenance"]["code_version"]
    assert codes == f"0.0.9+elsewhere, {manifest['code_version']}"
    # Videos asked of episodes driven earlier: they are driven again for their animations.
    later = tmp_path / "later"
    res = run_cli(*args[:-1], str(later))
    assert res.returncode == 0, res.stderr[-3000:]
    assert len(list(later.glob("*-000.gif"))) == 5
    assert json.loads(episode.read_text())["scores"] == first["scores"]


def test_a_stopped_drive_ends_in_one_line_and_leaves_no_temporary_files(pipeline, tmp_path):
    """SIGTERM to the drive's process group (as a scheduler sends it) while two workers drive:
    exit 143, one line saying what is written and how to go on, the scratch folders gone."""
    import os
    import signal
    import time

    from conftest import start_cli

    scratch = tmp_path / "tmp"
    scratch.mkdir()
    args = ("drive", str(pipeline / "planner"), "--scenes", "2", "--seconds", "4", "--seed", "7", "--workers", "2")
    # torch makes its compile cache on import, in the temporary directory unless told where:
    # a cache of torch's, not a temporary folder of the drive's.
    env = {"TMPDIR": str(scratch), "TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "inductor")}
    proc = start_cli(*args, env=env, session=True)
    deadline = time.time() + 120
    while not list(scratch.glob("occtrain-drive-*/frames-*")) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)  # until a worker is driving an episode
    assert proc.poll() is None, "the drive ended before the signal"
    os.killpg(proc.pid, signal.SIGTERM)
    code = proc.wait(60)
    out, err = proc.output()
    lines = [line for line in err.splitlines() if "interrupted" in line or "Traceback" in line or "error" in line]
    assert code == 143, err[-2000:]
    assert lines == [lines[-1]] and lines[0].startswith(f"interrupted: occtrain drive of {pipeline / 'planner'} ")
    assert "episodes are written under" in lines[0]
    assert lines[0].endswith("run the same command again to drive the rest")
    assert list(scratch.iterdir()) == []


def test_the_family_keeps_the_contract(pipeline, tmp_path):
    """Its tasks build, its scorers score, its export round-trips, its inputs are served and
    a few steps lower its loss, checked as every family's are (tests/family_contract.py)."""
    check_contract(pipeline, "pretrain", tmp_path)
