"""The language releases joined to a dataset's frames by sample token, each read in its own
layout and key names (``occtrain data import omnidrive|drivelm|nuscenes-qa SRC --into DIR``).

- **OmniDrive-nuScenes** (SRC: its root): ``{desc,conv,vqa,keywords}/<split>/<token>.json``,
  with ``{"description": ...}``, lists of ``{"question", "answer"}`` and the action string.
  Placed in ``DIR/omnidrive/`` in the same layout, the files as they are (hard links; a
  family's ``tasks.omnidrive`` setting reads it: descriptions, conversations), and each
  description becomes its frame's ``caption`` in the sidecar (what every caption task reads).
- **DriveLM-nuScenes** (SRC: a ``v1_1_<split>_nus.json``-style file): scene token ->
  ``{"key_frames": {sample token: {"QA": {"perception", "prediction", "planning", "behavior"}}}}``,
  each QA item ``{"Q", "A", ...}``. Written, items as they are, to
  ``DIR/drivelm/DriveLM_<split>_qa.json`` (``{"info", "frames": {token: {category: [items]}}}``,
  the split the dataset's): no occtrain task reads it yet (docs/real-data.md).
- **NuScenes-QA** (SRC: ``NuScenes_<split>_questions.json`` or the folder holding both):
  ``{"questions": [...]}``, each question as :class:`~occtrain.data.schema.QAQuestion`.
  Written to ``DIR/nuscenes_qa/NuScenes_<split>_questions.json``, where every QA task reads.

Each import counts the release's items: *matched* (its sample token is a frame of the
dataset: written), *unmatched* (not a frame of the dataset) and *skipped* (a frame of the
dataset, not written, for the reason the report gives: an empty item, or a NuScenes-QA or
OmniDrive item whose release split is not the dataset's split of its sample, which would
mix training and evaluation). One summary line says them; ``DIR/occtrain/imports/<release>.json``
(``<release>-<file>.json`` for a file) holds them with the reasons. Everything is read and
checked before anything is written.
"""

from __future__ import annotations

import re
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, TypedDict

from occtrain.data.layout import DATASET_FILE, FRAMES_DIR, QA_DIR, SPLITS, DatasetIndex, qa_file
from occtrain.data.releases.files import place
from occtrain.data.releases.nuscenes_tables import read_json
from occtrain.data.schema import FrameAnnotation, QAQuestion
from occtrain.data.validate import first_problem
from occtrain.errors import DataError
from occtrain.formats.io import atomic_write_json

OMNIDRIVE_FOLDERS = ("desc", "conv", "vqa", "keywords")
OMNIDRIVE_DIR = "omnidrive"
DRIVELM_DIR = "drivelm"
DRIVELM_CATEGORIES = ("perception", "prediction", "planning", "behavior")
#: DriveLM's question about the ego's own behavior (its behavior category).
DRIVELM_BEHAVIOR_QUESTION = "Predict the behavior of the ego vehicle."
IMPORTS_DIR = "occtrain/imports"
QA_NAME = re.compile(r"^NuScenes_(?P<split>\w+?)_questions\.json$")
QA_KEYS = ("question", "answer", "sample_token", "template_type", "num_hop")


class _Pair(TypedDict):
    """An OmniDrive conversation or VQA pair."""

    question: str
    answer: str


def omnidrive_file(root: Path, folder: str, split: str, token: str) -> Path:
    """Where OmniDrive-nuScenes keeps one annotation of a sample."""
    return root / folder / split / f"{token}.json"


def drivelm_file(split: str) -> str:
    """The name DriveLM-nuScenes gives a split's file (v1.1)."""
    return f"v1_1_{split}_nus.json"


def drivelm_output(split: str) -> str:
    """Where an import writes a split's DriveLM QA, relative to the dataset root."""
    return f"{DRIVELM_DIR}/DriveLM_{split}_qa.json"


@dataclass
class ImportReport:
    """What one text import did (written as JSON beside the dataset's sidecars)."""

    release: str
    source: str
    matched: int = 0
    unmatched: int = 0
    skipped: int = 0
    skipped_why: dict[str, int] = field(default_factory=dict)
    written: list[str] = field(default_factory=list)
    #: The first sample tokens the dataset does not hold (up to 5), to tell a wrong release.
    unmatched_examples: list[str] = field(default_factory=list)

    def unmatched_item(self, token: str) -> None:
        self.unmatched += 1
        if len(self.unmatched_examples) < 5:
            self.unmatched_examples.append(token)

    def skip(self, why: str) -> None:
        self.skipped += 1
        self.skipped_why[why] = self.skipped_why.get(why, 0) + 1

    def line(self) -> str:
        return (
            f"{self.release}: {self.matched} matched, {self.unmatched} unmatched, {self.skipped} skipped "
            f"(report: {self.written[-1] if self.written else '-'})"
        )


