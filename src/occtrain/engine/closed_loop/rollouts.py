"""A dagger round's routes driven in worker processes, as ``occtrain drive --workers`` drives
its episodes.

The stage writes the policy's weights of the moment (``safetensors``, named by their
``policy_key``) beside its aggregate; each worker, spawned, rebuilds the planner over its
frozen world model from the consumed exports, loads those weights, checks they hash to the
same key, and drives its routes with one thread, writing each route's frames and record as
the stage would in process (``Aggregate.record``). A route is what it is whichever process
drove it: its seed, its coin and the weights decide it. A cut round resumes at its first
route not recorded, as in process.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from occtrain.data.closed_loop_recording import RecordedDataset
from occtrain.engine.closed_loop import StageDriver
from occtrain.engine.dagger import (
    Aggregate,
    DaggerSettings,
    drive_route,
    load_policy,
    policy_key,
    route_seed,
    scene_name,
)
from occtrain.formats.io import atomic_write_safetensors

POLICIES_DIR = "policies"


@dataclass(frozen=True)
class _Request:
    """What rebuilding the planner reads (a ``PlannerRequest``)."""

    export: Path
    consumed: list[Path]
    data_root: str
    cache_dir: Path | None


@dataclass(frozen=True)
class RolloutJob:
    """One route of a round, with what a worker needs to drive it as the stage would."""

    world_export: str
    planner_export: str
    data_root: str
    #: The policy's weights, their ``policy_key`` and the parameters it hashes (those it trains).
    weights: str
    policy: str
    trainable: tuple[str, ...]
    aggregate: str  # the stage's ``dagger/`` directory
    settings: DaggerSettings
    max_new_text_tokens: int
    camera: tuple[int, int] | None
    round_: int
    route: int
    scratch: str  # where the worker keeps its caches: removed with the round


def write_policy(planner: torch.nn.Module, aggregate: Path, key: str) -> Path:
    """The policy's weights (every tensor of its state) at ``aggregate/policies/<key>.safetensors``."""
    path = aggregate / POLICIES_DIR / f"{key}.safetensors"
    if not path.is_file():
        state = {k: v.detach().cpu().contiguous().clone() for k, v in planner.state_dict().items()}
        atomic_write_safetensors(path, state)
    return path


_DRIVERS: dict[str, StageDriver] = {}  # the policy being driven, loaded once per worker


def _init_worker() -> None:
    torch.set_num_threads(1)
    # Ctrl-C reaches the whole process group: the stage stops its workers itself.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _driver(job: RolloutJob) -> StageDriver:
    from safetensors.torch import load_file

    if job.policy not in _DRIVERS:
        cache = tempfile.mkdtemp(prefix="cache-", dir=job.scratch)
        request = _Request(Path(job.planner_export), [Path(job.world_export)], job.data_root, Path(cache))
        planner, teacher = load_policy(request, "a dagger rollout worker", job.max_new_text_tokens)
        planner.load_state_dict(load_file(job.weights), strict=True)
        for name, param in planner.named_parameters():  # as the stage trains them: what the key hashes
            param.requires_grad_(name in job.trainable)
        if policy_key(planner) != job.policy:
            raise RuntimeError(f"{job.weights}: the weights hash to {policy_key(planner)}, not {job.policy}")
        _DRIVERS.clear()
        _DRIVERS[job.policy] = StageDriver(teacher, planner.eval().waypoints)
    return _DRIVERS[job.policy]


def drive_job(job: RolloutJob) -> int:
    """Drive and record one route; its index."""
    with torch.no_grad():
        settings = job.settings
        aggregate = Aggregate(Path(job.aggregate), settings, RecordedDataset(Path(job.aggregate) / "frames"))
        labelled, result = drive_route(
            _driver(job),
            aggregate.dataset,
            scene_name(job.round_, job.route),
            route_seed(settings, job.round_, job.route),
            settings.seconds,
            settings.beta_at(job.round_),
            job.camera,
            job.policy,
        )
        aggregate.record(labelled, result)
    return job.route


def drive_in_workers(jobs: list[RolloutJob], workers: int, advance: Callable[[int], None]) -> None:
    """Drive ``jobs`` in ``workers`` spawned processes (torch's thread pools do not survive a
    fork), calling ``advance(1)`` as each route is recorded."""
    workers = max(1, min(workers, len(jobs), len(os.sched_getaffinity(0))))
    pool = multiprocessing.get_context("spawn").Pool(workers, initializer=_init_worker)
    with pool:
        for _ in pool.imap_unordered(drive_job, jobs):
            advance(1)


__all__ = ["RolloutJob", "drive_in_workers", "drive_job", "write_policy"]
