"""Progress of long work: a rich bar on a terminal, a plain line now and then in a log file."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

#: Lines are never hard-wrapped (a terminal wraps them for the eye; a log file or a grep
#: needs each message on one line).
console = Console(stderr=True, soft_wrap=True)


def print_wide(table: Any, to: Console | None = None) -> None:
    """A rich table on ``to`` (the console): fitted to a terminal, and at its full width in
    a log file or CI output, which have no width to fit (rich would cut it to 80 columns)."""
    to = to or console
    if to.is_terminal:
        to.print(table)
        return
    width = to.width
    to.width = max(to.measure(table, options=to.options.update_width(10_000)).maximum, 1)
    try:
        to.print(table)
    finally:
        to.width = width


#: Seconds between two plain progress lines when stderr is not a terminal.
INTERVAL_ENV = "OCCTRAIN_PROGRESS_INTERVAL"
DEFAULT_INTERVAL_S = 30.0


def interval_s() -> float:
    """The plain lines' interval: ``$OCCTRAIN_PROGRESS_INTERVAL`` seconds, else 30."""
    try:
        value = float(os.environ.get(INTERVAL_ENV, DEFAULT_INTERVAL_S))
    except ValueError:
        return DEFAULT_INTERVAL_S
    return value if math.isfinite(value) and value >= 0 else DEFAULT_INTERVAL_S


def plain() -> bool:
    """Whether progress goes out as plain lines: stderr is a log file or a pipe, where a
    redrawn bar is either dropped (rich) or thousands of carriage returns (tqdm)."""
    return not console.is_terminal


def duration(seconds: float) -> str:
    """``9 s``, ``4 min 05 s``, ``2 h 03 min``: short enough for a progress line."""
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def rate_text(rate: float, unit: str = "") -> str:
    """``3.1 steps/s`` when fast, ``12 s/step`` when slow: never ``0.08/s``."""
    plural = f" {unit}{'es' if unit.endswith(('s', 'ch', 'sh', 'x')) else 's'}" if unit else ""
    if rate >= 1 or rate <= 0:
        return f"{rate:.3g}{plural}/s"
    return f"{1 / rate:.3g} s/{unit or 'each'}"


class Ticker:
    """Progress of one piece of work as text: done of total, rate and time left.

    ``start`` is where this process began (a resumed run starts past 0): the rate counts
    only what this process did, so a resume does not claim the earlier steps' speed.
    """

    def __init__(
        self, description: str, total: int | None, start: int = 0, unit: str = "", every_s: float | None = None
    ):
        self.description, self.total, self.unit = description, total, unit
        self.start = self.done = start
        self.every_s = interval_s() if every_s is None else every_s
        self.t0 = self.last = time.monotonic()

    def text(self, extra: str = "", final: bool = False) -> str:
        """``12/40 (30%), loss 2.1, 3.1/s, 9 s left`` (``in 13 s`` once ``final``)."""
        elapsed = time.monotonic() - self.t0
        prefix = f"{self.unit} " if self.unit else ""
        parts = [
            f"{prefix}{self.done}/{self.total} ({100 * self.done // max(1, self.total)}%)"
            if self.total
            else f"{prefix}{self.done}"
        ]
        if extra:
            parts.append(extra)
        made = self.done - self.start
        rate = made / elapsed if elapsed > 0 and made > 0 else None
        if rate is not None:
            parts.append(rate_text(rate, self.unit))
        if final:
            parts.append(f"in {duration(elapsed)}")
        elif rate is not None and self.total:
            parts.append(f"{duration(max(0, self.total - self.done) / rate)} left")
        return ", ".join(parts)

    def update(self, done: int, extra: str = "") -> None:
        """Set the count; print a line when the interval has passed since the last one."""
        self.done = done
        now = time.monotonic()
        # The last count is left to the final line, which says how long it all took.
        if now - self.last >= self.every_s and not (self.total and done >= self.total):
            self.last = now
            self.say(extra)

    def say(self, extra: str = "", final: bool = False) -> None:
        from occtrain.ranks import is_rank_zero

        if not is_rank_zero():  # every rank writes the same log: one set of lines says it all
            return
        # markup and highlighting off: a description may hold brackets, and a log wants no escapes
        console.print(f"{self.description}: {self.text(extra, final)}", markup=False, highlight=False)


@contextmanager
def progress_bar(total: int, description: str) -> Iterator[Callable[[int], None]]:
    """Yield ``advance(n)``: a bar on a terminal; otherwise a plain line every
    :func:`interval_s` seconds and one at the end, so a log shows the work is moving."""
    if plain():
        ticker = Ticker(description, total)

        def tick(n: int = 1) -> None:
            ticker.update(ticker.done + n)

        yield tick
        if total:
            ticker.say(final=True)
        return
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    ) as bar:
        task = bar.add_task(description, total=total)

        def advance(n: int = 1) -> None:
            bar.advance(task, n)

        yield advance
