"""A family's per-sample inputs: the shipped ones read what they name, and a family that
registers inputs that cannot work is refused in one line when it registers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from occtrain.core.registry import register_family
from occtrain.core.sample_inputs import IMAGE_TOKENS, VOXELS, SampleInput
from occtrain.data.layout import DatasetIndex
from occtrain.errors import ConfigError


class Source:
    """Stands in for the engine's frozen camera encoder: each view's mean colour."""

    def encode_images(self, images: torch.Tensor) -> torch.Tensor:
        return images.float().mean((2, 3))  # (B, N, 3)


def test_voxels_are_the_frames_labels(synth_dataset):
    index = DatasetIndex.open(synth_dataset)
    samples = list(index.samples())[:2]
    rows = VOXELS.rows(Source(), index, samples)
    for row, (scene, token) in zip(rows, samples):
        assert np.array_equal(row.numpy(), index.labels(scene, token)["semantics"])
    assert not VOXELS.encoded and VOXELS.cache_file == "voxels.safetensors"


def test_image_tokens_go_through_the_frozen_encoder(synth_dataset):
    index = DatasetIndex.open(synth_dataset)
    samples = list(index.samples())[:2]
    rows = IMAGE_TOKENS.rows(Source(), index, samples)
    views = np.stack([index.images(s, t) for s, t in samples]).astype(np.float32)
    assert torch.allclose(rows, torch.from_numpy(views.mean((2, 3))))
    assert IMAGE_TOKENS.encoded and IMAGE_TOKENS.reads_cameras


def _with_inputs(*inputs: object, reads_cameras: bool = False):
    from plugins.tiny_family import TINY

    world = dataclasses.replace(TINY.world, sample_inputs=inputs, reads_cameras=reads_cameras)
    return dataclasses.replace(TINY, name="tiny_inputs_check", world=world)


@pytest.mark.parametrize(
    ("inputs", "reads_cameras", "message"),
    [
        (("voxels",), False, "is not an occtrain.core.sample_inputs.SampleInput"),
        ((VOXELS, SampleInput("voxels", VOXELS.rows)), False, "share a name"),
        ((IMAGE_TOKENS,), False, "needs reads_cameras=True"),
    ],
)
def test_a_family_with_unusable_inputs_is_refused(inputs, reads_cameras, message):
    with pytest.raises(ConfigError, match=message):
        register_family(_with_inputs(*inputs, reads_cameras=reads_cameras))
