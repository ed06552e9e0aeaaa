"""The terminal progress of a stage's steps, one readable line at a time when not on a terminal."""

from __future__ import annotations

import math
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import ProgressBar
from rich.progress import BarColumn, Progress, TextColumn

from occtrain.progress import Ticker, console, plain


class StepProgress(ProgressBar):
    """The stage's optimizer steps (``step 8/20``), loss, rate and time left: a bar on a
    terminal, a plain line every few seconds in a log (see :mod:`occtrain.progress`).

    Lightning's own bars count the batches of an epoch, which a stage budgeted in steps
    does not have: they showed ``Epoch 0/-2``, the logger's version and ``8/5`` after a
    resume. Validation gets a line of its own, as batches of the validation loop.
    """

    def __init__(self, name: str):
        super().__init__()
        self.name = name
        self.enabled = True
        self._bar: Progress | None = None
        self._tasks: dict[str, Any] = {}
        self._train: Ticker | None = None
        self._val: Ticker | None = None

    def disable(self) -> None:
        self.enabled = False

    def enable(self) -> None:
        self.enabled = True

    def print(self, *args: Any, **kwargs: Any) -> None:
        console.print(*args, **kwargs)  # the bar's own console: printed above the bar, not through it

    @staticmethod
    def _metrics(trainer: L.Trainer) -> str:
        # What the stage logs with prog_bar=True (its training loss), without the "train/" prefix.
        items = trainer.progress_bar_metrics.items()
        return ", ".join(f"{k.removeprefix('train/')} {v:.4g}" for k, v in items if isinstance(v, (int, float)))

    def _show(self, key: str, ticker: Ticker) -> None:
        """Start ``ticker``'s row of the bar (terminal) or keep it quiet until its interval (log)."""
        if plain():
            return
        ticker.every_s = math.inf  # the bar shows it; no plain lines through the bar
        if self._bar is None:
            self._bar = Progress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                TextColumn("{task.fields[text]}"),
                console=console,
                transient=False,
            )
            self._bar.start()
        self._tasks[key] = self._bar.add_task(
            ticker.description, total=ticker.total, completed=ticker.done, text=ticker.text()
        )

    def _set(self, key: str, ticker: Ticker, done: int, extra: str = "", final: bool = False) -> None:
        ticker.update(done, extra)
        if self._bar is not None and key in self._tasks:
            self._bar.update(self._tasks[key], completed=done, text=ticker.text(extra, final))

    def _stop(self) -> None:
        if self._bar is not None:
            self._bar.stop()
        self._bar, self._tasks = None, {}

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self.enabled:
            return
        total = trainer.max_steps if trainer.max_steps and trainer.max_steps > 0 else None
        # A resume starts at its checkpoint's step; the rate counts this process's steps only.
        self._train = Ticker(self.name, total, start=trainer.global_step, unit="step")
        self._show("train", self._train)

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        if self.enabled and self._train is not None:
            self._set("train", self._train, trainer.global_step, self._metrics(trainer))

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.enabled and self._train is not None:
            self._set("train", self._train, trainer.global_step, self._metrics(trainer), final=True)
            if plain():
                self._train.say(self._metrics(trainer), final=True)
        self._stop()

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self.enabled or trainer.sanity_checking:
            return
        batches = trainer.num_val_batches
        total = sum(batches) if isinstance(batches, list) else batches
        self._val = Ticker(
            f"{self.name} validation", int(total) if math.isfinite(total) and total > 0 else None, unit="batch"
        )
        self._show("val", self._val)

    def on_validation_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        if self.enabled and self._val is not None:
            self._set("val", self._val, self._val.done + 1)

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self._val is None:
            return
        if plain():
            self._val.say(final=True)
        if self._bar is not None and "val" in self._tasks:
            self._bar.remove_task(self._tasks.pop("val"))
        if "train" not in self._tasks:  # trainer.validate(): no training row to keep the bar for
            self._stop()
        self._val = None

    def on_exception(self, *args: Any, **kwargs: Any) -> None:
        self._stop()  # leave the terminal usable for the traceback

    def teardown(self, *args: Any, **kwargs: Any) -> None:
        self._stop()
