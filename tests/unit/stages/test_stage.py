"""What every stage kind inherits from ``Stage``: how a batch reaches the device."""

from __future__ import annotations

from pathlib import Path

import torch

from occtrain.data.datamodule import RECORD_KEYS
from occtrain.stages.stage import Stage


class _Bare(Stage):
    def __init__(self) -> None:  # no StageContext: only the inherited hooks are exercised
        torch.nn.Module.__init__(self)

    def export(self, path: Path) -> Path:
        return path


def test_a_batch_moves_its_tensors_and_leaves_its_records_as_they_are():
    """Every tensor reaches the device, nested ones included; the per-sample records
    (never tensors) are handed on as the very objects collated, not walked or copied."""
    ann = [{"anchor": {"boxes": [[1.0, 2.0, 0.5]] * 50}, "ego_poses": [[0.0, 0.0, 0.0]]}]
    qa = [[{"question": "Any cars?", "answer": "yes"}]]
    batch = {
        "semantics": torch.zeros(1, 4, 2, 2, 2, dtype=torch.uint8),
        "ann": ann,
        "qa": qa,
        "token": ["t0"],
        "extra": {"nested": [torch.ones(2)]},  # not a record key: Lightning's own walk
    }
    assert {"ann", "qa", "token"} <= RECORD_KEYS and "extra" not in RECORD_KEYS
    moved = _Bare().transfer_batch_to_device(batch, torch.device("meta"), 0)
    assert list(moved) == list(batch)
    assert moved["semantics"].is_meta and moved["extra"]["nested"][0].is_meta
    assert moved["ann"] is ann and moved["qa"] is qa and moved["token"] is batch["token"]
    pair = (torch.ones(1), ["x"])  # a batch that is not a dict: Lightning's default
    assert _Bare().transfer_batch_to_device(pair, torch.device("meta"), 0)[0].is_meta
