"""Where a stage's time goes, read from the durations Lightning's profiler timed."""

from __future__ import annotations

import pytest

from occtrain.stages.phases import PHASES, PhaseProfiler, phase_seconds


def _profiled(durations: dict[str, list[float]]) -> PhaseProfiler:
    profiler = PhaseProfiler()
    for action, seconds in durations.items():
        profiler.recorded_durations[action] = list(seconds)
    return profiler


def test_the_phases_of_three_steps_and_a_validation():
    profiler = _profiled(
        {
            "run_training_batch": [5.0, 1.0, 1.2],
            "[_TrainingEpochLoop].train_dataloader_next": [0.1, 0.2, 0.3],
            # The optimizer step's closure holds the forward and the backward.
            "[LightningModule]TokenizerStage.optimizer_step": [4.9, 0.9, 1.1],
            "[Strategy]DDPStrategy.training_step": [2.0, 0.3, 0.4],
            "[Strategy]DDPStrategy.backward": [2.5, 0.5, 0.6],
            "[Strategy]DDPStrategy.validation_step": [0.7, 0.8],
            "[_EvaluationLoop].val_next": [0.05, 0.05],
            "[LightningModule]TokenizerStage.on_validation_epoch_end": [0.4],
            # A checkpoint written by the checkpoint callback's validation hook: a checkpoint.
            "[Callback]ModelCheckpoint{'monitor': 'val/x'}.on_validation_end": [0.25],
            "save_checkpoint": [0.25, 0.1],
        }
    )
    phases = phase_seconds(profiler)
    assert set(phases) == {f"{p}_phase_s" for p in PHASES} - {"export_phase_s"}  # the runner times the export
    assert phases["data_phase_s"] == pytest.approx(0.6)
    assert phases["forward_phase_s"] == pytest.approx(2.7)
    assert phases["backward_phase_s"] == pytest.approx(3.6)
    assert phases["optimizer_phase_s"] == pytest.approx(6.9 - 2.7 - 3.6)
    assert phases["validation_phase_s"] == pytest.approx(0.7 + 0.8 + 0.1 + 0.4)
    assert phases["checkpoints_phase_s"] == pytest.approx(0.35)
    assert phases["first_step_phase_s"] == pytest.approx(5.0 - 1.2)  # over the median step


def test_a_profiler_that_timed_nothing_gives_zeros():
    assert phase_seconds(_profiled({})) == {
        "data_phase_s": 0.0,
        "forward_phase_s": 0.0,
        "backward_phase_s": 0.0,
        "optimizer_phase_s": 0.0,
        "validation_phase_s": 0.0,
        "checkpoints_phase_s": 0.0,
        "first_step_phase_s": 0.0,
    }


def test_the_profiler_prints_no_report(capsys, caplog):
    profiler = _profiled({"run_training_batch": [1.0]})
    profiler.describe()
    assert capsys.readouterr().out == "" and not caplog.records
