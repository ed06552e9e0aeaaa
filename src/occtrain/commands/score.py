"""``occtrain score``: score anyone's predictions with the papers' metric conventions.

Each subcommand reads prediction and ground-truth files, feeds them through the same
:mod:`occtrain.metrics` classes that training validates with, prints one JSON object on
stdout and, with ``--out FILE``, writes it atomically. Numbers that are undefined (a
class absent from both sides under Occ3D rules) come out as ``null``.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any, Literal, NotRequired, TypedDict

import numpy as np

from occtrain.data.labels import load_labels, read_npz
from occtrain.data.layout import ANNOTATIONS_FILE, GTS_DIR, LABELS_FILE, DatasetIndex
from occtrain.data.schema import QAFile, Vec2
from occtrain.data.validate import Len, first_problem
from occtrain.errors import DataError
from occtrain.formats.io import atomic_write_json, finite_or_null, parse_json
from occtrain.formats.occ3d import FUTURE_STEPS, GRID_SHAPE, NUM_CLASSES

# The metrics (torch, torchmetrics) load with the first score, not with the CLI's parser.
from occtrain.metrics.conventions import FORECAST_FILE, FORECAST_HORIZONS

# The JSON inputs, declared; occtrain.data.validate names the key of the first mismatch.
Waypoints = Annotated[list[Vec2], Len(FUTURE_STEPS)]  # [x, y] per 0.5 s step, ego frame
AgentBox = Annotated[list[float], Len(5)]  # x, y, length, width, yaw


class PlanningTruth(TypedDict):
    traj: Waypoints
    mask: NotRequired[Annotated[list[Literal[0, 1, True, False]], Len(FUTURE_STEPS)]]  # default: all valid
    agents: NotRequired[Annotated[list[list[AgentBox]], Len(FUTURE_STEPS)]]  # per step, for the collision rate


PlanningPredictions = dict[str, Waypoints]
CaptionPredictions = dict[str, str]
CaptionReferences = dict[str, str | list[str]]
#: Strings only, as NuScenes-QA's answers are: the integer 1 is not the answer "1".
QAPredictions = list[str]


#: Every output names how it was computed (occupancy and forecasts carry occ3d/occworld).
PLANNING_CONVENTION = (
    "L2_stp3/collision_stp3: ST-P3 (mean over the steps up to each horizon); "
    "L2_uniad/collision_uniad: UniAD (at the horizon's step)"
)
CAPTION_CONVENTION = "coco-caption (pycocoevalcap on PTB-tokenized text, scores as fractions, not percent)"
QA_CONVENTION = "nuscenes-qa (exact match of the answer string, by template type and hop)"


# ----------------------------------------------------------------------------- output


#: Metric results (tensors, NaN for an undefined metric) as standard JSON values.
to_json = finite_or_null


def emit(result: dict[str, Any], out: str | None) -> None:
    """Print the result as one standard JSON object; first write it to ``out`` atomically."""
    obj = to_json(result)
    text = json.dumps(obj, indent=2, allow_nan=False)
    if out:
        atomic_write_json(out, obj)
    print(text)


# ----------------------------------------------------------------------------- reading


def read_json(path: str | Path, what: str) -> Any:
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: {what} not found")
    try:
        return parse_json(path.read_text())  # NaN/Infinity parse here; the declared types refuse them by key
    except ValueError as err:
        raise DataError(f"{path}: {what} is not valid JSON ({err})") from None
    except OSError as err:
        raise DataError(f"{path}: cannot read the {what} ({err.strerror})") from None


def check_json(data: Any, schema: Any, path: Path, hint: str) -> None:
    """Raise the first way ``data`` (read from ``path``) differs from ``schema`` as one DataError line."""
    problem = first_problem(data, schema)
    if problem:
        raise DataError(f"{path}: {problem}; {hint}")


def _has_annotations(gt: Path) -> bool:
    return (gt / ANNOTATIONS_FILE).is_file() or (gt.name == GTS_DIR and (gt.parent / ANNOTATIONS_FILE).is_file())


def gt_samples(gt: Path, split: str | None) -> list[tuple[str, str, Path]]:
    """(scene, token, labels path) of a dataset root, or of a plain ``<scene>/<token>/labels.npz`` tree."""
    if not gt.is_dir():
        raise DataError(f"{gt}: ground-truth directory not found")
    if _has_annotations(gt):
        index = DatasetIndex.open(gt)
        if split and split not in index.splits:
            raise DataError(f"{gt}: no split '{split}'")
        found = [(s, t, index.labels_path(s, t)) for s, t in index.samples(split)]
    else:
        if split:
            raise DataError(f"{gt}: --split needs a dataset root with {ANNOTATIONS_FILE}; this is a plain labels tree")
        found = [(p.parent.parent.name, p.parent.name, p) for p in sorted(gt.glob(f"*/*/{LABELS_FILE}"))]
    if not found:
        raise DataError(f"{gt}: no samples found (expected <scene>/<token>/{LABELS_FILE} or a dataset root)")
    return found


def _missing_error(kind: str, missing: list[str], where: Path | str) -> DataError:
    more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
    return DataError(f"{where}: no {kind} for sample {missing[0]}{more}; predict every sample or pass --allow-missing")


# ----------------------------------------------------------------------------- occupancy


def score_occupancy(
    pred_dir: Path,
    gt: Path,
    convention: str = "occ3d",
    use_mask: bool = True,
    split: str | None = None,
    allow_missing: bool = False,
) -> dict[str, Any]:
    """Score ``<pred_dir>/<scene>/<token>/labels.npz`` against the ground truth's labels."""
    import torch

    from occtrain.metrics import OccupancyMetric

    if not pred_dir.is_dir():
        raise DataError(f"{pred_dir}: prediction directory not found")
    samples = gt_samples(gt, split)
    present = [(s, t, p) for s, t, p in samples if (pred_dir / s / t / LABELS_FILE).is_file()]
    missing = [f"{s}/{t}" for s, t, _ in samples if not (pred_dir / s / t / LABELS_FILE).is_file()]
    if missing and not allow_missing:
        raise _missing_error(f"{LABELS_FILE} prediction", missing, pred_dir)
    if not present:
        raise DataError(f"{pred_dir}: holds no prediction for any ground-truth sample of {gt}")
    masked = use_mask and convention == "occ3d"
    metric = OccupancyMetric(convention=convention, use_mask=masked)
    for scene, token, gt_path in present:
        truth = load_labels(gt_path, require_masks=masked)
        pred = load_labels(pred_dir / scene / token / LABELS_FILE, require_masks=False)["semantics"]
        mask = torch.from_numpy(truth["mask_camera"])[None] if masked else None
        metric.update(torch.from_numpy(pred)[None], torch.from_numpy(truth["semantics"])[None], mask)
    result = metric.compute()
    result["mask"] = "mask_camera" if masked else "none"
    return result


