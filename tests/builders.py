"""Small files the tests write by hand and more than one test module reads."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path


def straight(dy: float = 0.0) -> list[list[float]]:
    return [[2.5 * (k + 1), dy] for k in range(6)]


def planning_files(tmp_path: Path) -> tuple[Path, Path]:
    far = [40.0, 40.0, 4.0, 2.0, 0.0]
    agents = [[far], [[5.0, 3.0, 2.0, 1.0, 0.0]], [far], [[10.0, 0.0, 2.0, 8.0, 0.0]], [far], []]
    preds = {"tok-a": straight(3.0), "tok-b": straight(1.0)}
    gts = {
        "tok-a": {"traj": straight(), "mask": [1] * 6, "agents": agents},
        "tok-b": {"traj": straight(), "mask": [1, 1, 1, 1, 1, 0]},
    }
    (tmp_path / "p.json").write_text(json.dumps(preds))
    (tmp_path / "g.json").write_text(json.dumps(gts))
    return tmp_path / "p.json", tmp_path / "g.json"


def qa_questions(path: Path) -> Path:
    qs = [
        {
            "question": "Are there any cars?",
            "answer": "yes",
            "sample_token": "t0",
            "template_type": "exist",
            "num_hop": 0,
        },
        {"question": "How many trucks?", "answer": "2", "sample_token": "t0", "template_type": "count", "num_hop": 0},
        {
            "question": "How many moving cars?",
            "answer": "1",
            "sample_token": "t1",
            "template_type": "count",
            "num_hop": 1,
        },
        {
            "question": "What is the parked thing?",
            "answer": "car",
            "sample_token": "t1",
            "template_type": "object",
            "num_hop": 1,
        },
    ]
    path.write_text(json.dumps({"info": {}, "questions": qs}))
    return path


def write_omnidrive(root, tokens: dict[str, str]) -> None:
    """A small OmniDrive-nuScenes tree in the released layout, for ``tokens`` (token -> split)."""
    for i, (token, split) in enumerate(tokens.items()):
        for folder, data in (
            ("desc", {"description": f"A quiet street number {i} with parked cars."}),
            ("conv", [{"question": "Is the road clear?", "answer": f"Yes, clear {i}."}]),
            ("vqa", [{"question": "What is ahead?", "answer": "A parked car."}]),
            ("keywords", "Keep going straight."),
        ):
            path = root / folder / split / f"{token}.json"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(data))


def snapshot(root: Path) -> dict[str, str]:
    """sha256 of every file under ``root`` (directories as "dir"), by relative path."""
    return {
        str(p.relative_to(root)): "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
    }


def read_only_disk(mp) -> None:
    """Every new file refused as on a read-only file system, through ``mp`` (a
    ``pytest.MonkeyPatch``): tests run as root, where chmod would not stop them. Atomic
    writes and ``check_output``'s probe both start with ``tempfile.mkstemp``."""
    import errno
    import tempfile

    def refuse(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    mp.setattr(tempfile, "mkstemp", refuse)
