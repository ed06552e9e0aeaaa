"""Progress of long work: plain lines in a log, the stage's steps on the training bar."""

from __future__ import annotations

import io
from types import SimpleNamespace

import pytest
from rich.console import Console

from occtrain import progress
from occtrain.progress import INTERVAL_ENV, interval_s, progress_bar, rate_text


def test_a_log_gets_a_plain_line_per_interval_and_a_final_one(monkeypatch, capsys):
    monkeypatch.setenv(INTERVAL_ENV, "0")
    with progress_bar(4, "synthesizing 2 scenes") as advance:
        for _ in range(4):
            advance(1)
    lines = capsys.readouterr().err.strip().splitlines()
    # 1/4, 2/4, 3/4 at each tick; 4/4 is left to the final line, which says how long it took.
    assert [line.split(",")[0] for line in lines] == [f"synthesizing 2 scenes: {n}/4 ({25 * n}%)" for n in (1, 2, 3, 4)]
    assert lines[0].endswith(" left") and ("/s" in lines[0] or " s/each" in lines[0])
    assert lines[-1].endswith(" s") and ", in " in lines[-1]


def test_only_the_final_line_without_an_interval_passing(monkeypatch, capsys):
    monkeypatch.delenv(INTERVAL_ENV, raising=False)
    with progress_bar(3, "planning [3] frames") as advance:  # brackets are text, not markup
        advance(3)
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("planning [3] frames: 3/3 (100%), ") and ", in " in line


@pytest.mark.parametrize("value, seconds", [("0", 0.0), ("2.5", 2.5), ("soon", 30.0), ("-1", 30.0), ("nan", 30.0)])
def test_the_interval_comes_from_the_environment(monkeypatch, value, seconds):
    monkeypatch.setenv(INTERVAL_ENV, value)
    assert interval_s() == seconds


def test_rates_read_well_fast_and_slow():
    assert rate_text(3.14, "step") == "3.14 steps/s"
    assert rate_text(0.08, "step") == "12.5 s/step"
    assert rate_text(0.5, "batch") == "2 s/batch" and rate_text(4, "batch") == "4 batches/s"


# ----------------------------------------------------------------------------- training


def _trainer(step: int, max_steps: int = 20) -> SimpleNamespace:
    return SimpleNamespace(
        global_step=step,
        max_steps=max_steps,
        progress_bar_metrics={"train/loss": 2.25},
        num_val_batches=[4],
        sanity_checking=False,
    )


def _resume_and_train(bar, trainer) -> None:
    """A stage resumed at step 8 of 20 that trains two steps and validates once."""
    bar.on_train_start(trainer, None)
    for step in (9, 10):
        trainer.global_step = step
        bar.on_train_batch_end(trainer, None, None, None, step)
    bar.on_validation_start(trainer, None)
    for i in range(4):
        bar.on_validation_batch_end(trainer, None, None, None, i)
    bar.on_validation_end(trainer, None)
    bar.on_train_end(trainer, None)


def test_training_lines_count_the_stages_steps_after_a_resume(monkeypatch, capsys):
    from occtrain.stages.step_progress import StepProgress

    monkeypatch.setenv(INTERVAL_ENV, "0")
    bar = StepProgress("tokenizer")
    _resume_and_train(bar, _trainer(8))
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert lines[0].startswith("tokenizer: step 9/20 (45%), loss 2.25, ") and lines[0].endswith(" left")
    assert any(line.startswith("tokenizer validation: batch 4/4 (100%)") for line in lines)
    assert lines[-1].startswith("tokenizer: step 10/20 (50%), loss 2.25, ") and ", in " in lines[-1]
    assert bar._train.start == 8  # the rate counts this process's 2 steps, not the 8 before it
    assert "Epoch" not in err and "v_num" not in err


def test_the_terminal_bar_shows_the_stages_steps(monkeypatch):
    from occtrain.stages import step_progress

    out = io.StringIO()
    terminal = Console(file=out, force_terminal=True, width=120, soft_wrap=True)
    monkeypatch.setattr(progress, "console", terminal)
    monkeypatch.setattr(step_progress, "console", terminal)
    bar = step_progress.StepProgress("tokenizer")
    _resume_and_train(bar, _trainer(8))
    text = out.getvalue()
    assert "step 10/20 (50%)" in text and "loss 2.25" in text
    assert "Epoch" not in text and "v_num" not in text
    assert bar._bar is None  # stopped: the terminal is the shell's again


def test_the_trainer_uses_it_instead_of_lightnings_bar(tmp_path):
    from lightning.pytorch.callbacks import ProgressBar

    from occtrain.config.groups import TrainerConfig
    from occtrain.stages.step_progress import StepProgress
    from occtrain.stages.trainer import build_trainer

    trainer, _ = build_trainer(TrainerConfig(max_steps=2, accelerator="cpu"), tmp_path / "tokenizer", None)
    bars = [c for c in trainer.callbacks if isinstance(c, ProgressBar)]
    assert len(bars) == 1 and isinstance(bars[0], StepProgress) and bars[0].name == "tokenizer"


def test_a_table_in_a_log_is_printed_at_its_full_width(monkeypatch, capsys):
    """occtrain drive's and eval's tables on stderr in CI (no terminal): rich would cut them
    to 80 columns, "…" in every cell; a log has no width to fit."""
    from rich.table import Table

    from occtrain.progress import console, print_wide

    monkeypatch.setenv("COLUMNS", "30")
    table = Table(title="driving")
    for name in ("driver", "driving score", "route completion %", "collisions a route", "red lights a route"):
        table.add_column(name)
    table.add_row("constant_acceleration", "64.3", "96.5", "0.38", "0.50")
    width = console.width
    print_wide(table)
    err = capsys.readouterr().err
    assert "constant_acceleration" in err and "red lights a route" in err and "…" not in err
    assert console.width == width