# ----------------------------------------------------------------------------- forecasting


def _forecast_form(key: str, shape: tuple[int, ...], dtype: np.dtype) -> str | None:
    """A forecast's shape, from its ``.npy`` header too (see ``read_npz``)."""
    if len(shape) != 4 or shape[1:] != GRID_SHAPE:
        return f"'{key}' has shape {shape}, expected (T, {', '.join(map(str, GRID_SHAPE))})"
    return None


def load_forecast(path: Path) -> np.ndarray:
    """A forecast's ``semantics`` (T, 200, 200, 16), validated."""
    arrays = read_npz(path, _forecast_form, ("semantics",))  # its shape checked from the header
    sem = arrays.get("semantics")
    if sem is None:
        raise DataError(f"{path}: missing array 'semantics'")
    if sem.shape[0] <= max(FORECAST_HORIZONS):
        raise DataError(
            f"{path}: holds {sem.shape[0]} future frames; the 1 s/2 s/3 s horizons need {max(FORECAST_HORIZONS) + 1}"
        )
    if sem.dtype.kind not in "ui":  # floats (NaN, 3.7) and bools are not class labels: never cast them
        raise DataError(f"{path}: 'semantics' has dtype {sem.dtype}; save class indices 0..{NUM_CLASSES - 1} as uint8")
    low, high = int(sem.min()), int(sem.max())
    if low < 0 or high >= NUM_CLASSES:
        raise DataError(
            f"{path}: 'semantics' holds class {low if low < 0 else high}; Occ3D classes are 0..{NUM_CLASSES - 1}"
        )
    return sem.astype(np.uint8, copy=False)  # lossless: every value is 0..17


