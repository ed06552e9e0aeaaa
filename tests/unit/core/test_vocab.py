"""The joint vocabulary's id layout, its conversions and the action quantizer."""

from __future__ import annotations

import pytest
import torch
from transformers import PreTrainedTokenizerFast

from occtrain.config.llm import LLMConfig
from occtrain.core.vocab import JointVocab
from occtrain.errors import ConfigError
from occtrain.models.actions import ActionQuantizer
from occtrain.models.text_tokenizer import train_text_tokenizer

TEXTS = ["the car turns left at the crossing", "Question: how many cars are there? Answer: 3"] * 10


@pytest.fixture()
def tok():
    return train_text_tokenizer(TEXTS, 300)


def small_cfg() -> LLMConfig:
    # 8 bins: x over [-40, 40] (10 m bins), y over [0, 8] (1 m bins), easy to check by hand.
    return LLMConfig(action_bins=8, action_range=[[-40.0, 40.0], [0.0, 8.0]])


def test_text_tokenizer_specials_and_round_trip(tok):
    assert [tok.pad_token_id, tok.bos_token_id, tok.eos_token_id, tok.unk_token_id] == [0, 1, 2, 3]
    ids = tok("how many cars turn left?", add_special_tokens=False)["input_ids"]
    assert tok.decode(ids) == "how many cars turn left?"
    # Byte level: text never seen still encodes and decodes exactly.
    assert tok.decode(tok("Zürich 42!", add_special_tokens=False)["input_ids"]) == "Zürich 42!"


def test_layout(tok):
    T = len(tok)
    v = JointVocab(tok, 16, scene_hw=(2, 3), llm_cfg=small_cfg())
    assert v.text_range == (0, T)
    assert v.occ_range == (T, T + 16)
    assert v.act_x_range == (T + 16, T + 24)
    assert v.act_y_range == (T + 24, T + 32)
    assert (v.occ_open_id, v.occ_close_id, v.act_open_id, v.act_close_id) == (T + 32, T + 33, T + 34, T + 35)
    assert v.query_range == (T + 36, T + 42)
    assert len(v) == T + 42 == len(tok)
    names = tok.convert_ids_to_tokens([T, T + 15, T + 16, T + 24, T + 32, T + 35, T + 36, T + 41])
    assert names == ["<occ_0>", "<occ_15>", "<bin_x_0>", "<bin_y_0>", "<occ>", "</act>", "<scene_q_0>", "<scene_q_5>"]
    assert (v.bos_id, v.eos_id, v.pad_id) == (1, 2, 0)


def test_masks_and_code_round_trip(tok):
    v = JointVocab(tok, 16, scene_hw=(2, 2), llm_cfg=small_cfg())
    T = v.text_size
    ids = torch.tensor([5, T, T + 15, T + 16, T + 31, T + 32, T + 36])
    assert v.is_text(ids).tolist() == [True, False, False, False, False, False, False]
    assert v.is_occ(ids).tolist() == [False, True, True, False, False, False, False]
    assert v.is_action(ids).tolist() == [False, False, False, True, True, False, False]
    assert v.is_query(ids).tolist() == [False] * 6 + [True]
    codes = torch.tensor([[0, 7], [15, 3]])
    assert torch.equal(v.occ_ids(codes), codes.reshape(-1) + T)  # a scene's codes, flat
    assert torch.equal(v.codes_from_ids(v.occ_ids(codes)), codes.reshape(-1))
    with pytest.raises(ValueError):
        v.occ_ids(torch.tensor([16]))
    with pytest.raises(ValueError):
        v.codes_from_ids(torch.tensor([T + 16]))


def test_action_ids_by_hand(tok):
    v = JointVocab(tok, 16, scene_hw=(2, 2), llm_cfg=small_cfg(), action_grid="range")
    xs, ys = v.act_x_start, v.act_y_start
    xy = torch.tensor([[-35.0, 3.5], [12.0, 0.2], [39.9, 7.99]])
    # x bins of 10 m from -40: -35 -> 0, 12 -> 5, 39.9 -> 7; y bins of 1 m from 0: 3.5 -> 3, 0.2 -> 0, 7.99 -> 7
    assert v.action_ids(xy).tolist() == [xs + 0, ys + 3, xs + 5, ys + 0, xs + 7, ys + 7]
    centres = v.actions_from_ids(v.action_ids(xy))
    assert torch.allclose(centres, torch.tensor([[-35.0, 3.5], [15.0, 0.5], [35.0, 7.5]]))
    with pytest.raises(ValueError):
        v.actions_from_ids(torch.tensor([ys, xs]))  # y before x


def test_the_zero_grid_makes_no_move_exact_by_hand():
    q = ActionQuantizer(8, (-40.0, 0.0), (40.0, 8.0))  # x bins of 10 m, y bins of 1 m
    # x centres -40, -30, ..., 30 (0 is one); y centres 0, 1, ..., 7.
    assert q.encode(torch.tensor([[0.0, 0.0], [-35.1, 3.4], [34.0, 7.6]])).tolist() == [[4, 0], [0, 3], [7, 7]]
    assert q.decode(torch.tensor([[4, 0], [0, 3]])).tolist() == [[0.0, 0.0], [-40.0, 3.0]]
    paper = ActionQuantizer(256, (-40.0, -40.0), (60.0, 40.0))
    assert paper.decode(paper.encode(torch.zeros(1, 2))).tolist() == [[0.0, 0.0]]
    edges = ActionQuantizer(256, (-40.0, -40.0), (60.0, 40.0), grid="range")
    assert edges.decode(edges.encode(torch.zeros(1, 2))).tolist() == [[0.0390625, 0.15625]]  # 0 lies on a y edge


