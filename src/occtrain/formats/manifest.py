"""``manifest.json``: the story of a run, one entry per stage, rewritten atomically."""

from __future__ import annotations

import os
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from occtrain.errors import OcctrainError
from occtrain.formats.io import atomic_write_json, parse_json, remove_inside, write_error
from occtrain.version import code_version

#: What a run's or a stage's name may be. Each becomes one directory (``<runs_root>/<run>``,
#: ``<run>/<stage>``) that the runner writes into and ``--restart`` deletes, so it is a
#: single plain path component: no separator, no ``..``, not hidden, never absolute.
NAME_PATTERN = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+-]{0,127}")
NAME_RULE = "letters, digits and _ . + - (first a letter, digit or _), at most 128 characters"

MANIFEST_FILE = "manifest.json"
#: The recipe the run's stages were trained with (resolved, with its overrides).
PIPELINE_FILE = "pipeline.yaml"
#: Where ``--restart`` keeps the stages it replaces until the new attempt has a checkpoint.
ASIDE_DIR = ".replaced"
ASIDE_ENTRIES = "entries.json"
#: A failed restart's traceback, kept when its stage directory gives way to the old one.
RESTART_TRACEBACK = "restart-traceback.txt"
STATUSES = ("pending", "running", "done", "failed", "interrupted")
#: A stage in one of these states has a checkpoint to resume from (or none yet).
RESUMABLE = ("running", "failed", "interrupted")


@dataclass
class StageEntry:
    """A stage's record in the manifest."""

    kind: str
    status: str = "pending"
    attempts: int = 0
    config_hash: str = ""
    started: float | None = None
    ended: float | None = None
    wall_time_s: float = 0.0
    metrics: dict[str, Any] = field(default_factory=dict)
    artifacts: dict[str, str] = field(default_factory=dict)
    error: str = ""
    code_version: str = ""
    #: The resolved stage config the hash was taken of, to explain a change key by key.
    config: dict[str, Any] = field(default_factory=dict)
    #: One record per attempt of what it actually did, as the trainer saw it: the optimizer
    #: step training began at (a resume begins at its checkpoint's step), the number of
    #: processes, and the samples each rank trained and validated on.
    history: list[dict[str, Any]] = field(default_factory=list)