def score_forecast(pred_dir: Path, gt: Path) -> dict[str, Any]:
    """Score every ``<pred_dir>/<scene>/<token>/forecast.npz`` against the scene's following frames.

    Future frames past the end of a scene are not counted; ``frames`` reports how many were.
    """
    import torch

    from occtrain.metrics import ForecastMetric

    if not pred_dir.is_dir():
        raise DataError(f"{pred_dir}: prediction directory not found")
    if not _has_annotations(gt):
        raise DataError(
            f"{gt}: forecasting needs a dataset root with {ANNOTATIONS_FILE} (it gives the scenes' frame order)"
        )
    index = DatasetIndex.open(gt)
    files = sorted(pred_dir.glob(f"*/*/{FORECAST_FILE}"))
    if not files:
        raise DataError(f"{pred_dir}: no <scene>/<token>/{FORECAST_FILE} files found")
    placed = []
    for path in files:
        scene, token = path.parent.parent.name, path.parent.name
        order = index.scenes.get(scene)
        if order is None or token not in order:
            raise DataError(f"{path}: sample {scene}/{token} is not in the ground truth {gt}")
        placed.append((scene, order.index(token), path))
    placed.sort()

    @lru_cache(maxsize=2 * FUTURE_STEPS)
    def frame(scene: str, position: int) -> np.ndarray:
        return index.labels(scene, index.scenes[scene][position])["semantics"]

    metric = ForecastMetric(horizons=FORECAST_HORIZONS)
    for scene, position, path in placed:
        pred = load_forecast(path)
        steps = pred.shape[0]
        target = np.zeros_like(pred)
        valid = np.zeros(steps, dtype=bool)
        for k in range(steps):
            if position + 1 + k < len(index.scenes[scene]):
                target[k] = frame(scene, position + 1 + k)
                valid[k] = True
        metric.update(torch.from_numpy(pred)[None], torch.from_numpy(target)[None], torch.from_numpy(valid)[None])
    result = metric.compute()
    result["samples"] = len(placed)
    return result


# ----------------------------------------------------------------------------- planning


def score_planning(pred_file: Path, gt_file: Path, allow_missing: bool = False) -> dict[str, Any]:
    """Score ``{token: [[x, y] x 6]}`` against ``{token: {"traj", "mask", "agents"?}}``."""
    import torch

    from occtrain.metrics import PlanningMetric

    preds = read_json(pred_file, "planning predictions")
    gts = read_json(gt_file, "planning ground truth")
    for obj, path in ((preds, pred_file), (gts, gt_file)):
        if not isinstance(obj, dict) or not obj:
            raise DataError(f"{path}: expected a non-empty JSON object keyed by sample token")
    check_json(preds, PlanningPredictions, pred_file, f"each sample needs {FUTURE_STEPS} waypoints [[x, y], ...]")
    check_json(
        gts,
        dict[str, PlanningTruth],
        gt_file,
        'each sample needs {"traj": [[x, y] x 6], "mask": [0/1 x 6], "agents": [[[x, y, length, width, yaw], ...] x '
        "6]}",
    )
    extra = [t for t in preds if t not in gts]
    if extra:
        raise DataError(f"{pred_file}: sample {extra[0]} is not in the ground truth {gt_file}")
    missing = [t for t in gts if t not in preds]
    if missing and not allow_missing:
        raise _missing_error("planned trajectory", missing, pred_file)
    metric = PlanningMetric()
    with_agents: dict[bool, list] = {True: [], False: []}
    for token, entry in gts.items():
        if token not in preds:
            continue
        mask = np.asarray(entry.get("mask", [1] * FUTURE_STEPS), dtype=bool)  # 0/1 or true/false: checked above
        row = (np.asarray(preds[token], dtype=np.float64), np.asarray(entry["traj"], dtype=np.float64), mask)
        agents = (
            [np.asarray(boxes, dtype=np.float64).reshape(-1, 5) for boxes in entry["agents"]]
            if "agents" in entry
            else None
        )
        with_agents[agents is not None].append((row, agents))
    for has_agents, rows in with_agents.items():
        if rows:
            pred, gt, valid = (torch.from_numpy(np.stack(col)) for col in zip(*(r for r, _ in rows)))
            metric.update(pred, gt, valid, [a for _, a in rows] if has_agents else None)
    return {"convention": PLANNING_CONVENTION, **metric.compute()}


