"""Occ-LLM's world model: patch tokens and their payload, frame separation, pre-fusion, the
patch head, generation against training, and scenes of two codebooks through the joint
vocabulary and the code cache."""

from __future__ import annotations

import json

import pytest
import torch

from occtrain.config.llm import LLMConfig
from occtrain.core.builder import collate
from occtrain.core.decoding import ActionAnswer, SceneAnswer
from occtrain.core.vocab import JointVocab
from occtrain.errors import ConfigError
from occtrain.families.occllama.world_model import OccLLaMAWorldModel as OccWorldModel
from occtrain.families.occllm import OccLLMWorldConfig, OccLLMWorldModel
from occtrain.models.llm import build_llm
from occtrain.models.text_tokenizer import train_text_tokenizer

TEXTS = ["go straight then turn left", "<4-D occupancy forecasting and self-ego planning>", "<question-answering>"]
SIZES = [8, 16]  # motion, static
HW = (4, 4)
XY = torch.tensor([[1.0, 0.5]])


def llm_cfg(mode: str = "next_scene") -> LLMConfig:
    return LLMConfig(
        hidden_size=32,
        num_layers=1,
        num_heads=2,
        intermediate_size=64,
        action_bins=16,
        action_range=[[-10.0, 10.0], [-10.0, 10.0]],
        scene_prediction=mode,
    )


def world(mode: str = "next_scene", seed: int = 0, **cfg) -> OccLLMWorldModel:
    torch.manual_seed(seed)
    vocab = JointVocab(train_text_tokenizer(TEXTS, 300), SIZES, HW, llm_cfg(mode), patch=cfg.get("patch_size", 2))
    books = [torch.randn(k, 3) for k in SIZES]
    settings = OccLLMWorldConfig(**{"patch_size": 2, "cell_dim": 8, **cfg})
    return OccLLMWorldModel(build_llm(llm_cfg(mode), len(vocab)), vocab, books, mode, settings, HW).eval()


