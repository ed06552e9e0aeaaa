"""The five-stage quickstart recipe through the real CLI, shrunk to seconds per stage.

One session-scoped run feeds several checks: every stage done and exported, ``occtrain
eval`` agreeing with ``occtrain score`` on the saved predictions, and the dashboard. The
fault test kills the pipeline during its third stage and resumes it.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import REPO, run_cli

pytestmark = pytest.mark.slow

STAGES = ("tokenizer", "pretrain", "instruct", "planner", "distill")
#: Optimizer steps per stage of the shared tiny run (a kill test interrupts each in between).
PIPELINE_STEPS = 5


def tiny_overrides(data: Path, steps: int = 3, stages: int = len(STAGES)) -> list[str]:
    """The quickstart recipe (or another whose first stages are tokenizer, pretrain,
    instruct) at test size: a 3-scene world, a few steps per stage."""
    out = [
        f"data.root={data}",
        "data.synth.train_scenes=2", "data.synth.val_scenes=1", "data.synth.frames_per_scene=13",
        "data.samples_per_shard=8", "data.shuffle_buffer=4",
        "trainer.ckpt_every_n_steps=1", "trainer.log_every_n_steps=1",
    ]
    for i in range(stages):
        out += [
            f"stages[{i}].trainer.max_steps={steps}", f"stages[{i}].trainer.val_check_interval={steps}",
            f"stages[{i}].trainer.limit_val_batches=1",
        ]
    out += [f"stages[{i}].model.val_samples=4" for i in (1, 2, 4) if i < stages]
    out += ["stages[1].model.tasks.forecast_frames=2", "stages[1].model.llm.text_vocab_size=400"]
    return out


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("pipeline")
    run_dir = root / "run"
    res = run_cli("run", "stages/quickstart.yaml", *tiny_overrides(root / "data", steps=PIPELINE_STEPS), "--run-dir", str(run_dir), timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    return run_dir


def test_every_stage_is_done_and_exported(pipeline):
    manifest = json.loads((pipeline / "manifest.json").read_text())
    assert [s for s in manifest["stages"]] == list(STAGES)
    for name in STAGES:
        entry = manifest["stages"][name]
        assert entry["status"] == "done" and entry["attempts"] == 1
        assert (pipeline / name / "export" / "model.safetensors").is_file()
        assert json.loads((pipeline / name / "metrics.json").read_text()) == pytest.approx(entry["metrics"], nan_ok=True)
    # World-model exports hold a Hugging Face directory (the quickstart fine-tunes fully:
    # no adapter; the LoRA export is checked on stages/occllama.yaml below).
    for name in ("pretrain", "instruct", "distill"):
        llm = pipeline / name / "export" / "llm"
        assert json.loads((llm / "config.json").read_text())["model_type"] == "llama"
        assert (llm / "generation_config.json").is_file() and (llm / "tokenizer.json").is_file()
        assert not (llm / "adapter").exists()
    distill = manifest["stages"]["distill"]["metrics"]
    assert distill["student_params"] < distill["teacher_params"]
    assert "val/teacher_tokens_per_s" in distill and "val/student_tokens_per_s" in distill
    planner = manifest["stages"]["planner"]["metrics"]
    assert "val/constant_velocity_L2_uniad_avg" in planner and "val/head_gt_meta_L2_uniad_avg" in planner
    from occtrain.models.planner import load_planning_head

    assert load_planning_head(pipeline / "planner" / "export").steps == 6
    assert (pipeline / "dashboard.html").stat().st_size > 10_000
    # The four world-model stages read one tokenizer on one world: one scene cache between them.
    assert len(list((pipeline / "cache").glob("scenes-*.safetensors"))) == 1
    assert not list(pipeline.glob("*/cache/scene*"))


def test_the_occllama_recipe_runs(pipeline, tmp_path):
    """stages/occllama.yaml (tokenizer -> pretrain -> instruct) end to end, shrunk, on the
    pipeline's world (the same data settings: its shards are reused, not made again)."""
    run_dir = tmp_path / "run"
    res = run_cli("run", "stages/occllama.yaml", *tiny_overrides(pipeline.parent / "data", stages=3), "--run-dir", str(run_dir), timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    stages = json.loads((run_dir / "manifest.json").read_text())["stages"]
    assert list(stages) == ["tokenizer", "pretrain", "instruct"] and all(s["status"] == "done" for s in stages.values())
    assert "val/qa_overall" in stages["instruct"]["metrics"]
    # The paper's instruction tuning is LoRA: the export holds the peft adapter beside the base.
    assert (run_dir / "instruct" / "export" / "llm" / "adapter" / "adapter_config.json").is_file()
    assert not (run_dir / "pretrain" / "export" / "llm" / "adapter").exists()


def test_eval_and_score_agree(pipeline, tmp_path):
    preds = tmp_path / "preds"
    res = run_cli("eval", str(pipeline / "instruct"), "--tasks", "planning,qa,cot_planning", "--save-predictions", str(preds))
    assert res.returncode == 0, res.stderr[-3000:]
    metrics = json.loads((pipeline / "instruct" / "eval" / "val" / "metrics.json").read_text())
    # Two tasks plan on every clip; the baselines still count each clip once.
    assert metrics["baseline_constant_velocity_samples"] == metrics["plan_direct_samples"] == metrics["plan_cot_samples"]

    planning = run_cli("score", "planning", "--pred", str(preds / "planning_pred.json"), "--gt", str(preds / "planning_gt.json"))
    assert planning.returncode == 0, planning.stderr
    scored = json.loads(planning.stdout)
    for conv in ("stp3", "uniad"):
        for h in ("1s", "2s", "3s", "avg"):
            assert scored[f"L2_{conv}"][h] == pytest.approx(metrics[f"plan_direct_L2_{conv}_{h}"], rel=1e-6, nan_ok=True)

    qa = run_cli("score", "qa", "--pred", str(preds / "qa_pred.json"), "--questions", str(preds / "qa_questions.json"))
    assert qa.returncode == 0, qa.stderr
    assert json.loads(qa.stdout)["overall"] == pytest.approx(metrics["qa_overall"])

    # A later eval of one task keeps what the earlier one wrote for the others.
    one_by_one = tmp_path / "one_by_one"
    again = run_cli("eval", str(pipeline / "instruct"), "--tasks", "qa", "--batch-size", "1", "--save-predictions", str(one_by_one))
    assert again.returncode == 0, again.stderr[-3000:]
    merged = json.loads((pipeline / "instruct" / "eval" / "val" / "metrics.json").read_text())
    assert merged["plan_direct_L2_stp3_avg"] == metrics["plan_direct_L2_stp3_avg"]
    assert merged["qa_overall"] == pytest.approx(metrics["qa_overall"])
    # Batch size does not change answers: every answer, not only the accuracy.
    assert json.loads((one_by_one / "qa_pred.json").read_text()) == json.loads((preds / "qa_pred.json").read_text())


def _export_tensors(stage_dir: Path) -> dict:
    from safetensors.torch import load_file

    out = {}
    for f in sorted((stage_dir / "export").rglob("*.safetensors")):
        rel = f.relative_to(stage_dir / "export")
        out.update({f"{rel}:{k}": v for k, v in load_file(f).items()})
    return out


def _train_rows(stage_dir: Path) -> list[tuple[str, str]]:
    import csv

    with open(stage_dir / "logs" / "csv" / "metrics.csv", newline="") as fh:
        return [(r["step"], r["train/loss"]) for r in csv.DictReader(fh) if r.get("train/loss")]


def test_kill_9_at_a_random_step_of_every_stage_resumes_bit_exact(pipeline, tmp_path):
    """Each stage kind is killed (-9) once, at a random optimizer step, and resumed: every
    export equals the uninterrupted run's bit for bit, the CSV log holds each step once,
    and the manifest counts two attempts per stage with their wall times summed."""
    import random

    import torch

    rng = random.Random(int(os.environ.get("OCCTRAIN_TEST_SEED", time.time_ns() % 10_000)))
    run_dir = tmp_path / "run"
    args = ["run", "stages/quickstart.yaml", *tiny_overrides(pipeline.parent / "data", steps=PIPELINE_STEPS), "--run-dir", str(run_dir)]
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    killed_at = {}
    for name in STAGES:
        target = rng.randint(1, PIPELINE_STEPS - 1)
        proc = subprocess.Popen([sys.executable, "-m", "occtrain", *args], cwd=REPO, env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        last = run_dir / name / "checkpoints" / "last.ckpt"
        deadline = time.time() + 600
        step = -1
        while proc.poll() is None and time.time() < deadline:
            if last.is_file():
                try:
                    step = torch.load(last, weights_only=True, map_location="cpu")["global_step"]
                except (RuntimeError, OSError, EOFError):
                    step = -1  # replaced while reading
                if step >= target:
                    break
            time.sleep(0.02)
        assert proc.poll() is None, f"{name} finished before step {target}"
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        killed_at[name] = torch.load(last, weights_only=True, map_location="cpu")["global_step"]  # the file as the kill left it
    res = run_cli(*args, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]

    stages = json.loads((run_dir / "manifest.json").read_text())["stages"]
    reference = json.loads((pipeline / "manifest.json").read_text())["stages"]
    for name in STAGES:
        entry = stages[name]
        assert entry["status"] == "done" and entry["attempts"] == 2, (name, entry["attempts"])
        assert entry["wall_time_s"] > 0
        # The second attempt continued from the checkpoint, not from step 0 (a restart would
        # give the same weights, training being deterministic).
        assert [h["start_step"] for h in entry["history"]] == [0, killed_at[name]], name
        ref, got = _export_tensors(pipeline / name), _export_tensors(run_dir / name)
        assert ref.keys() == got.keys(), name
        for key in ref:
            assert torch.equal(ref[key], got[key]), f"{name} (killed at step {killed_at[name]}): {key} differs"
        rows = _train_rows(run_dir / name)
        assert [s for s, _ in rows] == [s for s, _ in _train_rows(pipeline / name)], name  # each step logged once
        assert rows == _train_rows(pipeline / name), name
        timing = ("per_s", "speedup", "_step_s", "_rss_mb")  # measurements of the machine, not results
        ours = {k: v for k, v in entry["metrics"].items() if not k.endswith(timing)}
        theirs = {k: v for k, v in reference[name]["metrics"].items() if not k.endswith(timing)}
        assert ours == theirs, name


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
    from occtrain.evaluate import eval_metrics_file

    scored = {}
    for seed in (5, 6):
        other = tmp_path / str(seed) / "world"
        made = run_cli("data", "synth", "--out", str(other), "--scenes", "1", "--val-scenes", "1", "--frames", "13", "--seed", str(seed))
        assert made.returncode == 0, made.stderr[-2000:]
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
    """stages/vision.yaml on a tiny world with cameras: trained, scored beside the prior,
    and exported as a directory plain transformers loads."""
    import torch
    from transformers import SiglipVisionModel

    from occtrain.models.vision import load_vision_encoder

    run_dir = tmp_path / "run"
    res = run_cli(
        "run", "stages/vision.yaml", f"data.root={tmp_path / 'data'}",
        "data.synth.train_scenes=1", "data.synth.val_scenes=1", "data.synth.frames_per_scene=4",
        "data.samples_per_shard=4", "data.history=1", "data.future=1",
        "stages.vision.trainer.max_steps=6", "stages.vision.trainer.val_check_interval=6", "stages.vision.model.prior_batches=2",
        "--run-dir", str(run_dir), timeout=900,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    metrics = json.loads((run_dir / "vision" / "metrics.json").read_text())
    for key in ("val/pixel_mIoU", "val/baseline_prior_pixel_mIoU", "val/depth_absrel", "val/baseline_prior_depth_absrel"):
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
    section = text[text.index("### The Python API"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert "occtrain.load(" in code
    code = code.replace("runs/quickstart/instruct/export", str(pipeline / "instruct" / "export"))
    code = code.replace("data/quickstart", str(pipeline.parent / "data"))
    names: dict = {}
    exec(compile(code, "README.md", "exec"), names)
    printed = capsys.readouterr().out.splitlines()
    assert printed[0] == "['answer', 'plan', 'forecast', 'chain_of_thought', 'meta_action']"
    model, clip = names["model"], names["clip"]
    assert model.plan(clip).shape == (6, 2) and model.forecast(clip).shape[1:] == (200, 200, 16)
    assert isinstance(model.answer(clip, "Are there any cars?"), str)


def test_bf16_mixed_trains_every_stage_on_cpu(pipeline, tmp_path):
    """The quickstart's five stage kinds at bf16-mixed on the CPU (the GPU default), the
    world-model stages with gradient checkpointing on, logging to MLflow and W&B (offline)
    where installed: every stage trains and exports, its losses are finite, the tokenizer's
    first loss (same weights, same batch) is fp32's to bf16's precision, and each stage has
    its tracker run."""
    import importlib.util
    import math

    run_dir = tmp_path / "bf16"
    checkpointing = [f"stages[{i}].model.gradient_checkpointing=true" for i in (1, 2)]
    trackers = [name for name in ("mlflow", "wandb") if importlib.util.find_spec(name)]
    res = run_cli(
        "run", "stages/quickstart.yaml", *tiny_overrides(pipeline.parent / "data", steps=2), "trainer.precision=bf16-mixed",
        *checkpointing, f"trainer.loggers=[csv,{','.join(trackers or ['tensorboard'])}]", "--run-dir", str(run_dir),
        timeout=900, env={"WANDB_MODE": "offline"},
    )
    assert res.returncode == 0, res.stderr[-3000:]
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert {s["config"]["trainer"]["precision"] for s in manifest["stages"].values()} == {"bf16-mixed"}
    for name in STAGES:
        rows = _train_rows(run_dir / name)
        assert len(rows) == 2 and all(math.isfinite(float(loss)) for _, loss in rows), (name, rows)
        assert (run_dir / name / "export").is_dir()
    fp32, bf16 = float(_train_rows(pipeline / "tokenizer")[0][1]), float(_train_rows(run_dir / "tokenizer")[0][1])
    assert bf16 == pytest.approx(fp32, rel=0.02)
    for name in STAGES:
        logs = run_dir / name / "logs"
        if "mlflow" in trackers:
            assert list((run_dir / "mlruns").glob(f"*/{(logs / 'mlflow_run_id').read_text()}/metrics/train/loss"))
        if "wandb" in trackers:
            assert len(list((logs / "wandb").glob("offline-run-*"))) == 1  # its own run, not the stage before's
