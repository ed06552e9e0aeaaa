"""recipes/occvla.yaml through the real CLI on a tiny world, a few steps per stage: the camera
encoder, the OccWorld VQ-VAE, stage 1, stage 2 with adapters and occupancy, the planning
head on generated meta actions and the VQA branch; ``occtrain eval``; the export reloaded
and generating the same text with and without its occupancy block."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from conftest import run_cli
from family_contract import check_contract

pytestmark = pytest.mark.slow

STAGES = ("vision", "tokenizer", "stage1", "stage2", "stage3", "vqa")
STEPS = 3


def overrides(root: Path) -> list[str]:
    out = [
        f"data.root={root / 'data'}",
        f"data.shards={root / 'data' / 'shards_h6'}",
        "data.synth.train_scenes=2",
        "data.synth.val_scenes=1",
        "data.synth.frames_per_scene=16",
        "data.samples_per_shard=8",
        "data.shuffle_buffer=4",
        "stages[0].model.prior_batches=2",
        "stages[1].data.batch_size=1",
        "stages[2].model.llm.text_vocab_size=400",
    ]
    for i in range(len(STAGES)):
        out += [
            f"stages[{i}].trainer.max_steps={STEPS}",
            f"stages[{i}].trainer.val_check_interval={STEPS}",
            f"stages[{i}].trainer.limit_val_batches=1",
        ]
    out += [f"stages[{i}].model.val_samples=3" for i in (2, 3, 5)]
    return out


@pytest.fixture(scope="module")
def occvla_run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("occvla")
    run_dir = root / "run"
    res = run_cli("run", "recipes/occvla.yaml", *overrides(root), "--run-dir", str(run_dir))
    assert res.returncode == 0, res.stderr[-3000:]
    return run_dir


def test_the_recipe_trains_every_stage_and_reports_the_papers_metrics(occvla_run):
    stages = json.loads((occvla_run / "manifest.json").read_text())["stages"]
    assert list(stages) == list(STAGES) and all(s["status"] == "done" for s in stages.values())
    stage2, stage3, vqa = (stages[s]["metrics"] for s in ("stage2", "stage3", "vqa"))
    for part in ("speed", "direction", "mean", "overall"):
        assert f"val/meta_action_{part}" in stage2 and f"val/baseline_prior_meta_action_{part}" in stage2
    for conv in ("occ3d", "occworld"):  # the query branch, decoded by the frozen OccWorld decoder
        assert f"val/occupancy_{conv}_mIoU" in stage2 and f"val/occupancy_{conv}_mIoU" in vqa
    assert "val/occupancy_occ3d_mIoU" not in stages["stage1"]["metrics"]  # stage 1 has no occupancy
    for conv in ("stp3", "uniad"):
        assert f"val/head_gt_meta_L2_{conv}_avg" in stage3 and f"val/constant_velocity_L2_{conv}_avg" in stage3
    assert {"val/qa_overall", "val/baseline_prior_qa_overall"} <= vqa.keys()
    # Each scored something: sample counts above zero, finite values.
    assert stage2["val/meta_action_samples"] > 0 and vqa["val/qa_questions"] > 0
    assert stage3["val/head_gt_meta_samples"] > 0
    for key in ("val/meta_action_overall", "val/occupancy_occworld_mIoU"):
        assert math.isfinite(stage2[key]), key
    assert math.isfinite(stage3["val/head_gt_meta_L2_stp3_avg"]) and math.isfinite(vqa["val/qa_overall"])


def test_stage2_exports_its_adapters_beside_the_hugging_face_directory(occvla_run):
    from transformers import AutoModelForCausalLM

    export = occvla_run / "stage2" / "export"
    assert {p.name for p in (export / "llm" / "bottleneck_adapter").iterdir()} == {
        "adapter.safetensors",
        "adapter_config.json",
    }
    assert (export / "vision_encoder" / "vision" / "config.json").is_file()
    config = json.loads((export / "config.json").read_text())
    assert config["family"] == "occvla" and config["vocab"]["image"] is True
    assert (
        config["tasks"]["occupancy_weight"] == 1.0 and config["tasks"]["meta_actions"]["accel_threshold_kmh_s"] == 1.0
    )
    # The LM's own weights load in plain transformers, no adapter key left over.
    model = AutoModelForCausalLM.from_pretrained(str(export / "llm"), local_files_only=True)
    assert not any("bottleneck" in k for k in model.state_dict())


def test_the_planning_head_trained_on_cached_generated_meta_actions(occvla_run):
    export = json.loads((occvla_run / "stage3" / "export" / "config.json").read_text())
    assert export["inputs"] == ["meta_action", "velocity", "visual", "past"] and export["train_meta"] == "generated"
    # The stage's own cache lives under the key of the world it was made from.
    (world,) = (occvla_run / "stage3" / "cache").iterdir()
    cache = json.loads((world / "teacher_outputs.json").read_text())
    # What the world model generated for each training clip, kept; the reference meta
    # action is read from each clip as it comes, never kept by token.
    assert cache and all("generated" in v and "reference" not in v for v in cache.values())
    assert (world / "teacher_outputs.safetensors").is_file()


def test_eval_scores_meta_actions_and_the_query_branch(occvla_run, tmp_path):
    res = run_cli("eval", str(occvla_run / "stage2"), "--save-predictions", str(tmp_path / "preds"))
    assert res.returncode == 0, res.stderr[-3000:]
    metrics = json.loads((occvla_run / "stage2" / "eval" / "val" / "metrics.json").read_text())
    assert {
        "meta_action_overall",
        "baseline_prior_meta_action_overall",
        "occupancy_occ3d_mIoU",
        "occupancy_occworld_mIoU",
    } <= metrics.keys()
    assert metrics["meta_action_samples"] == metrics["baseline_prior_meta_action_samples"] > 0
    assert metrics["baseline_repeat_last_meta_action_samples"] == metrics["meta_action_samples"]
    # Every scored chain of thought, with what was read from it: the metrics recount from them.
    chains = json.loads((tmp_path / "preds" / "meta_actions.json").read_text())
    assert len(chains) == metrics["meta_action_samples"]
    right = sum(c["parsed"] == c["truth"] for c in chains.values())
    last_right = sum(c["last_past"] == c["truth"] for c in chains.values())
    assert 100.0 * right / len(chains) == pytest.approx(metrics["meta_action_overall"])
    assert 100.0 * last_right / len(chains) == pytest.approx(metrics["baseline_repeat_last_meta_action_overall"])
    assert all(c["prompt"].startswith("Past meta actions:") and c["reference"] for c in chains.values())


def test_the_reloaded_model_generates_the_same_text_with_and_without_occupancy(occvla_run):
    from occtrain.core.decoding import TextAnswer
    from occtrain.data.clips import frame_clips
    from occtrain.data.layout import DatasetIndex
    from occtrain.engine import load_world_model

    engine = load_world_model(occvla_run / "stage2" / "export").eval()
    root = occvla_run.parent / "data"
    engine.prepare_inputs(root)
    clip = next(iter(frame_clips(DatasetIndex.open(root), "val", 6, 6, partial_history=False)))
    parts = engine.task_items("meta_action", clip)[0]
    prompt, _ = engine.prompt_and_plan(parts, {})
    # No end of text: 20 tokens each way, whatever a model of 3 steps would choose to say.
    engine.world.vocab.eos_id = -1
    skipped, _ = engine.world.generate_with_occupancy(prompt, [TextAnswer(20)], occupancy=False)
    with_occ, logits = engine.world.generate_with_occupancy(prompt, [TextAnswer(20)], occupancy=True)
    assert len(skipped[0]) == 20 and skipped == with_occ and logits.shape[1] == 18


def test_distillation_takes_a_camera_reading_teacher(occvla_run, tmp_path):
    """A student of OccVLA's stage 2: the same image tokens (one shared cache), the
    teacher's architecture around a smaller LLM; scored like its teacher."""
    from conftest import REPO

    recipe = (REPO / "recipes" / "occvla.yaml").read_text().replace("../configs/", f"{REPO}/configs/")
    recipe += """
  - name: student
    kind: distill
    consumes: [stage2]
    model:
      student: {hidden_size: 32, num_layers: 1, num_heads: 2, intermediate_size: 64}
      tasks: {weights: {meta_action: 1}, occupancy_weight: 1.0, context_frames: 6}
      val_samples: 3
      max_new_text_tokens: 24
"""
    path = tmp_path / "occvla_distill.yaml"
    path.write_text(recipe)
    extra = [
        f"stages[6].trainer.max_steps={STEPS}",
        f"stages[6].trainer.val_check_interval={STEPS}",
        "stages[6].trainer.limit_val_batches=1",
    ]
    res = run_cli(
        "run",
        str(path),
        *overrides(occvla_run.parent),
        *extra,
        "--run-dir",
        str(occvla_run),
        "--only",
        "student",
    )
    assert res.returncode == 0, res.stderr[-3000:]
    metrics = json.loads((occvla_run / "student" / "metrics.json").read_text())
    assert metrics["student_params"] < metrics["teacher_params"]
    assert "val/meta_action_overall" in metrics and "val/teacher_meta_action_overall" in metrics
    assert "val/occupancy_occworld_mIoU" in metrics  # the student's query branch, through the same frozen decoder
    export = json.loads((occvla_run / "student" / "export" / "config.json").read_text())
    assert export["family"] == "occvla" and (occvla_run / "student" / "export" / "vision_encoder").is_dir()


def test_the_family_keeps_the_contract(occvla_run, tmp_path):
    """Its tasks build, its scorers score, its export round-trips, its inputs are served and
    a few steps lower its loss, checked as every family's are (tests/family_contract.py)."""
    check_contract(occvla_run, "stage1", tmp_path)
