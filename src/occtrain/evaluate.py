"""``occtrain eval RUN_DIR/STAGE``: score a stage's export on a split.

A world-model export (scene tokenizer + LLM + adapter) is loaded exactly as a later stage
would load it, its answers are generated on every clip of the split, and the papers'
metrics are written to ``<stage>/eval/<split>/metrics.json``. A tokenizer export
reconstructs every frame of the split (IoU/mIoU in both conventions, code use per codebook). ``--save-predictions DIR`` also writes
the predictions in the formats ``occtrain score`` reads, so both paths give one number.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from occtrain.config import load_config
from occtrain.config.recipe import RecipeConfig
from occtrain.errors import ConfigError
from occtrain.io import atomic_write_json, atomic_write_npz
from occtrain.progress import console, progress_bar

#: The world-model stage kinds ``occtrain eval`` scores (besides tokenizers); by default the
#: tasks each trained on, as its validation scored them.
EVAL_KINDS = ("pretrain", "instruct", "distill")


def eval_metrics_file(stage_dir: str | Path, split: str = "val", data_root: str | Path | None = None) -> Path:
    """Where ``evaluate`` writes its metrics."""
    out = Path(stage_dir) / "eval"
    return (out / Path(data_root).resolve().name if data_root is not None else out) / split / "metrics.json"


def evaluate(
    stage_dir: str | Path,
    split: str = "val",
    tasks: list[str] | None = None,
    save_predictions: str | Path | None = None,
    samples: int = -1,
    batch_size: int = 16,
    data_root: str | Path | None = None,
) -> dict[str, float]:
    """Metrics of ``stage_dir``'s export on ``split`` (see the module docstring) of the run's
    dataset, or of ``data_root`` (e.g. a world synthesized from another seed): then the
    metrics go to ``eval/<its directory name>/<split>/`` and its baselines come from its
    own train split."""
    from occtrain.engine import Evaluator, Priors, load_world_model

    stage_dir = Path(stage_dir)
    pipeline = stage_dir.parent / "pipeline.yaml"
    if not pipeline.is_file():
        raise ConfigError(f"{stage_dir}: not a stage of a run directory (no {pipeline}); pass RUN_DIR/STAGE")
    recipe = load_config(RecipeConfig, pipeline)
    spec = next((s for s in recipe.stages if s.name == stage_dir.name), None)
    if spec is None:
        raise ConfigError(f"{pipeline} has no stage '{stage_dir.name}'; stages are {', '.join(s.name for s in recipe.stages)}")
    if spec.kind not in EVAL_KINDS and spec.kind != "tokenizer":
        raise ConfigError(f"occtrain eval scores tokenizer and world-model stages ({', '.join(EVAL_KINDS)}); '{spec.name}' is a {spec.kind} stage")
    if batch_size < 1:
        raise ConfigError(f"--batch-size {batch_size}: must be at least 1")
    if spec.kind == "tokenizer":
        root = str(data_root) if data_root is not None else recipe.data.root
        metrics = reconstruction_metrics(stage_dir / "export", root, split, batch_size, samples)
        return _save(eval_metrics_file(stage_dir, split, data_root), metrics)
    # Prompts and generation length come from the export: exactly what the model trained with.
    engine = load_world_model(stage_dir / "export").eval()
    # Scenes (or a vision-language model's camera tokens) are looked up in the stage's cache
    # (made by the same frozen encoder; built here if the stage trained without one)
    # instead of being encoded per clip.
    out_dir = stage_dir / "eval"
    cache_dir = stage_dir / "cache"
    root = recipe.data.root
    if data_root is not None:
        root = str(data_root)
        out_dir = out_dir / Path(root).resolve().name
        cache_dir = out_dir / "cache"  # another dataset's scenes: never the stage's cache
    engine.prepare_inputs(root, cache_dir)
    unknown = [t for t in tasks or [] if t not in engine.task_builders]
    if unknown:
        raise ConfigError(f"--tasks: '{unknown[0]}' is not a task of the '{engine.family}' world model; its tasks are {', '.join(engine.task_builders)}")
    if not tasks and not Evaluator.scorable(engine.tasks.weights):
        raise ConfigError(f"{stage_dir}: the stage trained no task with a generated answer to score; name some with --tasks")
    # By default the tasks the stage trained on (saved with the export), as its validation scored them.
    evaluator = Evaluator(tasks or Evaluator.scorable(engine.tasks.weights), record=save_predictions is not None, priors=Priors.of(root))
    torch.manual_seed(0)
    total = evaluator.total(engine, root, split, samples)
    with progress_bar(total, f"evaluating {stage_dir.name} on {split} ({', '.join(evaluator.tasks)})") as advance:
        evaluator.run(engine, root, split, batch_size, samples=samples, advance=advance)
    metrics = {k.removeprefix(f"{split}/"): v for k, v in evaluator.compute(split).items()}
    if spec.kind == "distill":
        metrics.update(_speedup(stage_dir.parent / spec.consumes[0] / "export", engine, root, split))
    _save(eval_metrics_file(stage_dir, split, data_root), metrics)
    if save_predictions is not None:
        write_predictions(Path(save_predictions), evaluator.predictions)
    return metrics


def _save(out_file: Path, metrics: dict[str, float]) -> dict[str, float]:
    """Write ``metrics``, keeping what an earlier eval wrote for other tasks; returns them."""
    try:
        earlier = json.loads(out_file.read_text()) if out_file.is_file() else {}
    except ValueError:
        raise ConfigError(f"{out_file}: not readable JSON; move it away to start the stage's eval afresh") from None
    atomic_write_json(out_file, {**earlier, **metrics})
    return metrics


@torch.no_grad()
def reconstruction_metrics(export: Path, data_root: str, split: str, batch_size: int = 16, samples: int = -1) -> dict[str, float]:
    """A tokenizer export's reconstruction of every frame of ``split`` (or the first
    ``samples``): IoU/mIoU in the ``occworld`` and ``occ3d`` conventions, beside an empty
    scene, and each codebook's usage and perplexity over the split."""
    from occtrain.data.layout import DatasetIndex
    from occtrain.families import load_tokenizer
    from occtrain.metrics.reconstruction import ReconstructionMetrics

    model = load_tokenizer(export)
    index = DatasetIndex.open(data_root)
    frames = [(scene, token) for scene in index.splits.get(split, []) for token in index.scenes[scene]]
    frames = frames if samples < 0 else frames[:samples]
    recon = ReconstructionMetrics(dict(zip(model.codebook_names, model.codebook_sizes)))
    with progress_bar(len(frames), f"reconstructing {len(frames)} {split} frames") as advance:
        for i in range(0, len(frames), batch_size):
            labels = [index.labels(scene, token) for scene, token in frames[i : i + batch_size]]
            sem = torch.from_numpy(np.stack([x["semantics"] for x in labels])).long()
            mask = torch.from_numpy(np.stack([x["mask_camera"] for x in labels])).bool()
            codes = model.encode(sem)
            recon.update(model.decode(codes).argmax(1), sem, mask, codes)
            advance(len(labels))
    return {"frames": float(len(frames)), **recon.compute()}


