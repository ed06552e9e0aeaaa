"""One worker pool for episodes: ``occtrain drive``'s and a dagger stage's rollouts alike.

Episodes are independent, so they run in spawned worker processes (torch's thread pools do
not survive a fork), each with its share of the cores. A worker builds what drives from a
picklable :class:`DriverSpec` the job carries, once per process (the next job of the same
spec reuses it), and builds each route's world once, handing every driver a copy: the
drivers of a route all start from the same world.
"""

from __future__ import annotations

import copy
import multiprocessing
import os
import signal
from collections.abc import Callable, Iterable
from typing import Any, Protocol, TypeVar

import torch

from occtrain.data.closed_loop_recording import DrivingWorld

Job = TypeVar("Job")


class DriverSpec(Protocol):
    """What builds a driver in a worker: picklable, named by ``key`` (two specs of one key
    build the same driver)."""

    @property
    def key(self) -> str: ...

    def build(self) -> Any: ...


_BUILT: dict[str, Any] = {}  # the last driver this process built, by its spec's key
_WORLDS: dict[tuple[int, float], DrivingWorld] = {}  # the last route this process built


def driver_for(spec: DriverSpec) -> Any:
    """The driver ``spec`` builds, built once per process (one at a time is kept)."""
    if spec.key not in _BUILT:
        _BUILT.clear()
        _BUILT[spec.key] = spec.build()
    return _BUILT[spec.key]


def fresh_world(seed: int, seconds: float) -> DrivingWorld:
    """Route ``seed`` for ``seconds`` as it starts: built once per process, a copy per driver."""
    key = (int(seed), float(seconds))
    if key not in _WORLDS:
        _WORLDS.clear()
        _WORLDS[key] = DrivingWorld(seed, seconds)
    return copy.deepcopy(_WORLDS[key])


def _init_worker(threads: int) -> None:
    torch.set_num_threads(threads)
    # Ctrl-C reaches the whole process group: the parent stops its workers itself.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def usable_workers(asked: int, jobs: int) -> int:
    """How many workers ``jobs`` jobs get: at most one each and one a core."""
    return max(1, min(asked, jobs, len(os.sched_getaffinity(0))))


def run_jobs(fn: Callable[[Job], object], jobs: Iterable[Job], workers: int, advance: Callable[[int], None]) -> None:
    """``fn(job)`` for every job: in this process with one worker, else in ``workers``
    spawned processes of ``cores // workers`` threads each; ``advance(1)`` as each ends. A
    pool, not an executor: on a stop signal its terminate() ends the workers at once."""
    jobs = list(jobs)
    workers = usable_workers(workers, len(jobs))
    if workers == 1:
        for job in jobs:
            fn(job)
            advance(1)
        return
    threads = max(1, len(os.sched_getaffinity(0)) // workers)
    pool = multiprocessing.get_context("spawn").Pool(workers, initializer=_init_worker, initargs=(threads,))
    with pool:
        for _ in pool.imap_unordered(fn, jobs):
            advance(1)


__all__ = ["DriverSpec", "driver_for", "fresh_world", "run_jobs", "usable_workers"]
