"""A dagger round's routes driven in worker processes, as ``occtrain drive --workers`` drives
its episodes.

The stage writes the policy's weights of the moment (``safetensors``, named by their
``policy_key``) beside its aggregate; each worker, spawned, rebuilds the planner over its
frozen world model from the consumed exports, loads those weights, checks they hash to the
same key, and drives its routes (``workers.run_jobs``), writing each route's frames and record as
the stage would in process (``Aggregate.record``). A route is what it is whichever process
drove it: its seed, its coin and the weights decide it. A cut round resumes at its first
route not recorded, as in process.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from occtrain.data.closed_loop_recording import RecordedDataset
from occtrain.engine.closed_loop.dagger import (
    Aggregate,
    DaggerSettings,
    drive_route,
    load_policy,
    policy_key,
    route_seed,
    scene_name,
)
from occtrain.engine.closed_loop.planners import StageDriver
from occtrain.engine.closed_loop.workers import driver_for, run_jobs
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
class PolicySpec:
    """The policy of the moment as a worker rebuilds it: the planner over its frozen world
    model from the consumed exports, with the stage's weights (``weights``, hashing to
    ``policy`` over the ``trainable`` parameters)."""

    world_export: str
    planner_export: str
    data_root: str
    weights: str
    policy: str
    trainable: tuple[str, ...]
    max_new_text_tokens: int
    scratch: str  # where the worker keeps its caches: removed with the round

    @property
    def key(self) -> str:
        return self.policy

    def build(self) -> StageDriver:
        from safetensors.torch import load_file

        cache = tempfile.mkdtemp(prefix="cache-", dir=self.scratch)
        request = _Request(Path(self.planner_export), [Path(self.world_export)], self.data_root, Path(cache))
        planner, teacher = load_policy(request, "a dagger rollout worker", self.max_new_text_tokens)
        planner.load_state_dict(load_file(self.weights), strict=True)
        for name, param in planner.named_parameters():  # as the stage trains them: what the key hashes
            param.requires_grad_(name in self.trainable)
        if policy_key(planner) != self.policy:
            raise RuntimeError(f"{self.weights}: the weights hash to {policy_key(planner)}, not {self.policy}")
        return StageDriver(teacher, planner.eval().waypoints)


@dataclass(frozen=True)
class RolloutJob:
    """One route of a round, with what a worker needs to drive it as the stage would."""

    spec: PolicySpec
    aggregate: str  # the stage's ``dagger/`` directory
    settings: DaggerSettings
    camera: tuple[int, int] | None
    round_: int
    route: int


def write_policy(planner: torch.nn.Module, aggregate: Path, key: str) -> Path:
    """The policy's weights (every tensor of its state) at ``aggregate/policies/<key>.safetensors``."""
    path = aggregate / POLICIES_DIR / f"{key}.safetensors"
    if not path.is_file():
        state = {k: v.detach().cpu().contiguous().clone() for k, v in planner.state_dict().items()}
        atomic_write_safetensors(path, state)
    return path


def drive_job(job: RolloutJob) -> int:
    """Drive and record one route; its index."""
    with torch.no_grad():
        settings = job.settings
        aggregate = Aggregate(Path(job.aggregate), settings, RecordedDataset(Path(job.aggregate) / "frames"))
        labelled, result = drive_route(
            driver_for(job.spec),
            aggregate.dataset,
            scene_name(job.round_, job.route),
            route_seed(settings, job.round_, job.route),
            settings.seconds,
            settings.beta_at(job.round_),
            job.camera,
            job.spec.policy,
        )
        aggregate.record(labelled, result)
    return job.route


def drive_in_workers(jobs: list[RolloutJob], workers: int, advance: Callable[[int], None]) -> None:
    """Drive ``jobs`` in ``workers`` spawned processes, calling ``advance(1)`` as each route is recorded."""
    run_jobs(drive_job, jobs, workers, advance)


__all__ = ["PolicySpec", "RolloutJob", "drive_in_workers", "drive_job", "write_policy"]
