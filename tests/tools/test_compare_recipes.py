"""tools/compare_recipes.py: which recipes it runs, and what counts as the same stage on both sides."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from conftest import REPO, load_tool


@pytest.fixture(scope="module")
def tool():
    return load_tool("compare_recipes")


def _stage(root: Path, run: str, stage: str, metrics: dict | None, weight: torch.Tensor | None) -> None:
    (root / run).mkdir(parents=True, exist_ok=True)
    manifest = root / run / "manifest.json"
    stages = json.loads(manifest.read_text())["stages"] if manifest.is_file() else {}
    manifest.write_text(json.dumps({"stages": {**stages, stage: {}}}))
    (root / run / stage / "export").mkdir(parents=True)
    if metrics is not None:
        (root / run / stage / "metrics.json").write_text(json.dumps(metrics))
    if weight is not None:
        save_file({"w": weight}, str(root / run / stage / "export" / "model.safetensors"))


def test_every_shipped_recipe_but_the_plan_only_sizes(tool):
    names = tool.shipped_recipes(REPO)
    assert {"quickstart", "sparseoccvla", "proof/occllm", "ablations/occllm_msvae"} <= set(names)
    assert not [n for n in names if n.startswith("scale/")]
    assert len(names) == len([p for p in (REPO / "recipes").rglob("*.yaml") if "scale" not in p.parts])


def test_same_differs_and_missing(tool, tmp_path, capsys):
    before, after = tmp_path / "before", tmp_path / "after"
    for i, side in enumerate((before, after)):
        timings = {"train_step_s": 0.1 + i, "train_mfu": 0.02 + i, "train_tokens_per_s": 300.0 + i}
        _stage(side, "quickstart", "tokenizer", {"val/loss": 1.0, **timings}, torch.ones(3))
    _stage(before, "quickstart", "pretrain", {"val/loss": 2.0}, torch.zeros(2))
    _stage(after, "quickstart", "pretrain", {"val/loss": 2.0}, torch.zeros(2))
    assert tool.compare(before, after) == 0  # timings are the machine's, not the model's
    _stage(before, "quickstart", "instruct", {"val/loss": 3.0}, torch.ones(1))
    _stage(after, "quickstart", "instruct", None, None)  # cut off before its end on this side
    assert tool.compare(before, after) == 1
    assert "instruct   MISSING" in capsys.readouterr().out
    save_file({"w": torch.zeros(2) + 1e-7}, str(after / "quickstart" / "pretrain" / "export" / "model.safetensors"))
    tool.compare(before, after)
    assert "tensor model.safetensors:w changed" in capsys.readouterr().out
