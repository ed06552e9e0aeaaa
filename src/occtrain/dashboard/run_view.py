"""Read a run directory into what the page shows: stage entries, curves, final metrics, samples.

A missing run or manifest is an :class:`OcctrainError`; a stage's unreadable log, metrics file or
samples are recorded as that stage's problems and the page shows them instead.
"""

from __future__ import annotations

import csv
import json
import math
import re
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from occtrain.dashboard.samples import read_samples
from occtrain.dashboard.svg import Series
from occtrain.data.stats import DatasetStats
from occtrain.errors import OcctrainError
from occtrain.formats.manifest import MANIFEST_FILE, Manifest, StageEntry
from occtrain.formats.metrics_file import Provenance, read_metrics
from occtrain.report.results import with_gains

METRICS_CSV = Path("logs") / "csv" / "metrics.csv"
MAX_POINTS = 600  # per series; longer curves are thinned evenly to keep the page light


@dataclass
class Chart:
    title: str
    ylabel: str
    series: list[Series]


@dataclass
class DriveView:
    """One ``occtrain drive`` of a stage: each driver's mean scores and the stage's animations."""

    name: str  # the results folder, e.g. seed1000-20s
    routes: int
    seconds: float
    drivers: dict[str, dict[str, float]]
    conventions: dict[str, str]
    #: (caption, GIF bytes) of the stage's own episodes, when ``--save-videos`` kept them.
    videos: list[tuple[str, bytes]] = field(default_factory=list)


@dataclass
class StageView:
    name: str
    entry: StageEntry
    charts: list[Chart] = field(default_factory=list)
    metrics: dict[str, float] = field(default_factory=dict)
    #: What the final metrics were measured on (None: not recorded, a run before provenance).
    provenance: Provenance | None = None
    images: list[tuple[str, bytes]] = field(default_factory=list)
    texts: list[dict[str, str]] = field(default_factory=list)
    drives: list[DriveView] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)


@dataclass
class DataView:
    """The run's dataset beside Occ3D-nuScenes (``occtrain data stats`` on a few val frames)."""

    root: str
    stats: DatasetStats | None = None
    chart: bytes = b""
    problem: str = ""


@dataclass
class RunView:
    run_dir: Path
    name: str
    updated: float | None
    pipeline_yaml: str
    stages: list[StageView]
    data: DataView | None = None


#: Where the dashboard keeps the data statistics it counted, with the world they are of.
DATA_STATS_FILE = "data_stats.json"
#: Val frames counted for the page: enough for the shares, cheap enough for every rewrite.
DATA_FRAMES = 20


def read_data(run_dir: Path, pipeline_yaml: str) -> DataView | None:
    """The statistics of the dataset the run's ``pipeline.yaml`` names (relative to the
    working directory, as ``occtrain run`` read it), counted once per world and kept in
    ``RUN_DIR/data_stats.json``; None when the run records no dataset."""
    from dataclasses import fields

    from omegaconf import OmegaConf

    from occtrain.data.shards import world_key
    from occtrain.data.stats import class_chart, dataset_stats
    from occtrain.formats.io import atomic_write_json, png_bytes

    try:
        root = str(OmegaConf.create(pipeline_yaml).data.root) if pipeline_yaml else ""
    except Exception:  # noqa: BLE001 - any unreadable pipeline.yaml only means no data section
        root = ""
    if not root:
        return None
    if not Path(root).is_dir():
        return DataView(
            root, problem=f"{root}: not found from {Path.cwd()}; run `occtrain dashboard` where the run was started"
        )
    try:
        key = world_key(root)
        cache = run_dir / DATA_STATS_FILE
        saved = json.loads(cache.read_text()) if cache.is_file() else {}
        names = {f.name for f in fields(DatasetStats)}
        if saved.get("world_key") == key and names <= set(saved):
            stats = DatasetStats(**{k: saved[k] for k in names})
        else:
            stats = dataset_stats(root, "val", DATA_FRAMES, progress=False)  # the page is the output
            atomic_write_json(cache, {**stats.to_json(), "world_key": key})
        return DataView(root, stats, png_bytes(class_chart(stats)))
    except (OcctrainError, OSError, ValueError, TypeError) as err:
        return DataView(root, problem=f"{root}: no statistics ({str(err).splitlines()[0]})")


def read_metrics_csv(path: Path) -> dict[str, list[tuple[float, float]]]:
    """Lightning CSVLogger columns -> [(step, value)] for the rows where the column is set."""
    curves: dict[str, list[tuple[float, float]]] = defaultdict(list)
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            try:
                step = float(row.get("step") or "nan")
            except ValueError:  # a header repeated when a resumed logger appends
                continue
            if math.isnan(step):
                continue
            for key, text in row.items():
                if key in (None, "step", "epoch") or not text:
                    continue
                try:
                    value = float(text)
                except (TypeError, ValueError):
                    continue
                if math.isfinite(value):
                    curves[key].append((step, value))
    return {k: sorted(v) for k, v in curves.items()}


