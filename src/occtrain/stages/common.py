"""What the world-model stage kinds share: validation means, family-typed schemas, evaluation."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import field, make_dataclass, replace
from typing import Any

import torch
from omegaconf import OmegaConf
from torchmetrics import MeanMetric

from occtrain.core.registry import get_world
from occtrain.engine import Evaluator, Priors, WorldModelEngine, scorable
from occtrain.errors import ConfigError
from occtrain.metrics import compute_metrics
from occtrain.progress import console, progress_bar
from occtrain.stages.stage import EvalRequest, EvalResult, StepWork, lacking_tasks


def lm_step_work(batch: dict[str, torch.Tensor], samples: int, per_token: Callable[[int], float]) -> StepWork:
    """A language-model step's work: its real tokens (``pad_mask``: a tokenizer whose
    padding is its end-of-text token ends real sequences with that id) and their model
    FLOPs at the batch's row length (what attention computes over), and the positions
    computed, padding included; read before the batch moves to the device, so counting
    costs the GPU no synchronization."""
    pad_mask = batch["pad_mask"]
    tokens = int(pad_mask.sum())
    return StepWork(samples, tokens, tokens * per_token(int(pad_mask.shape[-1])), positions=pad_mask.numel())


class ValidationMeans(torch.nn.Module):
    """Validation means weighted by sample count, each a torchmetrics ``MeanMetric``.

    Under DDP the sums and counts of every rank are gathered before dividing, so a split
    spread unevenly over ranks averages exactly as in one process (Lightning's own
    ``sync_dist`` reduction of a logged value does not promise that).
    """

    def __init__(self, *names: str):
        super().__init__()
        self.names = names
        self.means = torch.nn.ModuleList(MeanMetric() for _ in names)

    def update(self, name: str, value: torch.Tensor | float, weight: int) -> None:
        mean = self.means[self.names.index(name)]
        assert isinstance(mean, MeanMetric)
        mean.update(torch.as_tensor(value, dtype=torch.float32).detach(), weight)

    def pop(self) -> dict[str, float]:
        """The means of this validation (all ranks must call it), then reset."""
        return compute_metrics("", dict(zip(self.names, self.means)), reset=True)


def family_schema(base: type, family: str | None, with_world: bool) -> type:
    """``base`` with ``tasks`` typed by ``family``'s task settings and, ``with_world``, its
    world settings as ``model.<family>``: only what the stage uses is validated and hashed."""
    if family is None:
        return base
    world = get_world(family)
    fields: list[tuple[str, Any, Any]] = [("tasks", world.task_config, field(default_factory=world.task_config))]
    if with_world and world.world_config is not None:
        fields.append((family, world.world_config, field(default_factory=world.world_config)))
    return make_dataclass(f"{base.__name__}_{family}", fields, bases=(base,), namespace={"schema_family": family})


def schema_family(model: Any) -> str | None:
    """The family a validated ``model:`` was typed for by :func:`family_schema` (None: none)."""
    return getattr(OmegaConf.get_type(model), "schema_family", None)


def evaluate_engine(engine: WorldModelEngine, request: EvalRequest) -> EvalResult:
    """Score ``engine``'s generated answers on ``request``'s split (see ``evaluate_export``)."""
    engine.prepare_inputs(request.data_root, request.cache_dir, request.shared_cache_dir)
    specs = engine.task_specs
    unknown = [t for t in request.tasks or [] if t not in specs]
    if unknown:
        raise ConfigError(
            f"--tasks: '{unknown[0]}' is not a task of the '{engine.family}' world model; its tasks are "
            f"{', '.join(specs)}"
        )
    tasks = request.tasks or scorable(specs, engine.tasks.weights)
    if not tasks:
        raise ConfigError(
            f"{request.export}: the stage trained no task with a generated answer to score; name some with --tasks"
        )
    lacking = lacking_tasks(request.data_root, tasks)
    if lacking and (request.tasks or len(lacking) == len(tasks)):
        task, why = next(iter(lacking.items()))
        raise ConfigError(
            f"task {task} {why} ({request.data_root}); score it on a dataset that has it, or leave it out of --tasks"
        )
    if lacking:
        console.print(
            f"[yellow]note[/]: {request.data_root} lacks what {', '.join(lacking)} need; scoring "
            f"{', '.join(t for t in tasks if t not in lacking)}"
        )
        tasks = [t for t in tasks if t not in lacking]
    evaluator = Evaluator(
        tasks,
        specs,
        record=request.record,
        priors=Priors.of(request.data_root, request.shared_cache_dir),
        hooks=engine.spec.eval_hooks,
    )
    torch.manual_seed(0)
    total = evaluator.total(engine, request.data_root, request.split, request.samples)
    if total == 0:
        raise ConfigError(
            f"{request.data_root}: its {request.split} split holds no item for {', '.join(evaluator.tasks)} "
            f"(a clip needs {engine.tasks.context_frames} frames of context and its future); score a dataset with "
            "longer scenes"
        )
    with progress_bar(
        total, f"evaluating {request.export.parent.name} on {request.split} ({', '.join(evaluator.tasks)})"
    ) as advance:
        evaluator.run(
            engine, request.data_root, request.split, request.batch_size, samples=request.samples, advance=advance
        )
    prefix = f"{request.split}/"
    metrics = {k.removeprefix(prefix): v for k, v in evaluator.compute(request.split).items()}
    sets = [replace(s, keys=[k.removeprefix(prefix) for k in s.keys]) for s in evaluator.sample_sets]
    return EvalResult(metrics, evaluator.predictions if request.record else {}, dict(evaluator.coverage), sets)
