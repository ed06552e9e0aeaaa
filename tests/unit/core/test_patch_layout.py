"""The patches layout shared by the families that read scenes as patches: cells in and
out of patches, the waypoint before a scene, query blocks that carry a scene (embedded as
patches, tracked as raw codes, the same in training and generation) and the copy path."""

from __future__ import annotations

import pytest
import torch

from occtrain.config.llm import LLMConfig
from occtrain.core.builder import collate
from occtrain.core.ego_steps import SceneContext
from occtrain.core.patch_layout import PatchWorldModel, last_waypoint
from occtrain.core.vocab import JointVocab
from occtrain.models.llm import build_llm
from occtrain.models.text_tokenizer import train_text_tokenizer

SIZES = [8, 16]
HW = (4, 4)
CFG = LLMConfig(
    hidden_size=32,
    num_layers=1,
    num_heads=2,
    intermediate_size=64,
    action_bins=16,
    action_range=[[-8.0, 8.0], [-8.0, 8.0]],
)
XY = torch.tensor([[2.0, -1.0]])


@pytest.fixture(scope="module")
def vocab():
    return JointVocab(train_text_tokenizer(["go straight", "turn left"], 300), SIZES, HW, CFG, patch=2)


class Carrying(PatchWorldModel):
    """Queries that carry the observed present unmoved; it records each context asked about."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.contexts: list[SceneContext] = []

    def query_cells(self, context: SceneContext) -> torch.Tensor | None:
        self.contexts.append(context)
        return None if context.observed is None else self.cells_of(context.observed)


def world(vocab, copy_bias: float | None = None, cls: type = PatchWorldModel, seed: int = 0) -> PatchWorldModel:
    torch.manual_seed(seed)
    books = [torch.randn(k, 3) for k in SIZES]
    return cls(build_llm(CFG, len(vocab)), vocab, books, "next_scene", HW, 2, cell_dim=8, copy_bias=copy_bias).eval()


def codes(seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.cat([torch.randint(0, k, (HW[0] * HW[1],), generator=g) for k in SIZES])


def test_a_scene_is_cut_into_patches_of_both_codebooks_and_back(vocab):
    w = world(vocab)
    scene = codes(1)
    cells = w.cells_of(scene)
    grid = scene.view(2, *HW)
    assert cells.shape == (4, 4, 2)
    # Patch 2 is the bottom-left 2 x 2 block, row-major, each cell with (first, second) codebook.
    assert cells[2].tolist() == [[int(grid[0, r, c]), int(grid[1, r, c])] for r in (2, 3) for c in (0, 1)]
    assert torch.equal(w.codes_of(cells), scene)
    # Without a copy bias (Occ-LLM's): no copy parameter, nothing a query carries.
    assert w.copy_bias is None and set(w.payload_spec) == {"cells", "fusion", "target"}
    assert "copy_bias" not in dict(w.named_parameters())


def test_the_waypoint_before_a_scene_is_the_last_of_the_action_block_the_ids_end_with(vocab):
    ids = torch.cat(
        [torch.tensor([vocab.act_open_id]), vocab.action_ids(torch.tensor([[1.0, 2.0], [3.0, -2.0]]))]
        + [torch.tensor([vocab.act_close_id])]
    )
    assert last_waypoint(vocab, ids).tolist() == [3.0, -2.0]
    assert last_waypoint(vocab, ids[:-1]) is None  # the block is not closed
    assert last_waypoint(vocab, torch.tensor(vocab.text_ids("go straight") + [vocab.act_close_id])) is None


def test_the_learned_queries_carry_zero_cells_in_training_and_generation(vocab):
    w = world(vocab)
    seq = w.builder().scene(codes(1)).actions(XY, True).scene(codes(2), True).build()
    q = seq.segment_ids < 0
    assert seq.input_ids[q].tolist() == vocab.query_ids().tolist()
    assert int(seq.payload["cells"][q].abs().sum()) == 0 and torch.equal(seq.payload["target"][q], w.cells_of(codes(2)))
    given = w.scene_query_payload(SceneContext(observed=codes(1)))
    assert int(given["cells"].abs().sum()) == 0 and bool((given["target"] == -100).all())


def test_a_query_block_carries_a_scene_only_with_a_copy_bias(vocab):
    w = world(vocab, cls=Carrying)
    with pytest.raises(ValueError, match="copy_bias"):
        w.builder().scene(codes(1)).actions(XY, True).scene(codes(2), True)


def test_a_query_that_carries_a_scene_is_embedded_as_its_patches_are(vocab):
    """Queries carrying the present unmoved: their input embeddings are the present's patch
    tokens' (the learned query rows are not read), and they are marked as carried."""
    w = world(vocab, copy_bias=1.0, cls=Carrying)
    seq = w.builder().scene(codes(1)).actions(XY, True).scene(codes(2), True).build()
    q, present = seq.segment_ids < 0, seq.segment_ids == 1
    assert seq.payload["carries"].tolist() == q.tolist()
    with torch.no_grad():
        emb = w.embed(seq.input_ids[None], {k: v[None] for k, v in seq.payload.items()})[0]
    assert torch.equal(emb[q], emb[present])
    assert not torch.equal(emb[q], w.llm.get_input_embeddings()(seq.input_ids[q]))


