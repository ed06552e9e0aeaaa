"""Sequence packing: which sequences share a row, and a packed batch's masks and indices."""

from __future__ import annotations

import pytest
import torch

from occtrain.core.builder import collate, sample_means
from occtrain.core.packing import pack_rows
from occtrain.core.sequence import IGNORE, TokenSequence


def test_first_fit_decreasing_by_hand():
    # Longest first: 6 fills a row; 5 opens one (room 1); 4 opens one (room 2); 3 fits
    # neither and opens one; 2 fits the 4's row. Rows listed by their first sequence.
    lengths = [5, 3, 4, 2, 6]
    rows = pack_rows(lengths)
    assert rows == [[0], [1], [2, 3], [4]]
    seqs = [seq(n, 10 * i) for i, n in enumerate(lengths)]
    padding = 1 - collate(seqs, pad_id=0, rows=rows)["pad_mask"].float().mean().item()
    assert padding == pytest.approx(1 - 20 / 24)
    # One to a row, the same five pad to 6 each: 1 - 20/30.
    assert 1 - collate(seqs, pad_id=0)["pad_mask"].float().mean().item() == pytest.approx(1 - 20 / 30)


def test_a_longer_row_takes_more_and_a_longer_sequence_is_never_cut():
    # 6 opens a row (room 4), 5 another (room 5), 4 fills the first, 3 and 2 the second.
    assert pack_rows([5, 3, 4, 2, 6], capacity=10) == [[0, 1, 3], [2, 4]]
    assert pack_rows([12, 3], capacity=10) == [[0], [1]]
    assert pack_rows([]) == []


def seq(n: int, first: int, segments: list[int] | None = None) -> TokenSequence:
    ids = torch.arange(first, first + n)
    labels = torch.cat([ids[1:], torch.tensor([IGNORE])])
    seg = torch.tensor(segments) if segments else torch.zeros(n, dtype=torch.long)
    zeros = torch.zeros(n, dtype=torch.long)
    return TokenSequence(ids, labels, seg, torch.arange(n), torch.zeros(n, dtype=torch.bool), zeros)


def test_a_packed_row_keeps_each_sequence_to_itself_at_its_own_positions():
    # b has a scene (segment 1) as a holds one: the same segment id, different sequences.
    a, b, c = seq(3, 10, [0, 1, 1]), seq(2, 20, [1, 1]), seq(4, 30)
    batch = collate([a, b, c], pad_id=0, rows=[[0, 1], [2]])
    assert batch["input_ids"].tolist() == [[10, 11, 12, 20, 21], [30, 31, 32, 33, 0]]
    assert batch["position_ids"].tolist() == [[0, 1, 2, 0, 1], [0, 1, 2, 3, 0]]
    assert batch["sample_index"].tolist() == [[0, 0, 0, 1, 1], [2, 2, 2, 2, -1]]
    assert batch["sample_row"].tolist() == [0, 0, 1]
    allowed = batch["attention_mask"][0, 0]
    # a's scene block is bidirectional, b's too, and neither sees the other.
    want = torch.tensor(
        [
            [1, 0, 0, 0, 0],
            [1, 1, 1, 0, 0],
            [1, 1, 1, 0, 0],
            [0, 0, 0, 1, 1],
            [0, 0, 0, 1, 1],
        ],
        dtype=torch.bool,
    )
    assert torch.equal(allowed, want)
    # Each sequence's last token predicts nothing: no target crosses into the next one.
    assert batch["labels"][0].tolist() == [11, 12, IGNORE, 21, IGNORE]


def test_sample_means_follow_the_sequences_not_the_rows():
    a, b, c = seq(3, 10), seq(2, 20), seq(4, 30)
    batch = collate([a, b, c], pad_id=0, rows=[[0, 1], [2]])
    sums = torch.tensor([[1.0, 2.0, 3.0, 4.0, 6.0], [1.0, 1.0, 1.0, 1.0, 9.0]])
    counts = batch["pad_mask"].long()
    assert sample_means(sums, counts, batch).tolist() == [2.0, 5.0, 1.0]  # padding's 9 left out


def test_what_cannot_share_a_row_is_refused():
    a, b = seq(3, 10), seq(2, 20)
    a.targets["voxels"] = torch.zeros(2)
    with pytest.raises(ValueError, match="per-sequence targets"):
        collate([a, b], pad_id=0, rows=[[0, 1]])
    with pytest.raises(ValueError, match="each of the 2 sequences once"):
        collate([a, b], pad_id=0, rows=[[0], [0]])