class _Frames:
    """The dataset's samples: split and scene by sample token."""

    def __init__(self, into: str | Path):
        self.index = DatasetIndex.open(into)
        self.root = self.index.root
        self.split_of: dict[str, str] = {}
        self.scene_of: dict[str, str] = {}
        for split in SPLITS:
            for scene, token in self.index.samples(split):
                self.split_of[token], self.scene_of[token] = split, scene


def report_path(root: Path, release: str, src: Path) -> Path:
    """Where an import's report lies: one per release, or per file for releases shipped as
    several files (DriveLM's and NuScenes-QA's splits)."""
    name = release if src.is_dir() else f"{release}-{src.stem}"
    return root / IMPORTS_DIR / f"{name}.json"


def _finish(report: ImportReport, root: Path) -> ImportReport:
    path = report_path(root, report.release, Path(report.source))
    report.written.append(str(path))
    atomic_write_json(path, asdict(report))
    return report


# ----------------------------------------------------------------------------- OmniDrive


def _omnidrive_item(path: Path, folder: str) -> Any:
    """One OmniDrive file, checked for its folder's shape (one line naming the file and key)."""
    data = read_json(path, "OmniDrive annotation", "restore the file from the OmniDrive-nuScenes release")
    if folder == "desc":
        problem = first_problem(data, dict[str, Any]) or (
            None if isinstance(data.get("description"), str) else "description is missing or not a string"
        )
    elif folder == "keywords":
        problem = None if isinstance(data, str) else "the file holds no string (the driving action)"
    else:
        problem = first_problem(data, list[_Pair])
    if problem:
        raise DataError(f"{path}: {problem}; OmniDrive-nuScenes' {folder}/ files hold {_OMNIDRIVE_SHAPE[folder]}")
    return data


_OMNIDRIVE_SHAPE = {
    "desc": '{"description": "..."}',
    "conv": 'a list of {"question", "answer"}',
    "vqa": 'a list of {"question", "answer"}',
    "keywords": "a JSON string",
}


def _empty(folder: str, data: Any) -> bool:
    return (folder == "desc" and not data["description"].strip()) or (folder != "desc" and not data)


def import_omnidrive(src: str | Path, into: str | Path) -> ImportReport:
    """Join an OmniDrive-nuScenes root to the dataset ``into`` (see the module docstring)."""
    src = Path(src)
    if not src.is_dir() or not any((src / f).is_dir() for f in OMNIDRIVE_FOLDERS):
        raise DataError(
            f"{src}: not an OmniDrive-nuScenes root (it holds none of {', '.join(f + '/' for f in OMNIDRIVE_FOLDERS)})"
        )
    ds = _Frames(into)
    report = ImportReport("omnidrive", str(src))
    keep: list[tuple[str, str, str, Any, Path]] = []  # folder, split, token, data, file
    for folder in OMNIDRIVE_FOLDERS:
        for path in sorted((src / folder).glob("*/*.json")):
            token, split = path.stem, path.parent.name
            data = _omnidrive_item(path, folder)
            if token not in ds.split_of:
                report.unmatched_item(token)
            elif ds.split_of[token] != split:
                report.skip(f"{folder}: release split is not the dataset's")
            elif _empty(folder, data):
                report.skip(f"{folder}: empty")
            else:
                report.matched += 1
                keep.append((folder, split, token, data, path))
    # Write: the layout under a staging folder swapped in whole, then each scene's captions.
    target = ds.root / OMNIDRIVE_DIR
    staging = ds.root / f".{OMNIDRIVE_DIR}.partial"
    if staging.exists():
        shutil.rmtree(staging)
    for folder, split, token, _, path in keep:  # the release's own bytes, hard-linked
        place(path, omnidrive_file(staging, folder, split, token))
    staging.mkdir(exist_ok=True)
    old = ds.root / f".{OMNIDRIVE_DIR}.old"
    if target.exists():
        target.rename(old)
    staging.rename(target)
    if old.exists():
        shutil.rmtree(old)
    captions = {token: data["description"] for folder, _, token, data, _ in keep if folder == "desc"}
    _set_frame_text(ds, "caption", captions)
    report.written.append(str(target))
    return _finish(report, ds.root)


def _set_frame_text(ds: _Frames, key: str, text: dict[str, str]) -> None:
    """Set ``key`` of the frames ``text`` names, scene by scene (each sidecar rewritten
    atomically), and mark the key present in the dataset record when any frame has it."""
    by_scene: dict[str, dict[str, str]] = {}
    for token, value in text.items():
        by_scene.setdefault(ds.scene_of[token], {})[token] = value
    for scene, values in sorted(by_scene.items()):
        frames: list[FrameAnnotation] = ds.index.frames(scene)
        for frame in frames:
            if frame["token"] in values:
                frame[key] = values[frame["token"]]  # type: ignore[literal-required]
        atomic_write_json(ds.root / FRAMES_DIR / f"{scene}.json", frames, indent=None)
    record = ds.index.generator
    if text and record and key in (record.get("absent") or {}):
        record = dict(record, absent={k: v for k, v in record["absent"].items() if k != key})
        atomic_write_json(ds.root / DATASET_FILE, record)