# ----------------------------------------------------------------------------- text


def score_captions(pred_file: Path, ref_file: Path, allow_missing: bool = False) -> dict[str, Any]:
    """Score ``{id: "caption"}`` against ``{id: ["reference", ...]}`` with pycocoevalcap."""
    from occtrain.metrics import coco_caption_scores

    preds = read_json(pred_file, "caption predictions")
    refs = read_json(ref_file, "caption references")
    check_json(preds, CaptionPredictions, pred_file, 'expected a JSON object {id: "caption"}')
    if not isinstance(refs, dict) or not refs:
        raise DataError(f'{ref_file}: expected a non-empty JSON object {{id: ["reference", ...]}}')
    check_json(refs, CaptionReferences, ref_file, 'expected a JSON object {id: ["reference", ...]}')
    refs = {k: [v] if isinstance(v, str) else v for k, v in refs.items()}
    for k, v in refs.items():
        if not v:
            raise DataError(f"{ref_file}: id {k} needs a non-empty list of reference strings")
    extra = [k for k in preds if k not in refs]
    if extra:
        raise DataError(f"{pred_file}: id {extra[0]} has no references in {ref_file}")
    missing = [k for k in refs if k not in preds]
    if missing and not allow_missing:
        raise _missing_error("caption", missing, pred_file)
    scored = {k: v for k, v in refs.items() if k in preds}
    if not scored:
        raise DataError(f"{pred_file}: no caption for any id of {ref_file}")
    result: dict[str, Any] = {
        "convention": CAPTION_CONVENTION,
        **coco_caption_scores({k: preds[k] for k in scored}, scored),
    }
    result["samples"] = len(scored)
    return result


def score_qa(pred_file: Path, questions_file: Path) -> dict[str, Any]:
    """Score a JSON list of answers against a NuScenes-QA question file, in order."""
    from occtrain.metrics import QAMetric

    preds = read_json(pred_file, "QA predictions")
    data = read_json(questions_file, "NuScenes-QA questions")
    check_json(data, QAFile, questions_file, 'expected {"questions": [...]} in NuScenes-QA format')
    questions = data["questions"]
    if not isinstance(preds, list):
        raise DataError(f"{pred_file}: expected a JSON list of answer strings, in the order of {questions_file}")
    check_json(
        preds, QAPredictions, pred_file, f"expected a JSON list of answer strings, in the order of {questions_file}"
    )
    if len(preds) != len(questions):
        raise DataError(f"{pred_file}: holds {len(preds)} answers but {questions_file} asks {len(questions)} questions")
    metric = QAMetric()
    metric.update(
        list(preds),
        [q["answer"] for q in questions],
        [q["template_type"] for q in questions],
        [q["num_hop"] for q in questions],
    )
    return {"convention": QA_CONVENTION, **metric.compute()}
