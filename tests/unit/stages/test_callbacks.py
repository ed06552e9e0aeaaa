"""The step meter: a stage's step time, tokens and samples per second and MFU, from what
each step says it processed, with validation left out of the clock."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from occtrain.dashboard.run_view import MFU, THROUGHPUT, charts_from_curves
from occtrain.models.compiling import is_compiled
from occtrain.stages import callbacks
from occtrain.stages.callbacks import StepMeter, cpu_matmul_flops, device_peak_flops
from occtrain.stages.stage import StepWork


class _Module:
    count_flops = False

    def __init__(self):
        self.device = torch.device("cpu")
        self.step_work: StepWork | None = None
        self.logged: list[tuple[str, float]] = []

    def log(self, name, value, batch_size):
        self.logged.append((name, value))


def _run(meter: StepMeter, module: _Module, clock: list[float], steps: list, monkeypatch, loading: float = 0.0):
    """Steps of the given durations, each ending with the given work, ``loading`` s apart."""
    monkeypatch.setattr(callbacks.time, "perf_counter", lambda: clock[0])
    trainer = SimpleNamespace(precision="32-true")
    for seconds, work in steps:
        clock[0] += loading
        meter.on_train_batch_start(trainer, module, None, 0)
        clock[0] += seconds
        module.step_work = work
        meter.on_train_batch_end(trainer, module, None, None, 0)


def test_rates_are_the_kept_steps_work_over_their_own_time(monkeypatch):
    meter, module, clock = StepMeter(warmup=1), _Module(), [100.0]
    meter.peak_flops = 1000.0
    steps = [(9.0, StepWork(2, 50, 500.0)), (1.0, StepWork(2, 100, 400.0)), (3.0, StepWork(4, 200, 2000.0))]
    _run(meter, module, clock, steps, monkeypatch, loading=0.5)
    summary = meter.summary()
    # The first (warm-up) step is left out: 6 samples, 300 tokens, 2,400 FLOPs in 4 s of
    # steps; the step time counts loading the next batch, 0.5 s (intervals 9.5 and 1.5 s:
    # the first is left out).
    assert summary["train_step_s"] == pytest.approx(1.5)
    assert summary["train_samples_per_s"] == pytest.approx(1.5)
    assert summary["train_tokens_per_s"] == pytest.approx(75.0)
    assert summary["train_model_flops_per_s"] == pytest.approx(600.0)
    assert summary["train_mfu"] == pytest.approx(0.6)
    assert summary["train_device_peak_flops_per_s"] == 1000.0
    # Each step's own rates are logged as it ends.
    assert ("train/tokens_per_s", pytest.approx(100.0)) in module.logged
    assert ("train/mfu", pytest.approx(2000.0 / 3.0 / 1000.0)) in module.logged


def test_validation_is_not_a_steps_time_and_a_stage_without_tokens_reports_samples(monkeypatch):
    meter, module, clock = StepMeter(warmup=0), _Module(), [0.0]
    _run(meter, module, clock, [(2.0, StepWork(4))], monkeypatch)
    meter.on_validation_start(None, module)
    clock[0] += 60.0  # a minute validating
    _run(meter, module, clock, [(2.0, StepWork(4)), (2.0, StepWork(4))], monkeypatch)
    summary = meter.summary()
    assert summary["train_step_s"] == pytest.approx(2.0) and summary["train_samples_per_s"] == pytest.approx(2.0)
    assert "train_tokens_per_s" not in summary and "train_mfu" not in summary


def test_the_padding_share_is_of_every_position_the_kept_steps_computed(monkeypatch):
    meter, module, clock = StepMeter(warmup=1), _Module(), [0.0]
    steps = [
        (1.0, StepWork(2, 10, positions=40)),
        (1.0, StepWork(2, 30, positions=40)),
        (1.0, StepWork(2, 20, 0.0, 40)),
    ]
    _run(meter, module, clock, steps, monkeypatch)
    assert meter.summary()["train_padding_share"] == pytest.approx(1 - 50 / 80)
    assert ("train/padding_share", pytest.approx(0.5)) in module.logged  # the last step's own


def test_a_kind_that_counts_flops_gets_every_steps_from_its_first_counted_one(monkeypatch):
    """A kind with ``count_flops`` (the tokenizer, the planner) has its first step counted by
    torch's FlopCounterMode: x (2 x 8) @ w (8 x 4) forward is 2 * 2 * 8 * 4 = 128 FLOPs, w's
    gradient 128 more, 256 for 2 samples. The counted step gets none (counting slowed it);
    the next ones 256 each: 512 FLOPs over their 2 s at a 1,000 FLOP/s peak is an MFU of 0.256.
    Under trainer.compile nothing is counted and no MFU is claimed."""
    clock = [0.0]
    monkeypatch.setattr(callbacks.time, "perf_counter", lambda: clock[0])
    for compiled in (False, True):
        meter, module = StepMeter(warmup=1, count_flops=not compiled), _Module()
        module.count_flops = True
        meter.peak_flops = 1000.0
        trainer = SimpleNamespace(precision="32-true")
        w = torch.randn(8, 4, requires_grad=True)
        # A step whose batch the model reads none of (a planner's clips without a meta
        # action) computes nothing: it is not the step's cost, and the next step is counted.
        meter.on_train_batch_start(trainer, module, None, 0)
        (torch.randn(0, 8) @ w).sum().backward()
        clock[0] += 1.0
        module.step_work = StepWork(samples=2)
        meter.on_train_batch_end(trainer, module, None, None, 0)
        meter.steps.clear()
        for _ in range(3):
            meter.on_train_batch_start(trainer, module, None, 0)
            (torch.randn(2, 8) @ w).sum().backward()
            clock[0] += 1.0
            module.step_work = StepWork(samples=2)
            meter.on_train_batch_end(trainer, module, None, None, 0)
        summary = meter.summary()
        if compiled:
            assert "train_mfu" not in summary and "train_model_flops_per_s" not in summary
        else:
            assert [work.flops for _, work in meter.steps] == [None, 256.0, 256.0]
            assert summary["train_model_flops_per_s"] == pytest.approx(256.0)
            assert summary["train_mfu"] == pytest.approx(0.256)
            # A resumed attempt counts nothing: it reads the count from the checkpoint and
            # gives its first step those FLOPs.
            resumed = StepMeter(warmup=0)
            resumed.load_state_dict(meter.state_dict())
            later = SimpleNamespace(precision="32-true")
            resumed.on_train_batch_start(later, module, None, 0)
            assert resumed._counter is None
            clock[0] += 1.0
            module.step_work = StepWork(samples=4)
            resumed.on_train_batch_end(later, module, None, None, 0)
            assert [work.flops for _, work in resumed.steps] == [512.0]


def test_work_a_stage_does_before_its_step_is_neither_the_steps_time_nor_its_flops(monkeypatch):
    """A dagger stage drives a round and runs its world model on the new frames in its
    ``on_train_batch_start`` (after the meter's): ``restart_step`` leaves that work out of
    the step's clock, of the interval to the next batch, and of the counted FLOPs (the
    step's own 256 here, not the 2 x 64 x 64 x 64 of the work before it)."""
    clock = [0.0]
    monkeypatch.setattr(callbacks.time, "perf_counter", lambda: clock[0])
    meter, module = StepMeter(warmup=0), _Module()
    module.count_flops = True
    trainer = SimpleNamespace(precision="32-true")
    w = torch.randn(8, 4, requires_grad=True)
    for step in range(2):
        meter.on_train_batch_start(trainer, module, None, 0)
        if step == 0:
            torch.randn(64, 64) @ torch.randn(64, 64)  # the round's work
            clock[0] += 60.0
            meter.restart_step()
        (torch.randn(2, 8) @ w).sum().backward()
        clock[0] += 1.0
        module.step_work = StepWork(samples=2)
        meter.on_train_batch_end(trainer, module, None, None, 0)
    assert [seconds for seconds, _ in meter.steps] == [1.0, 1.0]
    assert meter.times == [1.0]
    assert meter.state_dict()["flops_per_sample"] == pytest.approx(128.0)


def test_compile_blocks_compiles_what_the_stage_names_and_says_so_once(capsys):
    block, other = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
    module = SimpleNamespace(compiled_blocks=lambda: [block])
    trainer = SimpleNamespace(is_global_zero=True)
    callbacks.CompileBlocks().on_fit_start(trainer, module)
    assert is_compiled(block) and not is_compiled(other)
    callbacks.CompileBlocks().on_fit_start(trainer, SimpleNamespace())  # a stage kind with none
    out = capsys.readouterr().err  # the run's console writes to stderr
    assert "1 block(s) (Linear) compiled" in out and "has no block to compile" in out


def test_compile_points_inductors_cache_into_the_run_unless_the_user_chose_one(tmp_path, monkeypatch):
    """trainer.compile's kernels go to RUN/cache/inductor (torch's default: the system's
    temp dir, over 100 MB nobody sees) for the stage's fit, and TORCHINDUCTOR_CACHE_DIR is put
    back after; a folder the user set is left alone."""
    import os

    from occtrain.config.groups import TrainerConfig
    from occtrain.stages.trainer import build_trainer

    def compile_blocks(compile: bool) -> list:
        trainer, _ = build_trainer(TrainerConfig(compile=compile, loggers=["csv"]), tmp_path / "run" / "tok", None)
        return [c for c in trainer.callbacks if isinstance(c, callbacks.CompileBlocks)]

    assert compile_blocks(False) == []
    (blocks,) = compile_blocks(True)
    fit = SimpleNamespace(is_global_zero=True, world_size=1)
    for user in (None, str(tmp_path / "mine")):
        if user is None:
            monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
        else:
            monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", user)
        blocks.on_fit_start(fit, SimpleNamespace(compiled_blocks=lambda: [torch.nn.Linear(2, 2)]))
        assert os.environ.get("TORCHINDUCTOR_CACHE_DIR") == (user or str(tmp_path / "run" / "cache" / "inductor"))
        blocks.teardown(fit, None, "fit")
        assert os.environ.get("TORCHINDUCTOR_CACHE_DIR") == user


def test_the_cpu_peak_is_a_measured_matmul_and_other_devices_have_none():
    peak = device_peak_flops(torch.device("cpu"), "32-true")
    assert peak == cpu_matmul_flops(torch.get_num_threads()) and 1e8 < peak < 1e14
    assert device_peak_flops(torch.device("meta"), "32-true") is None


def test_the_dashboard_charts_throughput_and_mfu_apart_from_other_train_curves():
    curves = {
        "train/tokens_per_s": [(1.0, 100.0), (2.0, 120.0)],
        "train/samples_per_s": [(1.0, 2.0), (2.0, 2.5)],
        "train/mfu": [(1.0, 0.01), (2.0, 0.02)],
    }
    charts = {c.title: [s.label for s in c.series] for c in charts_from_curves(curves)}
    assert charts == {THROUGHPUT: ["samples", "tokens"], MFU: ["model FLOPs / peak"]}
