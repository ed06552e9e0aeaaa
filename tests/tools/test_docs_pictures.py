"""tools/docs_pictures.py: the docs' pictures drawn from a finished run, each with alt text
and a caption stamped with the run (recipe, seed, code, world), never its path."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from conftest import load_tool
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
    facts = tool.RunFacts(tmp_path, "r", {"tok": "tokenizer", "pre": "pretrain"}, tmp_path, "recipe r")
    with pytest.raises(tool.Skipped, match="no done planner or dagger stage"):
        facts.stage("planner", "dagger")
    assert facts.stage("tokenizer") == "tok"


def test_unknown_pictures_are_refused(tool, capsys):
    with pytest.raises(SystemExit):
        tool.main(["run", "--out", "x", "--only", "world,movie"])
    assert "--only movie: the pictures are world" in capsys.readouterr().err
