"""occtrain eval's outputs: what --save-predictions writes is what it refuses to overwrite."""

from __future__ import annotations

import re

import numpy as np
import pytest

from occtrain.commands.evaluate import FORECAST_DIR, PREDICTION_FILES, _check_outputs, write_predictions
from occtrain.errors import ConfigError


def test_every_file_save_predictions_writes_is_one_a_later_eval_refuses_to_overwrite(tmp_path):
    predictions = {
        "planning": {"t": [[0.0, 1.0]]},
        "planning_gt": {"t": {"traj": [[0.0, 1.0]]}},
        "forecast": {"t": ("scene-0000", np.zeros((2, 1, 1, 1), np.uint8))},
        "qa": {"t-0": ({"question": "q", "answer": "a"}, "a")},
        "captions": {"t": "c"},
        "captions_gt": {"t": ["c"]},
        "meta_actions": {"t": {"generated": "g"}},
    }
    out = tmp_path / "preds"
    write_predictions(out, predictions)
    written = [*PREDICTION_FILES, f"{FORECAST_DIR}/scene-0000/t/forecast.npz"]
    assert {str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()} == set(written)
    for name in written:  # each refused, in the order the check looks
        with pytest.raises(
            ConfigError, match=re.escape(f"{out / name}: exists, and --save-predictions would overwrite")
        ):
            _check_outputs(tmp_path, "pretrain", True, tmp_path / "metrics.json", out)
        (out / name).unlink()
    _check_outputs(tmp_path, "pretrain", True, tmp_path / "metrics.json", out)  # emptied: accepted


def test_predictions_appear_whole_or_under_a_partial_name(tmp_path, monkeypatch):
    """A kill while the predictions are written (here: a failure after the first file) leaves
    no folder that looks like a whole set; the next eval's replaces the partial one."""
    import occtrain.commands.evaluate as evaluate

    predictions = {"qa": {"t|q": ({"question": "q"}, "yes")}, "meta_actions": {"t": {"truth": "maintain"}}}
    out = tmp_path / "preds"
    real = evaluate.atomic_write_json
    calls = []

    def dies_after_one(path, data):
        calls.append(path)
        if len(calls) > 1:
            raise KeyboardInterrupt  # stands for the kill
        return real(path, data)

    monkeypatch.setattr(evaluate, "atomic_write_json", dies_after_one)
    with pytest.raises(KeyboardInterrupt):
        evaluate.write_predictions(out, predictions)
    assert not out.exists() and (tmp_path / ".preds.partial" / "qa_questions.json").is_file()
    monkeypatch.setattr(evaluate, "atomic_write_json", real)
    evaluate.write_predictions(out, predictions)
    assert sorted(p.name for p in out.iterdir()) == ["meta_actions.json", "qa_pred.json", "qa_questions.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["preds"]
