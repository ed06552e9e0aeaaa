"""What keeps one run directory sane: a lock for the run's life, and signals turned into
a clean stop.

A scheduler stops a job with SIGTERM, a person with Ctrl-C (SIGINT). Either one raises
:class:`Interrupted` in the main thread wherever it is; Lightning tears the trainer down
on it like on any exception, the runner records the stage as ``interrupted`` and the CLI
exits 128 + the signal's number (143, 130). ``last.ckpt`` is left as it is: a rerun resumes.
"""

from __future__ import annotations

import errno
import fcntl
import os
import signal
import socket
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import IO

from occtrain.errors import OcctrainError
from occtrain.formats.io import write_error

LOCK_FILE = ".lock"
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


class Interrupted(BaseException):
    """A stop signal arrived. A BaseException, so no ``except Exception`` swallows it."""

    def __init__(self, signum: int, message: str = ""):
        super().__init__(message or f"interrupted by {signal.Signals(signum).name}")
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return 128 + self.signum

    def with_message(self, message: str) -> Interrupted:
        return Interrupted(self.signum, message)


@contextmanager
def stop_on_signals() -> Iterator[None]:
    """Turn the first SIGTERM or SIGINT into :class:`Interrupted`; later ones are ignored
    while the run records where it stopped (a second Ctrl-C must not cut that short)."""

    def handler(signum: int, frame: object) -> None:
        for s in STOP_SIGNALS:
            signal.signal(s, signal.SIG_IGN)
        raise Interrupted(signum)

    previous = {s: signal.signal(s, handler) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


class RunLocked(OcctrainError):
    """Another process holds the run directory."""


@contextmanager
def run_lock(run_dir: Path) -> Iterator[None]:
    """Hold an exclusive OS lock on ``run_dir/.lock`` for the block's life.

    The kernel drops a ``flock`` when its holder exits in any way, kill -9 included, so a
    stale lock file never blocks a later run; the pid written in it only names the holder.
    """
    path = Path(run_dir) / LOCK_FILE
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fh: IO[str] = open(path, "a+")
    except OSError as err:
        raise write_error(path, err) from None
    try:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            if err.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            fh.seek(0)
            holder = fh.read().strip() or "an unknown process"
            raise RunLocked(
                f"{run_dir} is in use by {holder}; wait for it to finish, stop it, or choose another --run-dir"
            ) from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        fh.flush()
        yield
    finally:
        fh.close()  # releases the lock


def lock_holder(run_dir: Path) -> str | None:
    """Who holds ``run_dir``'s lock (as its lock file names them), or None when nobody does:
    found by asking for a shared lock, which writes nothing."""
    try:
        fh = open(Path(run_dir) / LOCK_FILE)
    except OSError:
        return None
    with fh:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            return fh.read().strip() or "an unknown process"
        return None


class StageBusy(OcctrainError):
    """A stage is being scored while a restart would replace it, or the other way round."""


#: The file of a done stage its readers that write into it (``occtrain eval``, ``drive``)
#: lock shared and a ``--restart`` of it alone: its export's config, which exists once the
#: stage is done and moves aside with the stage (a lock belongs to the file, not its path),
#: so taking it writes nothing.
STAGE_LOCK_FILE = ("export", "config.json")


@contextmanager
def stage_lock(run_dir: Path, stage: str, shared: bool, busy: str) -> Iterator[None]:
    """Hold ``run_dir``'s lock of ``stage``, shared (a process scoring it) or exclusive (a
    restart replacing it), for the block's life; when another process holds it the other
    way, raise :class:`StageBusy` with ``busy``, the one line saying who and what to do. A
    stage with no export has nothing to protect: nothing is held."""
    path = Path(run_dir, stage, *STAGE_LOCK_FILE)
    try:
        fh: IO[str] = open(path)
    except FileNotFoundError:
        yield
        return
    except OSError as err:
        raise write_error(path, err) from None
    try:
        try:
            fcntl.flock(fh.fileno(), (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except OSError as err:
            if err.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            raise StageBusy(busy) from None
        yield
    finally:
        fh.close()


def restart_lock(run_dir: Path, stage: str, restart: str) -> AbstractContextManager[None]:
    """The lock ``--restart restart`` holds on a stage it replaces (``restart`` itself or one
    after it): none while the stage is being scored (``occtrain eval`` and ``drive`` share it
    while they read and write it)."""
    busy = (
        f"{run_dir / stage} is being scored by `occtrain eval` or `occtrain drive` in another process; wait for it "
        f"to finish (or stop it), then --restart {restart}"
    )
    return stage_lock(run_dir, stage, shared=False, busy=busy)


def scoring_lock(stage_dir: Path, command: str) -> AbstractContextManager[None]:
    """The lock ``command`` (``occtrain eval`` or ``drive``) holds on a stage while it
    scores it: shared with other scorers, none while ``--restart`` replaces the stage."""
    busy = (
        f"{stage_dir}: the stage is being retrained (`occtrain run --restart`) in another process; run {command} "
        "when that run has finished"
    )
    return stage_lock(stage_dir.parent, stage_dir.name, shared=True, busy=busy)