def _speedup(teacher_export: Path, student, data_root: str, split: str) -> dict[str, float]:
    """The distilled student's generation speed against its teacher's, by the protocol the
    distill stage's validation uses (``engine.speed``)."""
    from occtrain.engine import compare_generation_speed, load_world_model, speed_prompt

    if not (teacher_export / "config.json").is_file():
        raise ConfigError(f"{teacher_export}: the distill stage's teacher export is missing; its speedup needs it")
    teacher = load_world_model(teacher_export).eval()
    teacher.code_cache = student.code_cache  # one frozen scene tokenizer: the same codes
    speed = compare_generation_speed({"teacher": teacher, "student": student}, speed_prompt(student, data_root, split))
    return {"student_tokens_per_s": speed["student"], "teacher_tokens_per_s": speed["teacher"], "speedup": speed["student"] / speed["teacher"]}


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


def sample_count(name: str, metrics: dict[str, float]) -> float | None:
    """How many samples ``name`` was computed on: the ``<family>_samples`` (or
    ``_questions``) entry of the longest family prefix of ``name`` that has one."""
    if name.startswith(("meta_", "baseline_prior_meta_")):
        return metrics.get("meta_action_samples")
    parts = name.split("_")
    for n in range(len(parts), 0, -1):
        prefix = "_".join(parts[:n])
        # A forecast's average is over its horizons; each horizon counts its own frames.
        for suffix in ("_samples", "_questions", f"_frames_{parts[-1]}", "_frames_1s"):
            if prefix + suffix in metrics:
                return metrics[prefix + suffix]
    return None


def print_metrics(metrics: dict[str, float], title: str) -> None:
    """A table of the metrics with the sample count each was computed on."""
    from rich.table import Table

    table = Table(title=title)
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_column("samples", justify="right")
    for name in sorted(metrics):
        if name.endswith(("_samples", "_questions")) or "_frames_" in name:
            continue  # shown in the samples column
        n = sample_count(name, metrics)
        table.add_row(name, f"{metrics[name]:.4g}", "" if n is None else f"{n:.0f}")
    console.print(table)
