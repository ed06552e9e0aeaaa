"""tools/docs_pictures.py: the docs' pictures drawn from a finished run, each with alt text
and a caption stamped with the run (recipe, seed, code, world), never its path; a mistake is
one line naming its file, and no picture is written."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from builders import read_only_disk, snapshot
from conftest import load_tool, write_hand_dataset
from occtrain.data.identity import world_identity
from quickstart_run import shared_quickstart_run


@pytest.fixture(scope="module")
def tool():
    return load_tool("docs_pictures")


@pytest.mark.slow
def test_pictures_of_the_tiny_run_are_drawn_with_their_stamped_captions(tool, tmp_path_factory, tmp_path, capsys):
    run = shared_quickstart_run(tmp_path_factory)
    out = tmp_path / "img"
    # Frame 4 of the tiny world's 13-frame val scene has the history and 3 s future a forecast reads.
    assert tool.main([str(run), "--out", str(out), "--only", "world,reconstruction,forecast", "--frame", "4"]) == 0
    index = json.loads((out / "pictures.json").read_text())["pictures"]
    assert set(index) == {"world", "reconstruction", "forecast"}
    code = json.loads((run / "manifest.json").read_text())["stages"]["tokenizer"]["code_version"]
    for name, entry in index.items():
        image = Image.open(out / entry["file"])
        assert image.width >= 400 and image.height >= 200, name
        assert len(entry["alt"]) > 30, name  # says what the picture shows
        caption = entry["caption"]
        assert "recipe quickstart, training seed 0" in caption and f"code {code}" in caption, name
        assert "world occtrain world v" in caption, name
        assert str(run) not in caption and str(tmp_path) not in caption, name  # never a path of this machine
    # The reconstruction sits beside the truth: two panels of the same width, both drawn.
    pixels = np.asarray(Image.open(out / "reconstruction.png").convert("RGB"))
    half = (pixels.shape[1] - 4) // 2
    left, right = pixels[16:400, :half], pixels[16:400, half + 4 : 2 * half + 4]
    assert len(np.unique(left.reshape(-1, 3), axis=0)) > 5 and len(np.unique(right.reshape(-1, 3), axis=0)) > 2
    # The tiny run forecasts two frames: the picture keeps the 1 s row it has and says so.
    assert "1 s ahead" in index["forecast"]["caption"] and "2, 3 s" not in index["forecast"]["caption"]

    # --only redraws one picture and keeps the others' entries.
    assert tool.main([str(run), "--out", str(out), "--only", "world", "--frame", "4"]) == 0
    assert set(json.loads((out / "pictures.json").read_text())["pictures"]) == set(index)
    assert "world:" in capsys.readouterr().out


def test_a_picture_the_run_cannot_give_is_skipped_and_said(tool, tmp_path):
    facts = tool.RunFacts(tmp_path, "r", {"tok": "tokenizer", "pre": "pretrain"}, tmp_path, "recipe r", "recipe r")
    with pytest.raises(tool.Skipped, match="no done planner or dagger stage"):
        facts.stage("planner", "dagger")
    assert facts.stage("tokenizer") == "tok"


def test_unknown_pictures_are_refused(tool, capsys):
    with pytest.raises(SystemExit):
        tool.main(["run", "--out", "x", "--only", "world,movie"])
    assert "--only movie: the pictures are world" in capsys.readouterr().err


@pytest.fixture(scope="module")
def worlds(tmp_path_factory) -> tuple[Path, Path]:
    """Two tiny worlds: the run's own, and another (one more val scene)."""
    root = tmp_path_factory.mktemp("worlds")
    return write_hand_dataset(root / "own", train=1, val=1, frames=6), write_hand_dataset(
        root / "other", train=1, val=2, frames=6
    )


def _run(tmp: Path, world: Path) -> Path:
    """A run directory as the pictures read it: a done tokenizer stage, trained on ``world``."""
    run = tmp / "run"
    run.mkdir()
    entry = {"kind": "tokenizer", "status": "done", "code_version": "0.1.0+abc1234", "config": {"trainer": {"seed": 0}}}
    (run / "manifest.json").write_text(json.dumps({"name": "quickstart", "stages": {"tokenizer": entry}}))
    (run / "pipeline.yaml").write_text(f"name: quickstart\ndata:\n  root: {world}\n")
    return run


