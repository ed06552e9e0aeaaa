"""The scene before, moved by the ego's step through the frozen tokenizer."""

import pytest
import torch

from occtrain.core.vocab import JointVocab
from occtrain.engine.moved_scenes import MovedScenes
from occtrain.formats.occ3d import FREE
from occtrain.models.text_tokenizer import train_text_tokenizer


class VoxelCodes:
    """A 'tokenizer' whose code at each cell is the label of the cell's one voxel (3 x 3 x 1)."""

    discrete = True
    export_dir = None

    def __init__(self):
        self.calls = 0

    def encode(self, semantics):
        self.calls += 1
        return semantics[..., 0].reshape(semantics.shape[0], -1)

    def decode(self, codes):
        return codes.reshape(codes.shape[0], 3, 3, 1)


class Module(VoxelCodes, torch.nn.Module):
    def __init__(self):
        torch.nn.Module.__init__(self)
        VoxelCodes.__init__(self)


@pytest.fixture(scope="module")
def vocab():
    return JointVocab(train_text_tokenizer(["go straight"], 300), 18, scene_hw=(3, 3))


def test_the_scene_moves_by_whole_voxels_and_what_comes_into_view_is_free(vocab):
    codes = torch.arange(9)  # labels 0..8, x-major
    mover = MovedScenes(vocab, Module())
    moved = vocab.codes_from_ids(mover(vocab.occ_ids(codes), (0.4, 0.0))).reshape(3, 3)
    # One voxel forward: row i of the new view is row i + 1 of the old; the far row is new.
    assert moved[:2].tolist() == codes.reshape(3, 3)[1:].tolist()
    assert moved[2].tolist() == [FREE] * 3
    left = vocab.codes_from_ids(mover(vocab.occ_ids(codes), (0.0, -0.45))).reshape(3, 3)
    assert left[:, 1:].tolist() == codes.reshape(3, 3)[:, :2].tolist()


def test_a_scene_moved_by_the_same_whole_voxels_again_is_not_encoded_again(vocab):
    encoder = Module()
    mover = MovedScenes(vocab, encoder, capacity=2)
    ids = vocab.occ_ids(torch.arange(9))
    first = mover(ids, (0.4, 0.0))
    assert torch.equal(mover(ids, (0.5, 0.1)), first)  # the same whole-voxel shift
    assert mover.computed == 1 and encoder.calls == 1
    mover(ids, (0.0, 0.4))
    mover(vocab.occ_ids(torch.arange(9).flip(0)), (0.0, 0.4))  # over capacity: the oldest goes
    mover(ids, (0.4, 0.0))
    assert mover.computed == 4


def test_a_continuous_scene_encoder_is_refused(vocab):
    encoder = Module()
    encoder.discrete = False
    with pytest.raises(ValueError, match="discrete"):
        MovedScenes(vocab, encoder)


def test_observed_labels_are_moved_without_decoding_and_generated_scenes_are_decoded(vocab):
    """A dataset frame's codes are moved from its observed labels (what training moves);
    codes no frame has (a generated scene) are decoded first."""
    observed_codes, labels = torch.arange(9), torch.full((3, 3, 1), 7)
    encoder = Module()
    mover = MovedScenes(vocab, encoder, lambda c: labels if torch.equal(c, observed_codes) else None)
    moved = vocab.codes_from_ids(mover(vocab.occ_ids(observed_codes), (0.4, 0.0))).reshape(3, 3)
    assert (moved[:2] == 7).all() and mover.decoded == 0  # the labels, not the codes, were moved
    generated = vocab.codes_from_ids(mover(vocab.occ_ids(torch.arange(9).flip(0)), (0.4, 0.0))).reshape(3, 3)
    assert generated[:2].tolist() == torch.arange(9).flip(0).reshape(3, 3)[1:].tolist() and mover.decoded == 1


def test_raw_codes_move_as_their_ids_do_and_share_what_is_kept(vocab):
    """The patches layout moves a scene's raw codes (its ids name only positions): the same
    scene as the codes layout's ids moves, from the same kept entry."""
    encoder = Module()
    mover = MovedScenes(vocab, encoder)
    codes = torch.arange(9)
    moved = mover.codes(codes, (0.4, 0.0))
    assert moved.tolist() == codes.reshape(3, 3)[1:].reshape(-1).tolist() + [FREE] * 3
    assert torch.equal(vocab.codes_from_ids(mover(vocab.occ_ids(codes), (0.5, 0.1))), moved)
    assert mover.computed == 1 and encoder.calls == 1