# ----------------------------------------------------------------------------- DriveLM


class _DriveLMItem(TypedDict):
    Q: str
    A: str


class _DriveLMFrame(TypedDict):
    QA: dict[str, list[_DriveLMItem]]


class _DriveLMScene(TypedDict):
    key_frames: dict[str, _DriveLMFrame]


def import_drivelm(src: str | Path, into: str | Path) -> ImportReport:
    """Join a DriveLM-nuScenes file to the dataset ``into`` (see the module docstring)."""
    src = Path(src)
    if src.is_dir():
        raise DataError(f"{src}: a folder; pass DriveLM's JSON file itself (e.g. {drivelm_file('train')})")
    data = read_json(src, "DriveLM file", "restore it from the DriveLM release")
    problem = first_problem(data, dict[str, _DriveLMScene])
    if problem:
        raise DataError(
            f"{src}: {problem}; DriveLM-nuScenes maps scene tokens to "
            '{"key_frames": {sample token: {"QA": {category: [{"Q", "A"}]}}}}'
        )
    for scene, content in data.items():
        for sample, frame in content["key_frames"].items():
            other = sorted(set(frame["QA"]) - set(DRIVELM_CATEGORIES))
            if other:
                raise DataError(
                    f"{src}: {scene}.key_frames.{sample}.QA.{other[0]} is not a DriveLM category "
                    f"({', '.join(DRIVELM_CATEGORIES)})"
                )
    ds = _Frames(into)
    report = ImportReport("drivelm", str(src))
    joined: dict[str, dict[str, dict]] = {s: {} for s in SPLITS}
    for content in data.values():
        for sample, frame in content["key_frames"].items():
            if sample not in ds.split_of:
                report.unmatched_item(sample)
            elif not any(frame["QA"].values()):
                report.skip("no QA")
            else:
                report.matched += 1
                joined[ds.split_of[sample]][sample] = {c: frame["QA"].get(c, []) for c in DRIVELM_CATEGORIES}
    for split, frames in joined.items():
        if not frames:
            continue
        path = ds.root / drivelm_output(split)
        existing = {}
        if path.is_file():
            existing = read_json(path, "DriveLM QA file", "delete it and import again").get("frames", {})
        merged = existing | frames
        atomic_write_json(
            path, {"info": {"release": "DriveLM-nuScenes", "split": split}, "frames": dict(sorted(merged.items()))}
        )
        report.written.append(str(path))
    return _finish(report, ds.root)


# ----------------------------------------------------------------------------- NuScenes-QA


def _qa_sources(src: Path) -> list[tuple[str, Path]]:
    """(split, file) of a NuScenes-QA file, or of each split's file in a folder."""
    if src.is_dir():
        found = [(m["split"], p) for p in sorted(src.iterdir()) if (m := QA_NAME.match(p.name))]
        if not found:
            raise DataError(f"{src}: holds no NuScenes_<split>_questions.json; point at NuScenes-QA's questions folder")
        return found
    m = QA_NAME.match(src.name)
    if m is None:
        raise DataError(
            f"{src}: NuScenes-QA names its files NuScenes_<split>_questions.json, which tells their split; "
            "keep the release's name"
        )
    return [(m["split"], src)]


class _QARelease(TypedDict):
    questions: list[QAQuestion]


def import_nuscenes_qa(src: str | Path, into: str | Path) -> ImportReport:
    """Join NuScenes-QA's questions to the dataset ``into`` (see the module docstring)."""
    src = Path(src)
    sources = _qa_sources(src)
    read = []
    for split, path in sources:
        data = read_json(path, "NuScenes-QA file", "restore it from the NuScenes-QA release")
        problem = first_problem(data, _QARelease)
        if problem:
            raise DataError(f'{path}: {problem}; NuScenes-QA\'s files are {{"questions": [...]}}')
        read.append((split, data["questions"]))
    ds = _Frames(into)
    report = ImportReport("nuscenes-qa", str(src))
    out: dict[str, list[dict]] = {}
    for split, questions in read:
        for q in questions:
            token = q["sample_token"]
            if token not in ds.split_of:
                report.unmatched_item(token)
            elif ds.split_of[token] != split:
                report.skip("release split is not the dataset's")
            else:
                report.matched += 1
                out.setdefault(split, []).append({k: q[k] for k in QA_KEYS})  # type: ignore[literal-required]
    for split, questions in out.items():
        path = ds.root / qa_file(split)
        atomic_write_json(path, {"info": {"release": "NuScenes-QA", "split": split}, "questions": questions})
        report.written.append(str(path))
    return _finish(report, ds.root)


__all__ = [
    "DRIVELM_BEHAVIOR_QUESTION",
    "ImportReport",
    "QA_DIR",
    "drivelm_file",
    "drivelm_output",
    "import_drivelm",
    "import_nuscenes_qa",
    "import_omnidrive",
    "omnidrive_file",
]