def test_quantizer_round_trip_within_half_a_bin():
    q = ActionQuantizer(256, (-40.0, -40.0), (60.0, 40.0), grid="range")
    g = torch.Generator().manual_seed(0)
    xy = torch.stack([torch.rand(1000, generator=g) * 100 - 40, torch.rand(1000, generator=g) * 80 - 40], dim=1)
    err = (q.decode(q.encode(xy)) - xy).abs()
    half = torch.tensor([100 / 512, 80 / 512])
    assert bool((err <= half + 1e-5).all())
    assert float(err.max(0).values[0]) > 0.9 * half[0]  # the bound is tight, not trivially met
    # Out of range clamps to the edge bins.
    far = torch.tensor([[-100.0, 100.0], [1e3, -1e3]])
    assert q.encode(far).tolist() == [[0, 255], [255, 0]]
    assert torch.allclose(
        q.decode(q.encode(far)), torch.tensor([[-40 + 50 / 256, 40 - 40 / 256], [60 - 50 / 256, -40 + 40 / 256]])
    )


def test_decode_text_hides_joint_tokens(tok):
    v = JointVocab(tok, 4, scene_hw=(1, 2), llm_cfg=small_cfg())
    ids = v.text_ids("the car") + [v.occ_start, v.act_open_id, v.eos_id] + v.text_ids(" turns")
    assert v.decode_text(ids) == "the car turns"
    assert "<occ_0><act>" in tok.decode(ids)


def test_json_round_trip_with_saved_tokenizer(tok, tmp_path):
    v = JointVocab(tok, 16, scene_hw=(3, 3), llm_cfg=small_cfg())
    tok.save_pretrained(str(tmp_path))
    loaded = PreTrainedTokenizerFast.from_pretrained(str(tmp_path), local_files_only=True)
    w = JointVocab.from_json(v.to_json(), loaded)
    assert (w.text_size, w.occ_range, w.act_y_range, w.query_range, len(w)) == (
        v.text_size,
        v.occ_range,
        v.act_y_range,
        v.query_range,
        len(v),
    )
    xy = torch.tensor([[-12.3, 4.4]])
    assert torch.equal(w.action_ids(xy), v.action_ids(xy))
    # A tokenizer of another layout is refused with one line naming it.
    other = JointVocab(train_text_tokenizer(TEXTS, 300), 8, scene_hw=(3, 3), llm_cfg=small_cfg())
    with pytest.raises(ConfigError, match="text tokenizer"):
        JointVocab.from_json(v.to_json(), other.tokenizer)


def test_config_errors_name_the_key(tok):
    with pytest.raises(ConfigError, match="llm.scene_prediction"):
        JointVocab(tok, 4, (1, 1), LLMConfig(scene_prediction="next_frame"))
    with pytest.raises(ConfigError, match="llm.action_range"):
        JointVocab(tok, 4, (1, 1), LLMConfig(action_range=[[5.0, -5.0], [0.0, 1.0]]))


def test_delta_encoding_holds_each_move_and_keeps_positions_within_half_a_bin():
    cfg = LLMConfig(action_bins=256, action_range=[[-40.0, 60.0], [-40.0, 40.0]], action_encoding="delta")
    v, absolute = (
        JointVocab(train_text_tokenizer(TEXTS, 300), 4, (1, 1), cfg),
        JointVocab(train_text_tokenizer(TEXTS, 300), 4, (1, 1), LLMConfig()),
    )
    plan = torch.tensor([[3.5, 0.0], [7.0, 0.1], [10.5, 0.3], [14.0, 0.6], [17.5, 1.0], [21.0, 1.5]])
    ids = v.action_ids(plan).reshape(-1, 2)
    # Steady moves of 3.5 m are one repeated x token, whatever the position.
    assert len(set(ids[:, 0].tolist())) <= 2 and len(set(absolute.action_ids(plan).reshape(-1, 2)[:, 0].tolist())) == 6
    back = v.actions_from_ids(v.action_ids(plan))
    assert bool(((back - plan).abs() <= torch.tensor([50 / 256, 40 / 256]) + 1e-5).all())  # error feedback: no drift
    one = torch.tensor([[12.3, -4.4]])
    assert torch.equal(v.action_ids(one), absolute.action_ids(one))  # a one-waypoint block is the same either way
    w = JointVocab.from_json(v.to_json(), v.tokenizer)
    assert (w.action_encoding, w.action_decoding) == ("delta", "greedy")
    old = {
        k: x
        for k, x in absolute.to_json().items()
        if not k.startswith("action_") or k in ("action_bins", "action_range")
    }
    assert (
        JointVocab.from_json(old, absolute.tokenizer).action_encoding == "absolute"
    )  # an export from before the switch


def test_expected_value_decoding_picks_the_bin_of_the_mean():
    v = JointVocab(
        train_text_tokenizer(TEXTS, 300),
        4,
        (1, 1),
        LLMConfig(action_bins=8, action_range=[[-40.0, 40.0], [0.0, 8.0]], action_decoding="expected"),
    )
    logits = torch.full((len(v),), -1e4)
    lo = v.act_x_start
    logits[lo + 1], logits[lo + 6] = 0.0, 0.0  # half on -25 m, half on 25 m: the mean is 0 m, bin 4
    assert v.pick_action(logits, 0) == lo + 4
    greedy = JointVocab(
        train_text_tokenizer(TEXTS, 300), 4, (1, 1), LLMConfig(action_bins=8, action_range=[[-40.0, 40.0], [0.0, 8.0]])
    )
    assert greedy.pick_action(logits, 0) == lo + 1  # the likeliest, the first of a tie
    with pytest.raises(ConfigError, match="llm.action_decoding"):
        JointVocab(train_text_tokenizer(TEXTS, 300), 4, (1, 1), LLMConfig(action_decoding="mean"))