def scene_codes(seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.cat([torch.randint(0, k, (HW[0] * HW[1],), generator=g) for k in SIZES])


def prompt(w: OccLLMWorldModel):
    return w.builder().actions(XY).scene(scene_codes(1)).text("go straight")


def test_a_scene_is_patch_tokens_carrying_their_cells_in_both_codebooks():
    w = world()
    v = w.vocab
    codes = scene_codes(1)
    seq = w.builder().scene(codes).build()
    slots = v.is_occ(seq.input_ids)
    assert v.scene_len == 4 and int(slots.sum()) == 4  # 4 x 4 latent, 2 x 2 patches
    assert seq.input_ids.tolist() == [v.bos_id, v.occ_open_id, *range(v.occ_start, v.occ_start + 4), v.occ_close_id]
    cells = seq.payload["cells"][slots]  # (patches, p*p, codebooks)
    grid = codes.view(2, *HW)
    # Patch 1 is the top-right 2 x 2 block; its cells row-major, each with (motion, static).
    assert cells[1].tolist() == [[int(grid[0, r, c]), int(grid[1, r, c])] for r in (0, 1) for c in (2, 3)]
    assert torch.equal(w.codes_of(w.cells_of(codes)), codes)


def test_frame_separation_is_a_switch():
    on, off = world(frame_separation=True), world(frame_separation=False)
    codes = scene_codes(2)
    with_markers = on.builder().actions(XY).scene(codes).build().input_ids
    without = off.builder().actions(XY).scene(codes).build().input_ids
    v = on.vocab
    assert (with_markers == v.occ_open_id).sum() == 1 and (with_markers == v.occ_close_id).sum() == 1
    assert not bool(((without == v.occ_open_id) | (without == v.occ_close_id)).any())
    assert len(with_markers) == len(without) + 2


def test_pre_fusion_gates_a_scene_by_the_action_before_it_and_learns_from_the_loss():
    w = world().train()
    v = w.vocab
    seq = (
        w.builder()
        .actions(XY)
        .scene(scene_codes(1))
        .actions(torch.tensor([[2.0, -1.0]]), True)
        .scene(scene_codes(2), True)
        .build()
    )
    slots = v.is_occ(seq.input_ids)
    fused = seq.payload["fusion"][slots]
    # The waypoint's bin centre: what generation reads back from the bins it chose.
    centre = lambda xy: v.actions_from_ids(v.action_ids(torch.tensor([xy])))[0].tolist()  # noqa: E731
    assert fused[:4].tolist() == [centre([1.0, 0.5])] * 4 and fused[4:].tolist() == [centre([2.0, -1.0])] * 4
    assert centre([1.0, 0.5]) != [1.0, 0.5]  # 1.25 m bins: the raw waypoint is not a centre
    # A scene after text fuses no action.
    assert w.builder().text("go straight").scene(scene_codes(1)).build().payload["fusion"].abs().sum() == 0
    out = w(collate([seq], v.pad_id))
    out.loss.backward()
    assert w.fusion.mlp[-1].weight.grad.abs().sum() > 0  # the gate learns from the world model's loss
    assert w.patch_embed.proj[1].weight.grad.abs().sum() > 0 and w.head.classify[1].weight.grad.abs().sum() > 0
    # Once the gate is away from the identity, the same scene embeds differently after another action.
    with torch.no_grad():
        w.fusion.mlp[-1].bias.normal_()
        w.fusion.mlp[-1].weight.normal_()
    a = w.builder().actions(XY).scene(scene_codes(1)).build()
    b = w.builder().actions(-XY).scene(scene_codes(1)).build()
    ea, eb = (
        w.embed(a.input_ids[None], {k: t[None] for k, t in a.payload.items()}),
        w.embed(b.input_ids[None], {k: t[None] for k, t in b.payload.items()}),
    )
    slots = v.is_occ(a.input_ids)
    assert not torch.allclose(ea[0, slots], eb[0, slots])
    assert world(pre_fusion=False).fusion is None


def test_the_loss_averages_text_and_cell_targets_alike():
    w = world()
    seq = prompt(w).actions(XY, True).scene(scene_codes(3), True).build()
    with torch.no_grad():
        out = w(collate([seq], w.vocab.pad_id))
    n_text = int((seq.labels != -100).sum())
    n_cells = 4 * 4 * 2  # one supervised scene: 16 cells, 2 codebooks
    assert out.loss == pytest.approx(
        (out.text_loss * n_text + out.scene_loss * n_cells).item() / (n_text + n_cells), rel=1e-5
    )
    assert out.scene_loss > 0 and out.text_loss > 0


@pytest.mark.parametrize("mode", ["next_scene", "next_token"])
@pytest.mark.parametrize("separation", [True, False])
def test_generation_is_the_same_cached_uncached_and_batched(mode, separation):
    w = world(mode, frame_separation=separation)
    p = prompt(w).build()
    outs = []
    for use_cache in (True, False):
        d = w.decoder(p, use_cache=use_cache)
        outs.append((d.actions(1), d.scene(), d.actions(1), d.scene()))
    batched = w.generate_batch(
        [p, prompt(w).text("go straight").build()],
        [[ActionAnswer(1), SceneAnswer(), ActionAnswer(1), SceneAnswer()]] * 2,
    )
    for got in (outs[1], batched[0]):
        for x, y in zip(outs[0], got):
            assert torch.equal(x, y)
    assert outs[0][1].shape == (2 * 16,) and bool((outs[0][1][:16] < SIZES[0]).all())


def test_generation_fuses_the_waypoint_it_generated_and_reads_what_training_reads():
    w = world("next_scene")
    with torch.no_grad():  # a gate that depends on the action, so a wrong one would show
        w.fusion.mlp[-1].weight.normal_()
    d = w.decoder(prompt(w).build())
    waypoint, codes = d.actions(1), d.scene()
    d.flush()  # the chosen patches are fed with their payload
    # Teacher-forcing the generated answer reproduces the decoder's query outputs.
    seq = prompt(w).actions(waypoint, True).scene(codes, True).build()
    out = w(collate([seq], w.vocab.pad_id), output_hidden_states=True)
    queries = w.vocab.is_query(seq.input_ids)
    chosen = torch.stack([logits.argmax(-1) for logits in w.head(out.hidden[0, queries])], -1)
    assert torch.equal(w.codes_of(chosen), codes)
    slots = w.vocab.is_occ(d.ids)
    fused = d.payload["fusion"][slots][-4:]  # the generated scene's patches
    assert torch.allclose(fused, waypoint.expand(4, 2))


def test_two_codebooks_in_the_codes_layout_pick_within_their_own_range():
    """OccLLaMA's world model reads a two-codebook tokenizer: a scene is 2 x h x w code
    tokens, codebook-major, each position choosing among its own codebook's codes."""
    torch.manual_seed(0)
    vocab = JointVocab(train_text_tokenizer(TEXTS, 300), SIZES, (2, 2), llm_cfg())
    assert vocab.scene_len == 8 and vocab.num_codes == 24
    assert vocab.scene_token_range(0) == (vocab.occ_start, vocab.occ_start + 8)
    assert vocab.scene_token_range(4) == (vocab.occ_start + 8, vocab.occ_start + 24)
    codes = torch.tensor([7, 0, 1, 2, 15, 0, 3, 9])
    ids = vocab.occ_ids(codes)
    assert ids.tolist() == [vocab.occ_start + c for c in (7, 0, 1, 2)] + [
        vocab.occ_start + 8 + c for c in (15, 0, 3, 9)
    ]
    assert torch.equal(vocab.codes_from_ids(ids), codes)
    with pytest.raises(ValueError, match="their codebook"):
        vocab.occ_ids(torch.tensor([8, 0, 0, 0, 0, 0, 0, 0]))  # 8 is not a code of the 8-code motion book
    logits = torch.zeros(8, len(vocab))
    logits[:, vocab.occ_start + 8] = 5.0  # static code 0 scores highest everywhere
    assert vocab.pick_scene(logits)[:4].lt(vocab.occ_start + 8).all()  # motion positions never take it
    w = OccWorldModel(build_llm(llm_cfg(), len(vocab)), vocab, torch.randn(24, 3)).eval()
    scene = w.decoder(w.builder().text("go straight").build().input_ids).scene()
    assert bool((scene[:4] < 8).all()) and bool((scene[4:] < 16).all())


def test_two_codebook_scenes_round_trip_through_the_code_cache(tmp_path, hand_dataset):
    from occtrain.core.tokenizer_exports import build_tokenizer, save_tokenizer
    from occtrain.data.layout import DatasetIndex
    from occtrain.engine import new_world_model
    from occtrain.families.occllm.tasks import TaskConfig

    tiny = dict(num_codes=16, num_codes_motion=8, code_dim=8, class_embed_dim=4, base_channels=8,
                channel_mult=[1, 1, 1], strides=[4, 5], num_res_blocks=1, latent_attention=False,
                z_channels=8)  # fmt: skip
    torch.manual_seed(0)
    tok = build_tokenizer("occllm_msvae", tiny).eval()
    export = save_tokenizer(tok, "occllm_msvae", tiny, tmp_path / "tok")
    assert json.loads((export / "config.json").read_text())["codebook_sizes"] == [8, 16]
    llm = LLMConfig(hidden_size=32, num_layers=1, num_heads=2, intermediate_size=64, text_vocab_size=300)
    engine = new_world_model(
        {"tokenizer": export},
        llm,
        TaskConfig(),
        hand_dataset,
        family="occllm",
        world_cfg=OccLLMWorldConfig(patch_size=5),
    )
    assert engine.vocab.codebook_sizes == [8, 16] and engine.vocab.scene_len == 4
    cache = tmp_path / "cache" / "codes.safetensors"
    engine.build_scene_cache(hand_dataset, cache)
    assert cache.is_file()
    again = new_world_model(
        {"tokenizer": export},
        llm,
        TaskConfig(),
        hand_dataset,
        family="occllm",
        world_cfg=OccLLMWorldConfig(patch_size=5),
    )

    def no_encoding(*args, **kwargs):
        raise AssertionError("the cached codes were encoded again")

    again.scene_encoder.encode = no_encoding
    again.build_scene_cache(hand_dataset, cache)  # read back from the file
    index = DatasetIndex.open(hand_dataset)
    assert set(again.scene_cache) == {t for _, t in index.samples()}
    scene, token = next((s, t) for s, ts in index.scenes.items() for t in ts)
    semantics = torch.from_numpy(index.labels(scene, token)["semantics"]).long()[None]
    with torch.no_grad():
        grids = tok.encode(semantics)  # (1, 2, 10, 10): motion, static
        assert grids.shape == (1, 2, 10, 10)
        assert torch.equal(again.scene_cache[token].long(), grids.reshape(-1))
        assert torch.equal(again.decode_scenes(again.scene_cache[token][None].long()), tok.decode(grids).argmax(1))


def test_the_tasks_use_the_papers_prompts_and_alternate_waypoints_with_frames(hand_dataset):
    from occtrain.data.clips import Actions, Scene, Text, frame_clips
    from occtrain.data.layout import DatasetIndex
    from occtrain.families.occllm.tasks import TaskConfig, every_question, forecasting

    index = DatasetIndex.open(hand_dataset)
    clip = next(c for c in frame_clips(index, "train", 2, 6, partial_history=False) if c.qa)
    cfg = TaskConfig(context_frames=2, forecast_frames=3)
    parts = forecasting(clip, cfg, None)
    a = clip.anchor_index
    positions = clip.ego_positions()
    # Context: each frame after the ego's position at it (the anchor's is the origin).
    assert [type(p) for p in parts[:6]] == [Actions, Scene] * 3 and [p.frame for p in parts[1:6:2]] == [a - 2, a - 1, a]
    assert [p.xy[0] for p in parts[0:6:2]] == [pytest.approx(tuple(positions[f])) for f in (a - 2, a - 1, a)]
    assert parts[4].xy[0] == pytest.approx((0.0, 0.0), abs=1e-9)
    assert parts[6] == Text("<4-D occupancy forecasting and self-ego planning>")
    answer = parts[7:]
    assert [type(p) for p in answer] == [Actions, Scene] * 3 and all(p.supervise for p in answer)
    assert [p.frame for p in answer[1::2]] == [a + 1, a + 2, a + 3]
    questions = every_question(clip, cfg)
    assert len(questions) == len(clip.qa) and questions[0][6] == Text("<question-answering>")
    assert questions[0][-2].text.startswith("Question: ") and questions[0][-1].supervise


def test_every_parameter_takes_part_in_a_step_without_scenes():
    """Under DDP a parameter without a gradient stalls the reduction: a batch of text alone
    still runs the patch embedding, pre-fusion and patch head (on zero rows)."""
    w = world().train()
    out = w(collate([w.builder().text("go straight", True).build()], w.vocab.pad_id))
    out.loss.backward()
    missing = [n for n, p in w.named_parameters() if p.requires_grad and p.grad is None]
    assert missing == []
    with pytest.raises(ValueError, match="pass the laid-out sequence"):
        w.decoder(prompt(w).build().input_ids)


def test_packed_sequences_train_as_they_would_alone():
    # Its cell loss sits at the positions that emit patches: per sequence through sample_index.
    w = world()
    seqs = [
        prompt(w).actions(XY, True).scene(scene_codes(3), True).build(),
        prompt(w).text("go straight then turn left", True).build(),
        prompt(w).scene(scene_codes(4), True).build(),
    ]
    with torch.no_grad():
        padded, packed = w(collate(seqs, w.vocab.pad_id)), w(collate(seqs, w.vocab.pad_id, [[0, 1], [2]]))
    for name in ("loss", "text_loss", "scene_loss", "sample_loss"):
        torch.testing.assert_close(getattr(packed, name), getattr(padded, name), rtol=1e-5, atol=1e-6)


def test_pre_fusion_comes_before_the_patch_parts_it_feeds():
    """The patch parts live in core now; pre-fusion is still made and registered first, so a
    seed gives the same initial weights as before and the parameters keep their order (a
    checkpoint's optimizer state lists them by position)."""
    names = [n.split(".")[0] for n, _ in world().named_parameters()]
    order = [n for i, n in enumerate(names) if n not in names[:i]]
    assert order == ["llm", "fusion", "patch_embed", "head"]


def test_a_scene_is_fused_with_the_egos_position_also_where_a_prior_writes_offsets():
    """History waypoints are written as positions, a forecast's under a plan prior as
    offsets from it: the scene after either carries the position (the bins read back, the
    prior added), in training and in generation alike."""
    w = world("next_scene")
    with torch.no_grad():
        w.fusion.mlp[-1].weight.normal_()
    base = ((2.0, 0.0),)
    position = torch.tensor([[2.6, 0.4]])  # 0.6 m ahead of the prior, 0.4 m left
    seq = prompt(w).actions(position, True, base).scene(scene_codes(3), True).build()
    slots = w.vocab.is_occ(seq.input_ids)
    fused = seq.payload["fusion"][slots][-4:]
    bins_of_offset = w.vocab.actions_from_ids(w.vocab.action_ids(position - torch.tensor(base)))
    assert torch.allclose(fused, (bins_of_offset + torch.tensor(base)).expand(4, 2))
    assert not torch.allclose(fused, bins_of_offset.expand(4, 2))  # not the offset the bins hold
    d = w.decoder(prompt(w).build())
    waypoint = d.answer(ActionAnswer(1, base))
    d.scene()
    d.flush()
    generated = d.payload["fusion"][w.vocab.is_occ(d.ids)][-4:]
    assert torch.allclose(generated, waypoint.expand(4, 2))  # the position, prior added back


def test_moved_observed_scene_queries_carry_the_present_moved_by_the_egos_position():
    moved = []

    class Mover:
        def codes(self, scene, step):
            moved.append(step)
            return torch.roll(scene, 1)

        def labels(self, codes, step):
            return None

    w = world("next_scene", scene_queries="moved_observed_scene", copy_bias=2.0)
    w.scene_mover = Mover()
    present = scene_codes(1)
    seq = w.builder().actions(XY).scene(present).actions(torch.tensor([[3.0, 1.0]]), True).scene(scene_codes(2), True)
    payload = seq.build().payload
    carrying = payload["carries"].bool()
    assert int(carrying.sum()) == 4  # the one query block
    assert torch.equal(w.codes_of(payload["cells"][carrying]), torch.roll(present, 1))
    assert moved == [(3.0, 1.0)]  # the ego's position at the new frame, from the present
    assert world("next_scene").copy_bias is None  # the paper's learned queries: no copy path
    with pytest.raises(ConfigError, match="scene_queries: 'moved' is not one of learned"):
        OccLLMWorldConfig(scene_queries="moved").validate("model.occllm", None)


def test_a_cell_the_query_carried_and_the_target_changes_weighs_change_weight():
    mover = type(
        "Mover", (), {"codes": staticmethod(lambda scene, step: scene), "labels": staticmethod(lambda c, s: None)}
    )()
    present, future = scene_codes(1), scene_codes(1).clone()
    future[:3] = (future[:3] + 1) % SIZES[0]  # three motion cells change, the rest are kept
    losses = {}
    for weight in (1.0, 5.0):
        w = world("next_scene", scene_queries="moved_observed_scene", change_weight=weight)
        w.scene_mover = mover
        seq = w.builder().actions(XY).scene(present).actions(XY, True).scene(future, True).build()
        payload = seq.payload
        emits = payload["target"][..., 0, 0] != -100
        weights = w.cell_weights(payload["target"][emits], payload, emits)
        assert int((weights == weight).sum()) == (3 if weight > 1 else weights.numel())
        with torch.no_grad():
            losses[weight] = w(collate([seq], w.vocab.pad_id)).scene_loss.item()
    assert losses[5.0] > losses[1.0]


def test_a_forecast_target_keeps_its_querys_code_where_the_scene_did_not_change_and_weighs_movers():
    """Over dataset frames (their labels known): a future code that differs from the moved
    present's where the voxels under the cell are the same is a synonym and becomes the
    query's; the cells where a car came and went weigh mover_weight (core.forecast_targets)."""
    from occtrain.formats.occ3d import CLASS_INDEX, FREE

    present, future = scene_codes(1), scene_codes(2)  # every cell's code may differ
    labels = {}
    for codes, car_at in ((present, 0), (future, 50)):
        volume = torch.full((200, 200, 16), FREE, dtype=torch.long)
        volume[car_at : car_at + 50, 0:50, 1:3] = CLASS_INDEX["car"]  # fills cell (0, 0), then (1, 0)
        labels[codes.numpy().tobytes()] = volume

    class Mover:
        def codes(self, scene, step):
            return scene  # the query carries the present as it is, codes and all

        def labels(self, codes, step):
            return labels.get(codes.reshape(-1).numpy().tobytes())

    w = world("next_scene", scene_queries="moved_observed_scene", mover_weight=4.0)
    w.scene_mover = Mover()
    seq = w.builder().actions(XY).scene(present).actions(XY, True).scene(future, True).build()
    payload = seq.payload
    carried = payload["carries"].bool()
    target = w.codes_of(payload["target"][carried]).reshape(len(SIZES), *HW)
    want = present.reshape(len(SIZES), *HW).clone()
    want[:, :2, 0] = future.reshape(len(SIZES), *HW)[:, :2, 0]  # the cells the car left and reached
    assert torch.equal(target, want)
    movers = w.codes_of(payload["mover"][carried].long()[..., None].expand(-1, -1, len(SIZES)))
    assert movers.reshape(len(SIZES), *HW)[0].nonzero().tolist() == [[0, 0], [1, 0]]
    emits = payload["target"][..., 0, 0] != -100
    weights = w.cell_weights(payload["target"][emits], payload, emits)
    assert int((weights == 4.0).sum()) == 2 * len(SIZES) and int((weights == 1.0).sum()) == weights.numel() - 4
