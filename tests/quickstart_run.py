"""The quickstart recipe at test size, shared by the end-to-end test files: its overrides,
the run itself, and readers of what a stage wrote."""

from __future__ import annotations

from pathlib import Path

from conftest import built_once, run_cli_process

STAGES = ("tokenizer", "pretrain", "instruct", "planner", "distill")
#: Optimizer steps per stage of the shared tiny run (a kill test interrupts each in between).
PIPELINE_STEPS = 5


def tiny_overrides(data: Path, steps: int = 3, stages: int = len(STAGES)) -> list[str]:
    """The quickstart recipe (or another whose first stages are tokenizer, pretrain,
    instruct) at test size: a 3-scene world, a few steps per stage."""
    out = [
        f"data.root={data}",
        "data.synth.train_scenes=2",
        "data.synth.val_scenes=1",
        "data.synth.frames_per_scene=13",
        "data.samples_per_shard=8",
        "data.shuffle_buffer=4",
        "trainer.ckpt_every_n_steps=1",
        "trainer.log_every_n_steps=1",
    ]
    for i in range(stages):
        out += [
            f"stages[{i}].trainer.max_steps={steps}",
            f"stages[{i}].trainer.val_check_interval={steps}",
            f"stages[{i}].trainer.limit_val_batches=1",
        ]
    out += [f"stages[{i}].model.val_samples=4" for i in (1, 2, 4) if i < stages]
    # Untrained, the chains of thought run to their length limit: 320 tokens cost the tiny
    # run's validations half its time (5.5 -> 2.8 min beside a training run) and say no more.
    out += [f"stages[{i}].model.max_new_text_tokens=32" for i in (2, 3, 4) if i < stages]
    out += ["stages[1].model.tasks.forecast_frames=2", "stages[1].model.llm.text_vocab_size=400"]
    return out


def quickstart_run(root: Path) -> Path:
    """The tiny quickstart run under ``root`` (data in ``root/data``); its run directory."""
    run_dir = root / "run"
    # Started from scratch as a user starts it: the suite's one run not forked from the
    # warm parent (tests/cli_zygote.py), so nothing comes to depend on it.
    args = [
        "run",
        "recipes/quickstart.yaml",
        *tiny_overrides(root / "data", steps=PIPELINE_STEPS),
        "--run-dir",
        str(run_dir),
    ]
    res = run_cli_process(*args, timeout=900, fresh=True)
    assert res.returncode == 0, res.stderr[-3000:]
    return run_dir


def shared_quickstart_run(tmp_path_factory) -> Path:
    """The tiny quickstart run, made once for the session's test files that read it."""
    return built_once(tmp_path_factory, "quickstart", quickstart_run)


def export_tensors(stage_dir: Path) -> dict:
    from safetensors.torch import load_file

    out = {}
    for f in sorted((stage_dir / "export").rglob("*.safetensors")):
        rel = f.relative_to(stage_dir / "export")
        out.update({f"{rel}:{k}": v for k, v in load_file(f).items()})
    return out


def train_rows(stage_dir: Path) -> list[tuple[str, str]]:
    import csv

    with open(stage_dir / "logs" / "csv" / "metrics.csv", newline="") as fh:
        return [(r["step"], r["train/loss"]) for r in csv.DictReader(fh) if r.get("train/loss")]
