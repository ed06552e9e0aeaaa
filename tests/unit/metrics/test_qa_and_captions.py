"""NuScenes-QA accuracy by hand, and caption metrics against pycocoevalcap run directly."""

from __future__ import annotations

import contextlib
import io
import shutil

import pytest
import torch

from occtrain.errors import OcctrainError
from occtrain.metrics import CAPTION_KEYS, CaptionMetric, QAMetric

needs_java = pytest.mark.skipif(
    shutil.which("java") is None, reason="pycocoevalcap's PTB tokeniser and METEOR need Java"
)


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
        {
            "exist_H0": 100.0,
            "exist_H1": 0.0,
            "count_H0": 100.0,
            "count_H1": 0.0,
            "object_H1": 100.0,
            "status_H0": 0.0,
            "comparison_H0": 100.0,
        }
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
    assert m.samples() == {
        "a": ("un vélo à gauche", ["a bicycle on the left", "bike left"]),
        "b": ("a truck", ["a truck ahead"]),
    }
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
        for scorer, names in (
            (Bleu(4), ["Bleu_1", "Bleu_2", "Bleu_3", "Bleu_4"]),
            (Meteor(), "METEOR"),
            (Rouge(), "ROUGE_L"),
            (Cider(), "CIDEr"),
        ):
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


@pytest.mark.slow
@needs_java
def test_caption_metric_by_hand():
    # "the cat sat on the mat" against "the cat is on the mat" (6 tokens each, brevity penalty 1):
    # n-gram precisions 5/6, 3/5, 1/4, 0/3; ROUGE-L: the common subsequence "the cat on the mat"
    # covers 5 of 6 tokens either way, so P = R = F = 5/6.
    m = CaptionMetric()
    m.update(["The cat sat on the mat."], [["the cat is on the mat"]], ids=["a"])
    got = {k: v.item() for k, v in m.compute().items()}
    assert got["Bleu_1"] == pytest.approx(5 / 6)
    assert got["Bleu_2"] == pytest.approx((5 / 6 * 3 / 5) ** 0.5)
    assert got["Bleu_3"] == pytest.approx((5 / 6 * 3 / 5 * 1 / 4) ** (1 / 3))
    assert got["Bleu_4"] < 1e-3  # no 4-gram matches (the reference code smooths 0 to about 1e-15)
    assert got["ROUGE_L"] == pytest.approx(5 / 6)
    assert 0 < got["METEOR"] < 1

    # CIDEr-D over two samples: one prediction equals its reference, so its tf-idf vectors
    # equal (cosine 1 at each n, equal lengths): 10; the other shares no n-gram: 0.
    m = CaptionMetric()
    m.update(
        ["a red car waits at the light", "trees line the road"],
        ["a red car waits at the light", "a bus turns left slowly"],
    )
    got = {k: v.item() for k, v in m.compute().items()}
    assert got["CIDEr"] == pytest.approx(5.0)
    assert got["samples"] == 2


def _two_process_captions(rank: int, port: int, out: str) -> None:
    """Rank 0 scores PREDS' first two samples, rank 1 the third; first with no Java on rank
    0 (every process must raise, none wait), then as they are."""
    import json
    from unittest import mock

    import torch.distributed as dist

    from occtrain.metrics import captions

    captions._METEOR = None  # a forked process's own, not this test process's
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=2)
    try:
        ids = list(PREDS)[:2] if rank == 0 else list(PREDS)[2:]
        result: dict = {}
        m = CaptionMetric()
        m.update([PREDS[i] for i in ids], [REFS[i] for i in ids], ids=ids)
        with mock.patch.object(shutil, "which", lambda name: None if rank == 0 else "/usr/bin/java"):
            try:
                m.compute()
            except OcctrainError as exc:
                result["error"] = str(exc)
        m = CaptionMetric()
        m.update([PREDS[i] for i in ids], [REFS[i] for i in ids], ids=ids)
        result["scores"] = {k: v.item() for k, v in m.compute().items()}
        result["started_meteor"] = captions._METEOR is not None
        with open(f"{out}.{rank}", "w") as fh:
            json.dump(result, fh)
    finally:
        dist.destroy_process_group()


@pytest.mark.slow
@needs_java
def test_two_processes_score_captions_once_on_the_first(tmp_path):
    """Under DDP the gathered captions are scored by the first process alone (one METEOR,
    not one per process) and every process gets exactly the single-process scores; when
    the first cannot score, every process raises instead of waiting."""
    import json

    from conftest import free_port, two_ranks

    out = tmp_path / "rank"
    two_ranks(_two_process_captions, free_port(), str(out))
    first, second = (json.loads(out.with_name(f"rank.{r}").read_text()) for r in (0, 1))
    assert "need Java" in first["error"] and "failed on the first process" in second["error"]
    single = CaptionMetric()
    single.update(list(PREDS.values()), list(REFS.values()), ids=list(PREDS))
    expected = {k: v.item() for k, v in single.compute().items()}
    assert first["scores"] == second["scores"] == expected
    assert first["started_meteor"] and not second["started_meteor"]
