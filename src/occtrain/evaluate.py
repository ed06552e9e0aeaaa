"""``occtrain eval RUN_DIR/STAGE``: score a world-model stage's export on a split.

The export (scene tokenizer + LLM + adapter) is loaded exactly as a later stage would load
it, its answers are generated on every clip of the split, and the papers' metrics are
written to ``<stage>/eval/<split>/metrics.json``. ``--save-predictions DIR`` also writes
the predictions in the formats ``occtrain score`` reads, so both paths give one number.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from occtrain.config import load_config
from occtrain.config.recipe import RecipeConfig
from occtrain.errors import ConfigError
from occtrain.io import atomic_write_json, atomic_write_npz
from occtrain.progress import console, progress_bar

#: World-model stage kinds, and whether ``--tasks`` defaults to the scorable tasks of
#: pretraining (forecasting, planning) or of instruction tuning (QA, chain of thought).
EVAL_KINDS = {"pretrain": "pretrain", "instruct": "instruct", "distill": "instruct"}


def evaluate(
    stage_dir: str | Path,
    split: str = "val",
    tasks: list[str] | None = None,
    save_predictions: str | Path | None = None,
    limit_batches: int | None = None,
    batch_size: int = 16,
) -> dict[str, float]:
    """Metrics of ``stage_dir``'s export on ``split`` (see the module docstring)."""
    from occtrain.data.clips import clips_from_batch
    from occtrain.data.datamodule import ShardDataModule, shards_dir
    from occtrain.data.shards import shard_urls
    from occtrain.engine import CODE_CACHE, Evaluator, load_world_model, qa_prior
    from occtrain.families.occllama.tasks import INSTRUCT_TASKS, PRETRAIN_TASKS

    stage_dir = Path(stage_dir)
    pipeline = stage_dir.parent / "pipeline.yaml"
    if not pipeline.is_file():
        raise ConfigError(f"{stage_dir}: not a stage of a run directory (no {pipeline}); pass RUN_DIR/STAGE")
    recipe = load_config(RecipeConfig, pipeline)
    spec = next((s for s in recipe.stages if s.name == stage_dir.name), None)
    if spec is None:
        raise ConfigError(f"{pipeline} has no stage '{stage_dir.name}'; stages are {', '.join(s.name for s in recipe.stages)}")
    if spec.kind not in EVAL_KINDS:
        raise ConfigError(f"occtrain eval scores world-model stages ({', '.join(EVAL_KINDS)}); '{spec.name}' is a {spec.kind} stage")
    # Prompts and generation length come from the export: exactly what the model trained with.
    engine = load_world_model(stage_dir / "export").eval()
    # Scenes are looked up in the stage's code cache (made by the same frozen tokenizer;
    # built here if the stage trained without one) instead of being encoded per clip.
    engine.build_code_cache(recipe.data.root, stage_dir / "cache" / CODE_CACHE)
    group = PRETRAIN_TASKS if EVAL_KINDS[spec.kind] == "pretrain" else INSTRUCT_TASKS
    evaluator = Evaluator(tasks or [t for t in Evaluator.TASKS if t in group], record=save_predictions is not None, qa_prior=qa_prior(recipe.data.root))
    if batch_size < 1:
        raise ConfigError(f"--batch-size {batch_size}: must be at least 1")
    # Clips of a batch generate together (one forward per step for all of them).
    data_cfg = OmegaConf.merge(recipe.data, {"batch_size": batch_size})
    data = ShardDataModule(data_cfg, "clips")
    data.prepare_data()
    loader = data.loader(split, train=False)
    _, samples = shard_urls(shards_dir(recipe.data), "clips", split)
    batches = math.ceil(samples / batch_size)
    if limit_batches is not None:
        batches = min(batches, limit_batches)
    torch.manual_seed(0)
    with progress_bar(batches, f"evaluating {stage_dir.name} on {split}") as advance:
        for i, batch in enumerate(loader):
            if limit_batches is not None and i >= limit_batches:
                break
            evaluator.update(engine, clips_from_batch(batch), batch)
            advance(1)
    metrics = {k.removeprefix(f"{split}/"): v for k, v in evaluator.compute(split).items()}
    out_file = stage_dir / "eval" / split / "metrics.json"
    # An eval of some tasks keeps the numbers an earlier eval wrote for the others.
    try:
        earlier = json.loads(out_file.read_text()) if out_file.is_file() else {}
    except ValueError:
        raise ConfigError(f"{out_file}: not readable JSON; move it away to start the stage's eval afresh") from None
    atomic_write_json(out_file, {**earlier, **metrics})
    if save_predictions is not None:
        write_predictions(Path(save_predictions), evaluator.predictions)
    return metrics


def write_predictions(out: Path, predictions: dict[str, dict]) -> None:
    """The evaluator's recorded predictions in ``occtrain score``'s input formats."""
    out.mkdir(parents=True, exist_ok=True)
    if predictions["planning"]:
        atomic_write_json(out / "planning_pred.json", predictions["planning"])
        atomic_write_json(out / "planning_gt.json", predictions["planning_gt"])
    for token, (scene, semantics) in predictions["forecast"].items():
        atomic_write_npz(out / "forecast" / scene / token / "forecast.npz", {"semantics": np.asarray(semantics, dtype=np.uint8)})
    if predictions["qa"]:
        # NuScenes-QA's format: answers in the order of a questions file, written beside them.
        questions, answers = zip(*predictions["qa"].values())
        atomic_write_json(out / "qa_questions.json", {"questions": list(questions)})
        atomic_write_json(out / "qa_pred.json", list(answers))
    if predictions["captions"]:
        atomic_write_json(out / "captions_pred.json", predictions["captions"])
        atomic_write_json(out / "captions_ref.json", predictions["captions_gt"])


def print_metrics(metrics: dict[str, float], title: str) -> None:
    """A two-column table of the metrics, grouped by their prefix."""
    from rich.table import Table

    table = Table(title=title)
    table.add_column("metric")
    table.add_column("value", justify="right")
    for name in sorted(metrics):
        table.add_row(name, f"{metrics[name]:.4g}")
    console.print(table)