@dataclass
class Manifest:
    """All stages of a run, in recipe order."""

    path: Path
    name: str = ""
    stages: dict[str, StageEntry] = field(default_factory=dict)
    #: False in DDP worker processes: only rank zero writes.
    writable: bool = True
    #: Wall time of the running stage's earlier attempts.
    _attempt_base: float = 0.0

    @classmethod
    def load(cls, run_dir: Path, writable: bool = True) -> Manifest:
        path = Path(run_dir) / MANIFEST_FILE
        if not path.is_file():
            return cls(path=path, writable=writable)
        try:
            raw = parse_json(path.read_text())
            stages = {name: StageEntry(**entry) for name, entry in raw["stages"].items()}
        except (ValueError, KeyError, TypeError, AttributeError) as err:
            raise OcctrainError(f"{path}: unreadable manifest ({err}); move it aside to start the run afresh") from None
        for name in stages:  # each names a directory the runner writes and --restart replaces
            if not NAME_PATTERN.fullmatch(name):
                raise OcctrainError(
                    f"{path}: stage '{name}' is not a folder name inside the run; move the manifest aside to start the "
                    "run afresh"
                )
        return cls(path=path, name=raw.get("name", ""), stages=stages, writable=writable)

    def save(self) -> None:
        if not self.writable:
            return
        atomic_write_json(
            self.path,
            {"name": self.name, "updated": time.time(), "stages": {n: asdict(e) for n, e in self.stages.items()}},
        )

    def entry(self, name: str, kind: str) -> StageEntry:
        if name not in self.stages:
            self.stages[name] = StageEntry(kind=kind)
        return self.stages[name]

    def mark_running(self, name: str, config_hash: str, config: dict) -> StageEntry:
        e = self.stages[name]
        e.status, e.attempts, e.started, e.ended, e.error = "running", e.attempts + 1, time.time(), None, ""
        e.config_hash, e.config, e.code_version = config_hash, config, code_version()
        e.history.append({"attempt": e.attempts})
        self._attempt_base = e.wall_time_s
        self.save()
        return e

    def record_attempt(self, name: str, facts: dict[str, Any]) -> None:
        """Add what the running attempt reports about itself (see ``StageEntry.history``)."""
        self.stages[name].history[-1].update(facts)
        self.save()

    def record_time(self, name: str, attempt_s: float) -> None:
        """This attempt has run ``attempt_s`` seconds so far: ``wall_time_s`` is the sum over
        attempts, a kill -9 loses at most the time since the last record."""
        e = self.stages[name]
        e.wall_time_s = self._attempt_base + attempt_s
        self.save()

    def mark_done(self, name: str, metrics: dict, artifacts: dict[str, str], attempt_s: float) -> None:
        e = self.stages[name]
        e.status, e.ended, e.metrics, e.artifacts = "done", time.time(), metrics, artifacts
        self.record_time(name, attempt_s)

    def mark_failed(self, name: str, error: str, attempt_s: float, status: str = "failed") -> None:
        e = self.stages[name]
        e.status, e.ended, e.error = status, time.time(), error
        self.record_time(name, attempt_s)

    def reset(self, name: str) -> None:
        kind = self.stages[name].kind
        self.stages[name] = StageEntry(kind=kind)
        self.save()

    # -- --restart replaces stages without losing them: they move to RUN/.replaced/ with their
    # entries and the run's pipeline.yaml (the recipe they were trained with); once a
    # retrained stage has a checkpoint or an export (or the command succeeded) they are stale
    # and go, and if the attempt fails or is killed before that they come back as they were.

    def set_aside(self, names: list[str]) -> None:
        """Move the stages ``--restart`` retrains to ``RUN/.replaced/`` and reset their entries;
        ``pipeline.yaml`` goes with them (the caller writes the restart's own after this).

        Their entries are written there first, so a kill at any point leaves what
        :meth:`settle_aside` needs to put them back: renames within one directory are atomic.
        """
        run_dir = self.path.parent
        aside = run_dir / ASIDE_DIR
        entries = {name: asdict(self.stages[name]) for name in names if name in self.stages}
        try:
            aside.mkdir(parents=True)
            atomic_write_json(aside / ASIDE_ENTRIES, entries)
            for name in names:
                if (run_dir / name).exists():
                    os.rename(run_dir / name, aside / name)
            if (run_dir / PIPELINE_FILE).is_file():
                os.rename(run_dir / PIPELINE_FILE, aside / PIPELINE_FILE)
        except OSError as err:
            raise write_error(aside, err) from None
        for name in names:
            if name in self.stages:
                self.stages[name] = StageEntry(kind=self.stages[name].kind)
        self.save()

    def set_aside_by_a_restart(self) -> list[str]:
        """The stages a ``--restart`` set aside and has not settled (none: []): while it runs,
        or after it was killed, until the next run settles them. Reads, writes nothing."""
        try:
            raw = parse_json((self.path.parent / ASIDE_DIR / ASIDE_ENTRIES).read_text())
        except (OSError, ValueError):
            return []
        return [name for name in raw if NAME_PATTERN.fullmatch(name)] if isinstance(raw, dict) else []

    def after_a_killed_restart(self) -> dict[str, str]:
        """What the next run makes of the stages a ``--restart`` set aside and was killed with
        (call it when nobody holds the run: ``run.control.lock_holder``): each stage's status
        as it will be, said so (``settle_aside`` does it)."""
        run_dir = self.path.parent
        aside = self.set_aside_by_a_restart()
        if any(_progressed(run_dir / name) for name in aside):
            return {name: "interrupted: a killed --restart; the next run resumes it" for name in aside}
        return {name: "done: a killed --restart set it aside; the next run puts it back" for name in aside}

    def settle_aside(self, succeeded: bool = False) -> str:
        """End a restart's set-aside: discard the old stages once the command succeeded or a
        retrained stage has a checkpoint, else put them back (directories and entries) as
        they were. Returns a line for the user ("" when nothing was put back)."""
        run_dir = self.path.parent
        aside = run_dir / ASIDE_DIR
        if not aside.is_dir():
            return ""
        try:
            raw = parse_json((aside / ASIDE_ENTRIES).read_text())
            restored = {name: StageEntry(**entry) for name, entry in raw.items() if NAME_PATTERN.fullmatch(name)}
        except (OSError, ValueError, TypeError, AttributeError):
            restored = None  # killed before the entries were written: nothing was moved yet
        if restored is None or succeeded or any(_progressed(run_dir / name) for name in restored):
            remove_inside(aside, run_dir)
            return ""
        kept = ""
        for name in sorted(p.name for p in aside.iterdir() if p.is_dir()):
            failed = run_dir / name / "logs" / "traceback.txt"
            if failed.is_file():  # why the attempt failed outlives the attempt's directory
                kept = f"; the failure's traceback is in {run_dir / RESTART_TRACEBACK}"
                os.replace(failed, run_dir / RESTART_TRACEBACK)
            remove_inside(run_dir / name, run_dir)  # the failed attempt's logs; it has no checkpoint
            os.rename(aside / name, run_dir / name)
        if (aside / PIPELINE_FILE).is_file():  # the recipe of the stages put back, not the failed attempt's
            os.replace(aside / PIPELINE_FILE, run_dir / PIPELINE_FILE)
        self.stages.update(restored)
        self.save()
        remove_inside(aside, run_dir)
        return (
            f"the stages --restart replaced ({', '.join(restored)}) are back as they were: "
            f"the retrained ones stopped before their first checkpoint{kept}"
        )


def _progressed(stage_dir: Path) -> bool:
    """Whether a retrained stage has something worth more than what it replaced."""
    return (stage_dir / "export").is_dir() or any((stage_dir / "checkpoints").glob("*.ckpt"))
