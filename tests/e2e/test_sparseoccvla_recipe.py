"""recipes/sparseoccvla.yaml through the real CLI on a tiny world with an OmniDrive-layout
text fixture, a few steps per stage: the vision teacher, stage 1 (the sparse occupancy
encoder from the cameras), stage 2, stage 3 through LoRA and the anchor-diffusion planner;
``occtrain eval`` on each stage; kill -9 and resume bit-exact; the stages from stage 1 on
under DDP (every parameter must get a gradient or DDP stops); the export through the
Python API."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest

from builders import write_omnidrive
from conftest import kill_at_checkpoint, run_cli, run_cli_process
from family_contract import check_contract

pytestmark = pytest.mark.slow

STAGES = ("vision", "stage1", "stage2", "stage3", "planner")
STEPS = 3
SYNTH = ("--scenes", "2", "--val-scenes", "1", "--frames", "16")


def overrides(root: Path) -> list[str]:
    out = [
        f"data.root={root / 'data'}",
        "data.synth.train_scenes=2",
        "data.synth.val_scenes=1",
        "data.synth.frames_per_scene=16",
        "data.samples_per_shard=8",
        "data.shuffle_buffer=4",
        "trainer.ckpt_every_n_steps=1",
        "trainer.log_every_n_steps=1",
        "stages.vision.model.prior_batches=2",
        "stages.stage1.model.sparseocc.queries=16",
        "stages.stage1.model.sparseocc.points_per_layer=[2,8]",
        "stages.stage1.model.sparseocc.gt_points=256",
        "stages.stage1.model.sparseocc.extended_range=1",
        "stages.stage2.model.llm.text_vocab_size=400",
        "stages.planner.model.anchors=4",
        "stages.planner.model.decision_tokens=8",
    ]
    for stage in ("stage2", "stage3"):
        out += [
            f"stages.{stage}.model.val_samples=3",
            f"stages.{stage}.model.max_new_text_tokens=16",
            f"stages.{stage}.model.tasks.questions_per_sample=2",
            f"stages.{stage}.model.tasks.omnidrive={root / 'omnidrive'}",
            f"stages.{stage}.model.tasks.weights={{caption: 1, conversation: 1, qa: 1, planning: 1, forecast: 1}}",
        ]
    for stage in STAGES:
        out += [
            f"stages.{stage}.trainer.max_steps={STEPS}",
            f"stages.{stage}.trainer.val_check_interval={STEPS}",
            f"stages.{stage}.trainer.limit_val_batches=1",
        ]
    return out


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    """The tiny world, synthesized ahead, and OmniDrive text for every one of its frames."""
    from occtrain.data.layout import DatasetIndex

    root = tmp_path_factory.mktemp("sparseoccvla")
    res = run_cli("data", "synth", "--out", str(root / "data"), *SYNTH)
    assert res.returncode == 0, res.stderr[-2000:]
    index = DatasetIndex.open(root / "data")
    write_omnidrive(root / "omnidrive", {t: split for split in ("train", "val") for _, t in index.samples(split)})
    return root


@pytest.fixture(scope="module")
def sparse_run(world) -> Path:
    run_dir = world / "run"
    res = run_cli("run", "recipes/sparseoccvla.yaml", *overrides(world), "--run-dir", str(run_dir))
    assert res.returncode == 0, res.stderr[-3000:]
    return run_dir


def test_every_stage_trains_and_reports_the_papers_metrics_beside_baselines(sparse_run):
    stages = json.loads((sparse_run / "manifest.json").read_text())["stages"]
    assert list(stages) == list(STAGES) and all(s["status"] == "done" for s in stages.values())
    stage1, stage2, stage3, planner = (stages[s]["metrics"] for s in STAGES[1:])
    for conv in ("occworld", "occ3d"):
        assert math.isfinite(stage1[f"val/{conv}_mIoU"])
    for m in (stage2, stage3):
        for key in (
            "caption_CIDEr",
            "baseline_typical_caption_CIDEr",
            "caption_METEOR",
            "caption_ROUGE_L",
            "conversation_CIDEr",
            "qa_overall",
            "baseline_prior_qa_overall",
            "meta_action_overall",
            "baseline_prior_meta_action_overall",
            "forecast_occworld_mIoU_1s",
            "baseline_copy_forecast_occworld_mIoU_1s",
            "baseline_copy_reconstruction_forecast_occworld_mIoU_1s",
            "baseline_true_future_reconstruction_forecast_occworld_mIoU_1s",
            "forecast_trimmed_occworld_mIoU_avg",
            "reconstruction_occworld_mIoU",
            "reconstruction_occ3d_mIoU",
        ):
            assert math.isfinite(m[f"val/{key}"]), key
        assert m["val/caption_samples"] > 0 and m["val/forecast_occworld_frames_1s"] > 0
        assert m["val/forecast_trimmed_occworld_frames_1s"] <= m["val/forecast_occworld_frames_1s"]
    for name in ("plan", "plan_top_anchor", "constant_velocity", "baseline_stationary"):
        assert math.isfinite(planner[f"val/{name}_L2_stp3_avg"]) and math.isfinite(planner[f"val/{name}_L2_uniad_avg"])
    assert planner["val/plan_samples"] > 0 and 0 <= planner["val/scorer_top1"] <= 100
    # Stage 3 trained its own parts beside the LoRA adapter (Sec. 4.2), the LLM frozen.
    import torch
    from safetensors.torch import load_file

    assert (sparse_run / "stage3" / "export" / "llm" / "adapter" / "adapter_config.json").is_file()
    before, after = (load_file(sparse_run / s / "export" / "model.safetensors") for s in ("stage2", "stage3"))
    for part in ("connector.", "forecaster.", "global_queries", "ego_embed."):
        key = next(k for k in before if k.startswith(part))
        assert not torch.equal(before[key], after[key]), key


def test_the_encoder_export_leaves_the_distillation_branch_out(sparse_run):
    from safetensors.torch import load_file

    export = sparse_run / "stage1" / "export"
    config = json.loads((export / "config.json").read_text())
    assert config["arch"] == "sparseocc" and config["discrete"] is False and config["tokens"] == 16
    state = load_file(export / "model.safetensors")
    assert not any(k.startswith("distillation.") for k in state) and any(k.startswith("connector.") for k in state)
    checkpoint_keys = __import__("torch").load(sparse_run / "stage1" / "checkpoints" / "last.ckpt", weights_only=True)[
        "state_dict"
    ]
    assert any(".distillation." in k for k in checkpoint_keys)  # trained with it
    assert not any(k.startswith("teacher.") for k in checkpoint_keys)  # the frozen teacher is not saved


@pytest.mark.parametrize("stage", ["stage1", "stage2", "planner"])
def test_eval_scores_each_stage_on_the_whole_split(sparse_run, stage):
    res = run_cli("eval", str(sparse_run / stage))
    assert res.returncode == 0, res.stderr[-3000:]
    metrics = json.loads((sparse_run / stage / "eval" / "val" / "metrics.json").read_text())
    if stage == "stage1":
        assert (
            metrics["frames"] == 16 and {"occworld_mIoU", "occ3d_mIoU", "baseline_free_occworld_mIoU"} <= metrics.keys()
        )
    elif stage == "stage2":
        assert metrics["caption_samples"] == 16 - 6  # every val frame with a whole future
        assert (
            metrics["forecast_occworld_frames_1s"]
            == metrics["baseline_copy_reconstruction_forecast_occworld_frames_1s"]
            == metrics["baseline_true_future_reconstruction_forecast_occworld_frames_1s"]
            == 16 - 6
        )
        # The paper's frames: the first 5 and last 7 of the 16 left out.
        assert (
            metrics["forecast_trimmed_occworld_frames_1s"]
            == metrics["baseline_copy_forecast_trimmed_occworld_frames_1s"]
            == 16 - 5 - 7
        )
        assert metrics["qa_questions"] > 0 and "baseline_prior_qa_overall" in metrics
    else:
        assert metrics["plan_samples"] == metrics["constant_velocity_samples"] == 16 - 6


def test_kill_9_in_stage_1_and_stage_2_resumes_bit_exact(sparse_run, world, tmp_path):
    import torch
    from safetensors.torch import load_file

    run_dir = tmp_path / "run"
    args = ["run", "recipes/sparseoccvla.yaml", *overrides(world), "--run-dir", str(run_dir)]
    for name in ("stage1", "stage2"):
        kill_at_checkpoint(args, run_dir / name / "checkpoints" / "last.ckpt", step=1)
    res = run_cli("run", "recipes/sparseoccvla.yaml", *overrides(world), "--run-dir", str(run_dir))
    assert res.returncode == 0, res.stderr[-3000:]
    stages = json.loads((run_dir / "manifest.json").read_text())["stages"]
    for name in ("stage1", "stage2"):
        assert stages[name]["attempts"] == 2 and stages[name]["history"][1]["start_step"] >= 1, name
    for name in STAGES:
        ref, got = (
            load_file(sparse_run / name / "export" / "model.safetensors"),
            load_file(run_dir / name / "export" / "model.safetensors"),
        )
        assert ref.keys() == got.keys(), name
        for key in ref:
            assert torch.equal(ref[key], got[key]), f"{name}: {key} differs"


def test_the_stages_train_under_ddp_with_every_parameter_getting_a_gradient(sparse_run, world, tmp_path):
    """Lightning's DDP (find_unused_parameters off) stops a step in which a parameter gets no
    gradient; the stages from stage 1 on run to the end on 2 processes. Training only: DDP
    validation is test_distributed's, and here it would score captions and forecasts on
    both processes of four stages for nothing this test reads."""
    run_dir = tmp_path / "ddp"
    shutil.copytree(sparse_run, run_dir)
    ddp = [f"stages.{s}.trainer.{k}" for s in STAGES[1:] for k in ("devices=2", "strategy=ddp", "limit_val_batches=0")]
    res = run_cli_process(
        "run",
        "recipes/sparseoccvla.yaml",
        *overrides(world),
        *ddp,
        "--restart",
        "stage1",
        "--run-dir",
        str(run_dir),
        timeout=900,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    stages = json.loads((run_dir / "manifest.json").read_text())["stages"]
    for name in STAGES[1:]:
        assert stages[name]["status"] == "done" and stages[name]["history"][-1]["world_size"] == 2, name
    assert stages["vision"]["attempts"] == 1  # reused, not retrained


def test_the_python_api_loads_stage_3_and_forecasts(sparse_run, world):
    import occtrain

    model = occtrain.load(sparse_run / "stage3" / "export")
    assert {"answer", "caption", "decision", "forecast"} <= set(model.operations)
    clip = model.clip(world / "data")
    forecast = model.forecast(clip)
    assert forecast.shape == (6, 200, 200, 16) and forecast.dtype.name == "uint8"
    assert isinstance(model.caption(clip), str) and isinstance(model.answer(clip, "Are there any cars?"), str)


def test_eval_with_blanked_cameras_scores_beside_the_real_ones_and_the_report_sets_them_side_by_side(sparse_run):
    res = run_cli("eval", str(sparse_run / "stage1"), "--blank-cameras")
    assert res.returncode == 0, res.stderr[-3000:]
    blanked = sparse_run / "stage1" / "eval" / "val+blank_cameras" / "metrics.json"
    assert f"metrics -> {blanked}" in res.stdout
    measured = json.loads(blanked.read_text())
    assert measured["provenance"]["world_name"].endswith(", its camera images blanked")
    assert measured["frames"] == 16 and "occworld_mIoU" in measured
    if not (sparse_run / "stage1" / "eval" / "val" / "metrics.json").is_file():
        assert run_cli("eval", str(sparse_run / "stage1")).returncode == 0
    page = run_cli("report", str(sparse_run)).stdout
    row = next(line for line in page.splitlines() if line.startswith("| stage1 | reconstruction mIoU"))
    assert f"the same with its cameras blanked {measured['occworld_mIoU']:.1f}" in row


def test_the_family_keeps_the_contract(sparse_run, tmp_path):
    """Its tasks build, its scorers score, its export round-trips, its inputs are served and
    a few steps lower its loss, checked as every family's are (tests/family_contract.py)."""
    check_contract(sparse_run, "stage2", tmp_path)
