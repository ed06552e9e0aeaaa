"""Where a stage's time goes: its training steps split into loading, forward, backward and
the optimizer, beside its validations, checkpoint writes and first step.

Lightning's ``SimpleProfiler`` already times each of the loops' actions (a perf counter
around each, a few microseconds a step); this reads its durations into a stage's
``metrics.json`` as ``<phase>_phase_s`` rather than printing its hundred-line report.
"""

from __future__ import annotations

from collections.abc import Mapping

from lightning.pytorch.profilers import SimpleProfiler

#: The phases, in the order a table shows them, and what each holds.
PHASES = {
    "data": "waiting for the data loader's next training batch",
    "forward": "the training steps' forward passes and losses",
    "backward": "their backward passes",
    "optimizer": "the optimizer steps, gradient clipping and zeroing",
    "validation": "validations, the final one included: their batches, steps and metrics",
    "checkpoints": "checkpoint writes",
    "export": "the export (a sharded stage's gather included)",
    "first_step": "the first training step beyond a typical one (FLOP counting, a compile, warm caches)",
}


class PhaseProfiler(SimpleProfiler):
    """``SimpleProfiler`` without its report: :func:`phase_seconds` reads what it timed."""

    def describe(self) -> None:
        pass


def _hook(durations: Mapping[str, list[float]], owner: str, action: str) -> float:
    """The seconds of an ``owner``'s ``action`` (``[Strategy]DDPStrategy.backward``, ...)."""
    return sum(sum(v) for k, v in durations.items() if k.startswith(f"[{owner}]") and k.endswith(f".{action}"))


def _matching(durations: Mapping[str, list[float]], *parts: str, but: str = "\0") -> float:
    return sum(sum(v) for k, v in durations.items() if any(p in k for p in parts) and but not in k)


def phase_seconds(profiler: SimpleProfiler) -> dict[str, float]:
    """The seconds of each of :data:`PHASES` the profiler timed, as ``<phase>_phase_s``.

    Lightning runs a step's forward and backward inside the optimizer step's closure, so
    the optimizer's share is the optimizer step's time less theirs. ``first_step`` is the
    first training batch's time less the median batch's: it overlaps the other phases
    (the first step's forward and backward are in theirs too)."""
    durations: Mapping[str, list[float]] = profiler.recorded_durations
    forward = _hook(durations, "Strategy", "training_step")
    backward = _hook(durations, "Strategy", "backward")
    stepping = _hook(durations, "LightningModule", "optimizer_step")
    batches = durations.get("run_training_batch", [])
    typical = sorted(batches)[len(batches) // 2] if batches else 0.0
    # A checkpoint callback's validation hooks write checkpoints, counted under their own phase.
    validating = _matching(durations, "validation_step", "val_next", "on_validation_", but="ModelCheckpoint")
    return {
        "data_phase_s": _matching(durations, "train_dataloader_next"),
        "forward_phase_s": forward,
        "backward_phase_s": backward,
        "optimizer_phase_s": max(stepping - forward - backward, 0.0),
        "validation_phase_s": validating,
        "checkpoints_phase_s": _matching(durations, "save_checkpoint"),
        "first_step_phase_s": max(batches[0] - typical, 0.0) if batches else 0.0,
    }