def _series(label: str, points: list[tuple[float, float]]) -> Series:
    stride = max(1, math.ceil(len(points) / MAX_POINTS))
    kept = points[::stride]
    if kept[-1] != points[-1]:
        kept.append(points[-1])
    return Series(label, [p[0] for p in kept], [p[1] for p in kept])


#: Validation charts: one per measure, one line per model or baseline scored with it. A
#: metric name (without ``val/``) matching a pattern joins that chart as series ``s``;
#: per-horizon, per-type and count details are left to the final-metrics table.
MEASURES = (
    (re.compile(r"^(?P<s>.*?)_?qa_overall$"), "QA accuracy (%)"),
    (re.compile(r"^(?P<s>.*?)_?meta_action_acc$"), "meta-action accuracy (%)"),
    (
        re.compile(r"^(?P<s>.*?meta_action)_(?P<m>speed|direction|mean|overall)$"),
        "meta-action accuracy: speed, direction, their mean, overall (%)",
    ),
    (re.compile(r"^(?P<s>meta_parsed_fraction)$"), "meta action parsed (%)"),
    (re.compile(r"^(?P<s>.+)_L2_stp3_avg$"), "planning L2, ST-P3 avg (m)"),
    (re.compile(r"^(?P<s>.+)_L2_uniad_avg$"), "planning L2, UniAD avg (m)"),
    (re.compile(r"^(?P<s>.+)_collision_stp3_avg$"), "collision rate, ST-P3 avg (%)"),
    (re.compile(r"^(?P<s>.+)_occworld_mIoU_avg$"), "forecast mIoU, OccWorld avg (%)"),
    (re.compile(r"^(?P<s>.+)_occworld_IoU_avg$"), "forecast IoU, OccWorld avg (%)"),
    (re.compile(r"^(?P<s>.+)_occworld_movable_mIoU_avg$"), "forecast movable-class mIoU, OccWorld avg (%)"),
    (re.compile(r"^(?P<s>.*?)_?(?P<m>mIoU|IoU)$"), "reconstruction IoU and mIoU (%)"),
    (re.compile(r"^(?P<s>.*cot_caption)_(?P<m>CIDEr|Bleu_4|METEOR|ROUGE_L)$"), "chain-of-thought text vs reference"),
    (re.compile(r"^(?P<s>.*token_acc)$"), "token accuracy"),
    (re.compile(r"^(?P<s>.+)_usage$"), "codebook usage over the val split (% of codes)"),
    (re.compile(r"^(?P<s>.+)_perplexity$"), "codebook perplexity over the val split"),
    (re.compile(r"^(?P<s>.*(speedup|tokens_per_s))$"), "generation speed"),
)


#: Per-step training throughput charts (``stages.callbacks.StepMeter``'s log).
THROUGHPUT = "training throughput per second, this device"
MFU = "model FLOPs utilization"
#: Closed-loop training's rounds (a ``dagger`` stage's ``dagger/rollout_*``): the mixture of
#: planner and expert that drove each round's routes, in percent, and its collisions.
ROUND_SCORES, ROUND_COLLISIONS = "closed-loop rounds: driving (%)", "closed-loop rounds: collisions per route"


def _measure(name: str) -> tuple[str, str] | None:
    """(chart title, series label) of a validation metric, None for the details."""
    split, _, leaf = name.partition("/")
    for pattern, title in MEASURES:
        m = pattern.match(leaf)
        if m:
            groups = m.groupdict()
            series = " ".join(v for v in (groups.get("s"), groups.get("m")) if v)
            return title, series or "model"
    return None


def charts_from_curves(curves: dict[str, list[tuple[float, float]]]) -> list[Chart]:
    """Training losses, validation losses, learning rate, then one chart per measure with a
    line per model and baseline (``MEASURES``); details stay in the final table."""
    fixed: dict[str, list[Series]] = {
        "train loss": [], "validation loss": [], "learning rate": [], "codebook usage per train batch": [],
        "codebook perplexity per train batch": [], THROUGHPUT: [], MFU: [], "train, other": [],
        ROUND_SCORES: [], ROUND_COLLISIONS: [],
    }  # fmt: skip
    measures: dict[str, list[Series]] = defaultdict(list)
    for name, points in sorted(curves.items()):
        if name.startswith("lr-"):
            fixed["learning rate"].append(_series(name.removeprefix("lr-"), points))
        elif "loss" in name and name.startswith(("train/", "val/")):
            title = "train loss" if name.startswith("train/") else "validation loss"
            fixed[title].append(_series(name.split("/", 1)[1], points))
        elif name in ("train/tokens_per_s", "train/samples_per_s"):
            fixed[THROUGHPUT].append(_series(name.split("/", 1)[1].replace("_per_s", ""), points))
        elif name.startswith("dagger/rollout_"):
            what = name.removeprefix("dagger/rollout_")
            if what in ("driving_score", "route_completion", "policy_share"):
                fixed[ROUND_SCORES].append(_series(what.replace("_", " "), points))
            elif what == "collisions":
                fixed[ROUND_COLLISIONS].append(_series(what, points))
        elif name == "train/mfu":
            fixed[MFU].append(_series("model FLOPs / peak", points))
        elif name.startswith("train/") and name.endswith(("codebook_usage", "perplexity")):
            kind = "usage" if name.endswith("usage") else "perplexity"
            label = (
                name.split("/", 1)[1].removesuffix("codebook_usage").removesuffix("perplexity").strip("_") or "codebook"
            )
            fixed[f"codebook {kind} per train batch"].append(_series(label, points))
        elif name.startswith("train/"):
            fixed["train, other"].append(_series(name.split("/", 1)[1], points))
        elif name.startswith("val/"):
            found = _measure(name)
            if found:
                measures[found[0]].append(_series(found[1], points))
    fixed["train, other"] = [s for s in fixed["train, other"] if len(set(s.ys)) > 1]  # a constant says nothing
    if all(len(s.xs) < 2 for s in fixed["validation loss"]):
        fixed["validation loss"] = []  # one validation is a dot: the final table has the number
    charts = [Chart(t, "loss" if "loss" in t else "lr" if "rate" in t else "", s) for t, s in fixed.items() if s]
    order = [title for _, title in MEASURES]
    for title in sorted(measures, key=order.index):
        # A validation run once is a dot: the final table says it better.
        if max(len(s.xs) for s in measures[title]) >= 2:
            charts.append(Chart(title, "", measures[title]))
    return charts


