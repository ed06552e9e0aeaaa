"""recipes/occllm.yaml through the real CLI, shrunk to seconds per stage: the MS-VAE, the
patch-token world model and its LoRA instruction tuning; ``occtrain eval`` on each world-
model stage; exports that plain transformers reads; the tokenizer stage resumed after kill -9."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from conftest import kill_at_checkpoint, run_cli
from family_contract import check_contract
from quickstart_run import export_tensors, tiny_overrides, train_rows

pytestmark = pytest.mark.slow

STAGES = ("tokenizer", "pretrain", "instruct")
STEPS = 4


def overrides(data: Path) -> list[str]:
    # The MS-VAE's convolutions at the full 200 x 200 x 16 grid are most of this file's time:
    # one frame a step is enough to train, kill and resume it.
    return tiny_overrides(data, steps=STEPS, stages=len(STAGES)) + [
        "stages[0].data.batch_size=1",
        "stages[2].model.tasks.forecast_frames=2",
        # The forecast's queries carry the present moved through the two-codebook MS-VAE
        # (the engine's SceneMover), with the weight on the cells that change.
        "stages[1].model.occllm.scene_queries=moved_observed_scene",
        "stages[1].model.occllm.change_weight=4.0",
    ]


@pytest.fixture(scope="module")
def occllm_run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("occllm")
    run_dir = root / "run"
    res = run_cli("run", "recipes/occllm.yaml", *overrides(root / "data"), "--run-dir", str(run_dir))
    assert res.returncode == 0, res.stderr[-3000:]
    return run_dir


def test_the_recipe_trains_every_stage_and_reports_the_papers_metrics(occllm_run):
    stages = json.loads((occllm_run / "manifest.json").read_text())["stages"]
    assert list(stages) == list(STAGES) and all(s["status"] == "done" for s in stages.values())
    tokenizer, pretrain, instruct = (stages[s]["metrics"] for s in STAGES)
    assert {"val/motion_usage", "val/static_perplexity", "val/occworld_mIoU"} <= tokenizer.keys()
    for h in ("1s", "2s", "3s"):
        assert {f"val/forecast_occworld_IoU_{h}", f"val/forecast_occworld_mIoU_{h}"} <= pretrain.keys()
    for conv in ("stp3", "uniad"):  # the paper names no convention: both, beside constant velocity
        assert {f"val/plan_alternate_L2_{conv}_avg", f"val/baseline_constant_velocity_L2_{conv}_avg"} <= pretrain.keys()
    assert {"val/qa_overall", "val/baseline_prior_qa_overall", "val/forecast_occworld_mIoU_avg"} <= instruct.keys()
    # Each scored something: sample counts above zero, finite values.
    assert pretrain["val/forecast_occworld_frames_1s"] > 0 and pretrain["val/plan_alternate_samples"] > 0
    assert instruct["val/qa_questions"] > 0
    for metrics, key in (
        (tokenizer, "val/occworld_mIoU"),
        (pretrain, "val/forecast_occworld_mIoU_1s"),
        (pretrain, "val/plan_alternate_L2_uniad_1s"),
        (instruct, "val/qa_overall"),
    ):
        assert math.isfinite(metrics[key]), key
    config = json.loads((occllm_run / "pretrain" / "export" / "config.json").read_text())
    assert (
        config["family"] == "occllm"
        and config["vocab"]["codebook_sizes"] == [128, 128]
        and config["vocab"]["patch"] == 2
    )
    assert config["world"]["occllm"] == {
        "patch_size": 2,
        "frame_separation": True,
        "pre_fusion": True,
        "fusion_hidden": 64,
        "cell_dim": 64,
        "scene_queries": "moved_observed_scene",
        "copy_bias": 4.0,
        "change_weight": 4.0,
        "mover_weight": 1.0,
    }


def test_exports_load_as_hugging_face_models_with_a_peft_adapter(occllm_run):
    from peft import PeftModel
    from transformers import AutoModelForCausalLM, AutoTokenizer

    llm_dir = occllm_run / "instruct" / "export" / "llm"
    assert (llm_dir / "adapter" / "adapter_config.json").is_file()
    model = AutoModelForCausalLM.from_pretrained(str(llm_dir), local_files_only=True)
    model = PeftModel.from_pretrained(model, str(llm_dir / "adapter"))
    tokenizer = AutoTokenizer.from_pretrained(str(llm_dir))
    ids = tokenizer("<question-answering> Question: how many cars? Answer:", return_tensors="pt").input_ids
    assert model(ids).logits.shape[-1] == len(tokenizer)
    assert tokenizer.convert_tokens_to_ids("<patch_24>") < len(tokenizer)  # 25 patch tokens per frame


@pytest.mark.parametrize("stage", ["tokenizer", "pretrain", "instruct"])
def test_eval_scores_each_stage(occllm_run, stage):
    res = run_cli("eval", str(occllm_run / stage), "--samples", "4")
    assert res.returncode == 0, res.stderr[-3000:]
    metrics = json.loads((occllm_run / stage / "eval" / "val" / "metrics.json").read_text())
    if stage == "tokenizer":  # reconstruction of the first 4 val frames, code use per codebook
        assert (
            metrics["frames"] == 4
            and {"occworld_mIoU", "occ3d_IoU", "motion_usage", "static_perplexity"} <= metrics.keys()
        )
        return
    assert "forecast_occworld_mIoU_3s" in metrics and "plan_alternate_L2_uniad_avg" in metrics
    assert ("qa_overall" in metrics) == (stage == "instruct")
    # Scored on the clips asked for, to finite numbers (an empty metric reports NaN).
    assert 0 < metrics["forecast_occworld_frames_1s"] == metrics["plan_alternate_samples"] <= 4
    assert math.isfinite(metrics["forecast_occworld_mIoU_1s"]) and math.isfinite(metrics["plan_alternate_L2_uniad_1s"])


def test_the_msvae_tokenizer_resumes_bit_exact_after_kill_9(occllm_run, tmp_path):
    import torch

    run_dir = tmp_path / "run"
    args = [
        "run",
        "recipes/occllm.yaml",
        *overrides(occllm_run.parent / "data"),
        "--run-dir",
        str(run_dir),
        "--only",
        "tokenizer",
    ]
    step = kill_at_checkpoint(args, run_dir / "tokenizer" / "checkpoints" / "last.ckpt", step=2)
    res = run_cli(*args)
    assert res.returncode == 0, res.stderr[-3000:]
    entry = json.loads((run_dir / "manifest.json").read_text())["stages"]["tokenizer"]
    assert entry["status"] == "done" and entry["attempts"] == 2
    assert [h["start_step"] for h in entry["history"]] == [0, step]  # resumed, not restarted
    ref, got = export_tensors(occllm_run / "tokenizer"), export_tensors(run_dir / "tokenizer")
    assert ref.keys() == got.keys()
    for key in ref:
        assert torch.equal(ref[key], got[key]), f"killed at step {step}: {key} differs"
    assert train_rows(run_dir / "tokenizer") == train_rows(occllm_run / "tokenizer")


def test_it_trains_on_a_plain_occ3d_release(synth_dataset, tmp_path):
    """Without occtrain's sidecars or NuScenes-QA (what an Occ3D download holds): the MS-VAE
    trains, and the world model forecasts and plans from the ego poses."""
    import shutil

    root = tmp_path / "occ3d"
    shutil.copytree(synth_dataset, root, ignore=shutil.ignore_patterns("occtrain", "NuScenes_*", "shards"))
    assert not (root / "occtrain").exists()
    run_dir = tmp_path / "run"
    args = [f"data.root={root}", "data.samples_per_shard=8", "data.shuffle_buffer=4", "stages[0].data.batch_size=1"]
    for i in range(2):
        args += [
            f"stages[{i}].trainer.max_steps=2",
            f"stages[{i}].trainer.val_check_interval=2",
            f"stages[{i}].trainer.limit_val_batches=1",
        ]
    args += ["stages[1].model.val_samples=2", "stages[1].model.llm.text_vocab_size=300"]
    res = run_cli("run", "recipes/occllm.yaml", *args, "--run-dir", str(run_dir), "--only", "tokenizer")
    assert res.returncode == 0, res.stderr[-3000:]
    res = run_cli("run", "recipes/occllm.yaml", *args, "--run-dir", str(run_dir), "--only", "pretrain")
    assert res.returncode == 0, res.stderr[-3000:]
    metrics = json.loads((run_dir / "pretrain" / "metrics.json").read_text())
    assert metrics["val/forecast_occworld_frames_3s"] > 0 and "val/plan_alternate_L2_stp3_avg" in metrics


def test_the_family_keeps_the_contract(occllm_run, tmp_path):
    """Its tasks build, its scorers score, its export round-trips, its inputs are served and
    a few steps lower its loss, checked as every family's are (tests/family_contract.py)."""
    check_contract(occllm_run, "pretrain", tmp_path)
