"""NuScenes-QA accuracy by hand, and caption metrics against pycocoevalcap run directly."""

from __future__ import annotations

import contextlib
import io
import shutil

import pytest
import torch

from occtrain.errors import OcctrainError
from occtrain.metrics import CAPTION_KEYS, CaptionMetric, QAMetric

needs_java = pytest.mark.skipif(shutil.which("java") is None, reason="pycocoevalcap's PTB tokeniser and METEOR need Java")


# ----------------------------------------------------------------------------- QA


def test_qa_hand_case_exact_match_after_str_only():
    m = QAMetric()
    m.update(
        predictions=["yes", "Yes", "2", "3", "car", "moving", "no"],
        answers=["yes", "yes", 2, "2", "car", "parked", "no"],
        template_types=["exist", "exist", "count", "count", "object", "status", "comparison"],
        num_hops=[0, 1, 0, 1, 1, 0, 0],
    )
    r = m.compute()
    # correct: yes; "Yes" is not "yes" (no lower-casing); "2" == str(2); "3" != "2"; car; moving != parked; no
    assert r["overall"].item() == pytest.approx(100 * 4 / 7)
    assert {k: v.item() for k, v in r["by_type"].items()} == pytest.approx(
        {"exist": 50.0, "count": 50.0, "object": 100.0, "status": 0.0, "comparison": 100.0}
    )
    assert {k: v.item() for k, v in r["by_type_hop"].items()} == pytest.approx(
        {"exist_H0": 100.0, "exist_H1": 0.0, "count_H0": 100.0, "count_H1": 0.0, "object_H1": 100.0, "status_H0": 0.0, "comparison_H0": 100.0}
    )
    assert r["questions"].item() == 7


def test_qa_accumulates_over_updates_and_refuses_unknown_types():
    m = QAMetric()
    m.update(["yes"], ["yes"], ["exist"], [0])
    m.update(["no"], ["yes"], ["exist"], [0])
    assert m.compute()["by_type_hop"]["exist_H0"].item() == pytest.approx(50.0)
    with pytest.raises(ValueError, match="unknown template type 'colour'"):
        m.update(["red"], ["red"], ["colour"], [0])
    with pytest.raises(ValueError, match="num_hop 2"):
        m.update(["yes"], ["yes"], ["exist"], [2])
    with pytest.raises(ValueError, match="differ in number"):
        m.update(["yes", "no"], ["yes"], ["exist"], [0])


# ----------------------------------------------------------------------------- captions


def test_caption_strings_survive_the_tensor_states_and_repeated_ids_count_once():
    m = CaptionMetric()
    m.update(["un vélo à gauche", "a truck"], [["a bicycle on the left", "bike left"], "a truck ahead"], ids=["a", "b"])
    m.update(["un vélo à gauche"], [["a bicycle on the left", "bike left"]], ids=["a"])
    assert all(t.dtype == torch.uint8 for t in m.text)
    assert m.samples() == {"a": ("un vélo à gauche", ["a bicycle on the left", "bike left"]), "b": ("a truck", ["a truck ahead"])}
    unnamed = CaptionMetric()
    unnamed.update(["x", "x"], ["y", "y"])
    assert list(unnamed.samples()) == ["#0", "#1"]


def test_caption_metric_without_java_says_so(monkeypatch):
    monkeypatch.setattr(shutil, "which", lambda name: None)
    m = CaptionMetric()
    m.update(["a car"], ["a car"])
    with pytest.raises(OcctrainError, match="need Java"):
        m.compute()


PREDS = {
    "s1": "A white car is parked on the right side of the road.",
    "s2": "The ego vehicle turns left at the intersection, a bus waits ahead.",
    "s3": "Two pedestrians cross in front; the ego car slows down.",
}
REFS = {
    "s1": ["A white car is parked on the right.", "There is a parked white car to the right of the road."],
    "s2": ["The ego car turns left at the junction while a bus is waiting ahead."],
    "s3": ["Pedestrians are crossing ahead, so the ego vehicle decelerates.", "Two people walk across; ego slows."],
}


def reference_scores() -> dict[str, float]:
    """pycocoevalcap's own pipeline, as its COCOEvalCap.evaluate runs it (SPICE left out)."""
    from pycocoevalcap.bleu.bleu import Bleu
    from pycocoevalcap.cider.cider import Cider
    from pycocoevalcap.meteor.meteor import Meteor
    from pycocoevalcap.rouge.rouge import Rouge
    from pycocoevalcap.tokenizer.ptbtokenizer import PTBTokenizer

    tok = PTBTokenizer()
    gts = tok.tokenize({k: [{"caption": c} for c in v] for k, v in REFS.items()})
    res = tok.tokenize({k: [{"caption": PREDS[k]}] for k in REFS})
    out = {}
    with contextlib.redirect_stdout(io.StringIO()):
        for scorer, names in ((Bleu(4), ["Bleu_1", "Bleu_2", "Bleu_3", "Bleu_4"]), (Meteor(), "METEOR"), (Rouge(), "ROUGE_L"), (Cider(), "CIDEr")):
            score, _ = scorer.compute_score(gts, res)
            out.update(zip(names, score) if isinstance(names, list) else {names: score})
    return out


@pytest.mark.slow
@needs_java
def test_caption_metric_equals_pycocoevalcap():
    m = CaptionMetric()
    ids = list(PREDS)
    m.update([PREDS[i] for i in ids[:2]], [REFS[i] for i in ids[:2]], ids=ids[:2])
    m.update([PREDS[ids[2]]], [REFS[ids[2]]], ids=ids[2:])
    got = m.compute()
    expected = reference_scores()
    assert list(got) == [*CAPTION_KEYS, "samples"]
    assert {k: got[k].item() for k in CAPTION_KEYS} == expected  # exactly: it is the same code
    assert got["samples"].item() == 3
    assert 0 < expected["Bleu_4"] < expected["Bleu_1"] < 1 and expected["CIDEr"] > 0