def _numbers(raw: dict) -> dict[str, float]:
    """Metrics as floats; ``null`` (how JSON files hold an undefined number) is NaN."""
    return {str(k): float("nan") if v is None else float(v) for k, v in raw.items()}


def _read_stage(run_dir: Path, name: str, entry: StageEntry) -> StageView:
    view = StageView(name, entry, metrics=_numbers(entry.metrics))
    stage_dir = run_dir / name
    csv_path = stage_dir / METRICS_CSV
    if csv_path.is_file():
        try:
            view.charts = charts_from_curves(read_metrics_csv(csv_path))
        except (OSError, csv.Error, UnicodeDecodeError) as err:
            view.problems.append(f"{csv_path}: unreadable training log ({err})")
    metrics_path = stage_dir / "metrics.json"
    if metrics_path.is_file():
        try:
            final = read_metrics(metrics_path)
            view.metrics, view.provenance = final.metrics, final.provenance
        except OcctrainError as err:
            view.problems.append(f"{err}; showing the manifest's copy")
    view.metrics = _with_forecast_gains(view.metrics)
    try:
        view.images, view.texts = read_samples(stage_dir)
    except OcctrainError as err:
        view.problems.append(str(err))
    for summary in sorted((stage_dir / "drive").glob("*/summary.json")):
        try:
            view.drives.append(read_drive(summary, name))
        except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError) as err:
            view.problems.append(f"{summary}: unreadable closed-loop results ({err})")
    return view


def _with_forecast_gains(metrics: dict[str, float]) -> dict[str, float]:
    """A stage's validation metrics with each forecast's gain over its moved query and its
    share of the reachable gain (``report.results.with_gains``, on the ``val/`` keys)."""
    plain = {k.removeprefix("val/"): v for k, v in metrics.items()}
    derived = {f"val/{k}": v for k, v in with_gains(plain).items() if k not in plain}
    return {**metrics, **derived}


#: Animations of the stage's own episodes embedded per drive (the page stays a few MB).
DRIVE_VIDEOS = 8


def read_drive(summary: Path, stage: str) -> DriveView:
    """An ``occtrain drive`` summary of stage ``stage`` and the GIFs of its own episodes."""
    raw = json.loads(summary.read_text())
    drivers = {d: _numbers(scores) for d, scores in raw["drivers"].items()}
    videos: list[tuple[str, bytes]] = []
    for key, path in sorted(raw.get("videos", {}).items()):
        if key.startswith(f"{stage}-") and Path(path).is_file() and len(videos) < DRIVE_VIDEOS:
            videos.append((f"route {key.removeprefix(stage + '-')}", Path(path).read_bytes()))
    return DriveView(
        summary.parent.name, int(raw["routes"]), float(raw["seconds"]), drivers, dict(raw["conventions"]), videos
    )


def load_run(run_dir: Path) -> RunView:
    """Everything the dashboard shows of ``run_dir``; raises OcctrainError when it is no run directory."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise OcctrainError(f"{run_dir}: no such run directory; pass runs/<name> as written by `occtrain run`")
    if not (run_dir / MANIFEST_FILE).is_file():
        raise OcctrainError(
            f"{run_dir}: no {MANIFEST_FILE}, so not a run directory; pass runs/<name> as written by `occtrain run`"
        )
    manifest = Manifest.load(run_dir, writable=False)
    try:
        updated = json.loads(manifest.path.read_text()).get("updated")
    except (OSError, json.JSONDecodeError, AttributeError):
        updated = None
    pipeline = run_dir / "pipeline.yaml"
    pipeline_yaml = pipeline.read_text(errors="replace") if pipeline.is_file() else ""
    stages = [_read_stage(run_dir, name, entry) for name, entry in manifest.stages.items()]
    return RunView(
        run_dir,
        manifest.name or run_dir.name,
        updated if isinstance(updated, (int, float)) else None,
        pipeline_yaml,
        stages,
    )
