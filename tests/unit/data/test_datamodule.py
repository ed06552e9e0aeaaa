"""The data module's hand-over of a collated batch to the device."""

from __future__ import annotations

import torch

from occtrain.config import DataConfig
from occtrain.data.datamodule import RECORD_KEYS, ShardDataModule


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
    data = ShardDataModule(DataConfig(root="unused"), "clips")
    moved = data.transfer_batch_to_device(batch, torch.device("meta"), 0)
    assert list(moved) == list(batch)
    assert moved["semantics"].is_meta and moved["extra"]["nested"][0].is_meta
    assert moved["ann"] is ann and moved["qa"] is qa and moved["token"] is batch["token"]
    pair = (torch.ones(1), ["x"])  # a batch that is not a dict: Lightning's default
    assert data.transfer_batch_to_device(pair, torch.device("meta"), 0)[0].is_meta