def test_the_copy_path_adds_its_bias_to_the_carried_code_of_carrying_queries_only(vocab):
    w = world(vocab, copy_bias=1.0)
    with torch.no_grad():
        w.copy_bias.copy_(torch.tensor([2.0, 5.0]))
    hidden = torch.randn(3, 32)
    cells = w.cells_of(codes(3))[:3]
    carries = torch.tensor([True, False, True])
    with torch.no_grad():
        plain = w.head(hidden)
        copied = w.patch_logits(hidden, {"cells": cells, "carries": carries})
    for i, bias in enumerate((2.0, 5.0)):
        want = torch.zeros_like(plain[i])
        for row in (0, 2):
            want[row].scatter_(-1, cells[row, :, i : i + 1], bias)
        torch.testing.assert_close(copied[i] - plain[i], want)


def test_generation_tracks_raw_codes_and_asks_for_the_queries_training_lays_out(vocab):
    """The decoder tracks the prompt's and its own scenes as raw codes (a patch id names only
    a position), asks ``query_cells`` with the context the builder gives the same sequence,
    and feeds the query block the payload training lays out."""
    w = world(vocab, copy_bias=0.0, cls=Carrying, seed=3)
    fed = []
    w.llm.register_forward_hook(lambda m, a, kw, out: fed.append(kw["inputs_embeds"]), with_kwargs=True)
    d = w.decoder(w.builder().scene(codes(1)).scene(codes(2)).build())
    a1, first, a2, second = d.actions(1), d.scene(), d.actions(1), d.scene()
    generated = list(w.contexts)
    w.contexts.clear()
    seq = w.builder().scene(codes(1)).scene(codes(2)).actions(a1, True).scene(first, True)
    seq = seq.actions(a2, True).scene(second, True).build()
    assert len(generated) == len(w.contexts) == 2
    for gen, train in zip(generated, w.contexts):
        assert torch.equal(gen.observed, codes(2)) and torch.equal(train.observed, codes(2))
        assert torch.equal(gen.last_scene, train.last_scene) and gen.offset == train.offset
    assert torch.equal(generated[1].last_scene, first)  # the generated scene, as codes
    with torch.no_grad():
        emb = w.embed(seq.input_ids[None], {k: v[None] for k, v in seq.payload.items()})[0]
    q = (seq.segment_ids < 0).nonzero().squeeze(1)
    query_blocks = [x[0, -4:] for x in fed if x.shape[1] >= 4 and torch.equal(x[0, -4:], emb[q[:4]])]
    assert len(query_blocks) == 2  # both generated query blocks were fed training's embeddings


def test_every_parameter_takes_part_in_a_step_without_scenes(vocab):
    """Under DDP a parameter without a gradient stalls the reduction: a text-only batch
    still runs the patch embedding, the head and the copy path (on zero rows)."""
    w = world(vocab, copy_bias=4.0).train()
    out = w(collate([w.builder().text("go straight", True).build()], vocab.pad_id))
    out.loss.backward()
    assert [n for n, p in w.named_parameters() if p.grad is None] == []