def test_a_picture_of_another_world_names_it_and_not_as_the_runs(tool, worlds, tmp_path):
    own, other = (world_identity(w) for w in worlds)
    run = _run(tmp_path, worlds[0])

    def caption(*data: str) -> str:
        out = tmp_path / "img"
        assert tool.main([str(run), "--out", str(out), "--only", "world", "--frame", "2", *data]) == 0
        return json.loads((out / "pictures.json").read_text())["pictures"]["world"]["caption"]

    stamp = f"recipe quickstart, training seed 0, code 0.1.0+abc1234, world {own.name} [{own.key}]"
    assert caption().endswith(stamp)
    assert caption("--data", str(worlds[0])).endswith(stamp)  # its own world, named by --data
    drawn = f"drawn on world {other.name} [{other.key}] given with --data"
    assert caption("--data", str(worlds[1])).endswith(f"{stamp}; {drawn}, not the run's own")
    # A run whose world is not on this machine: the world drawn is named, never as the run's.
    (run / "pipeline.yaml").write_text(f"data:\n  root: {tmp_path / 'gone'}\n")
    unknown = caption("--data", str(worlds[1]))
    assert unknown.endswith(f"code 0.1.0+abc1234; {drawn} (the run's own world is not here to compare)")


@dataclass(frozen=True)
class Case:
    """One mistake: ``setup(tmp)`` breaks a copy of a run (tmp/run, trained on a tiny world)
    and its pictures (tmp/img); ``argv`` (``{tmp}`` filled in) replaces the arguments it names."""

    id: str
    says: str
    argv: dict[str, str]
    setup: Callable[[Path], None] = lambda tmp: None
    patch: Callable[[pytest.MonkeyPatch], None] | None = None


CASES = [
    Case("missing run dir", "{tmp}/nope: not a run directory (no manifest.json)", {"run": "{tmp}/nope"}),
    Case(
        "--out onto a file", "{tmp}/img/world.png: is a file; --out takes a directory", {"--out": "{tmp}/img/world.png"}
    ),
    Case("--out read-only", "cannot write {tmp}/img: the file system is read-only", {}, patch=read_only_disk),
    Case(
        "a run without pipeline.yaml",
        "{tmp}/run: no pipeline.yaml",
        {},
        setup=lambda tmp: (tmp / "run" / "pipeline.yaml").unlink(),
    ),
    Case(
        "a pipeline.yaml that is not YAML",
        "{tmp}/run/pipeline.yaml line 2: not valid YAML",
        {},
        setup=lambda tmp: (tmp / "run" / "pipeline.yaml").write_text("data: {root: [\n"),
    ),
    Case(
        "a pipeline.yaml without data.root",
        "{tmp}/run/pipeline.yaml: no data.root",
        {},
        setup=lambda tmp: (tmp / "run" / "pipeline.yaml").write_text("data: [1]\n"),
    ),
    Case(
        "a corrupt manifest",
        "{tmp}/run/manifest.json: not a run manifest (JSONDecodeError",
        {},
        setup=lambda tmp: (tmp / "run" / "manifest.json").write_text('{"stages": '),
    ),
    Case("--data not a dataset", "{tmp}/img: not a dataset (no annotations.json)", {"--data": "{tmp}/img"}),
    Case(
        "--drive-stage not a done stage",
        "--drive-stage zz: the run has no done stage of that name",
        {"--only": "drive", "--drive-stage": "zz"},
    ),
    Case(
        "a broken pictures index",
        "{tmp}/img/pictures.json: not a pictures index (pictures.world is the integer 3",
        {},
        setup=lambda tmp: (tmp / "img" / "pictures.json").write_text('{"pictures": {"world": 3}}'),
    ),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_a_mistake_is_one_line_naming_its_file_and_draws_nothing(case, tool, worlds, tmp_path, capsys, monkeypatch):
    _run(tmp_path, worlds[0])
    (tmp_path / "img").mkdir()
    (tmp_path / "img" / "world.png").write_bytes(b"drawn before")
    (tmp_path / "img" / "pictures.json").write_text(json.dumps({"pictures": {}}))
    case.setup(tmp_path)
    args = {"run": "{tmp}/run", "--out": "{tmp}/img", "--only": "world", "--frame": "2"} | case.argv
    argv = [args.pop("run")] + [part for flag_value in args.items() for part in flag_value]
    before = snapshot(tmp_path)
    if case.patch is not None:
        case.patch(monkeypatch)
    code = tool.main([a.format(tmp=tmp_path) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    assert code == 2, out + err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert case.says.format(tmp=tmp_path) in err, err
    assert out == ""
    assert snapshot(tmp_path) == before
