"""OccLLaMA's world model: sequence layout, losses, training/generation agreement, KV cache."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
import torch.nn.functional as F

from occtrain.config.llm import LLMConfig
from occtrain.core.builder import SequenceBuilder, collate
from occtrain.core.decoding import QueryBlock
from occtrain.core.lm_world_model import WorldInputs
from occtrain.core.sequence import IGNORE
from occtrain.core.vocab import JointVocab
from occtrain.families.occllama.config import OccLLaMAWorldConfig
from occtrain.families.occllama.world_model import OccLLaMAWorldModel as OccWorldModel
from occtrain.models.llm import build_llm, checkpoint_layers
from occtrain.models.text_tokenizer import train_text_tokenizer

TEXTS = ["go straight", "plan the route", "turn left then stop", "the car turns left"] * 10
CFG = LLMConfig(
    hidden_size=64,
    num_layers=2,
    num_heads=4,
    intermediate_size=128,
    action_bins=16,
    action_range=[[-8.0, 8.0], [-8.0, 8.0]],
)
CTX = torch.tensor([1, 2, 3, 4, 5, 6, 7, 8, 9])
TARGET = torch.tensor([9, 9, 0, 15, 4, 4, 12, 1, 3])
XY = torch.tensor([[2.0, -1.0], [4.0, 3.0]])  # bin centres (1 m bins centred on whole metres)


@pytest.fixture(scope="module")
def vocab():
    return JointVocab(train_text_tokenizer(TEXTS, 300), 16, scene_hw=(3, 3), llm_cfg=CFG)


def make_world(vocab, mode: str, seed: int = 0, queries: str = "learned") -> OccWorldModel:
    torch.manual_seed(seed)
    return OccWorldModel(build_llm(CFG, len(vocab)), vocab, torch.randn(16, 8), mode, OccLLaMAWorldConfig(queries))


def prompt(b: SequenceBuilder) -> SequenceBuilder:
    return b.text("go straight").scene(CTX).text("plan the route")


def full_sequence(b: SequenceBuilder):
    return prompt(b).actions(XY, True).scene(TARGET, True).text("turn left then stop", True).build()


def test_next_scene_layout(vocab):
    v = vocab
    seq = SequenceBuilder(v, "next_scene").scene(CTX).actions(XY[:1], True).scene(TARGET, True).build()
    ctx_ids, tgt_ids = (v.occ_ids(CTX).tolist(), v.occ_ids(TARGET).tolist())
    act = v.action_ids(XY[:1]).tolist()
    queries = v.query_ids().tolist()
    OPEN, CLOSE, ACT, END = v.occ_open_id, v.occ_close_id, v.act_open_id, v.act_close_id
    assert seq.input_ids.tolist() == [v.bos_id, OPEN, *ctx_ids, CLOSE, ACT, *act, END, OPEN, *queries, *tgt_ids, CLOSE]
    assert seq.segment_ids.tolist() == [0, 0] + [1] * 9 + [0] * 6 + [-2] * 9 + [2] * 9 + [0]
    # Queries take the positions of the codes they stand for.
    assert seq.position_ids.tolist() == list(range(17)) + list(range(17, 26)) + list(range(17, 26)) + [26]
    # Targets: the context scene predicts nothing; </occ> predicts <act> and on through the
    # action block to the target's <occ>; the queries predict the codes; the copied codes
    # predict only </occ>.
    want = [IGNORE] * 11 + [ACT, *act, END, OPEN, IGNORE] + tgt_ids + [IGNORE] * 8 + [CLOSE, IGNORE]
    assert seq.labels.tolist() == want
    assert seq.scene_target.tolist() == [False] * 17 + [True] * 9 + [False] * 10


def test_next_token_layout(vocab):
    v = vocab
    seq = SequenceBuilder(v, "next_token").text("go straight").scene(TARGET, True).build()
    text = v.text_ids("go straight")
    tgt = v.occ_ids(TARGET).tolist()
    assert seq.input_ids.tolist() == [v.bos_id, *text, v.eos_id, v.occ_open_id, *tgt, v.occ_close_id]
    assert seq.segment_ids.abs().sum() == 0  # causal everywhere
    n = len(text) + 2
    # eos (the last prompt token) predicts <occ>, <occ> the first code, the last code </occ>.
    assert seq.labels.tolist() == [IGNORE] * (n - 1) + [v.occ_open_id, *tgt, v.occ_close_id, IGNORE]
    assert seq.scene_target.tolist() == [False] * n + [True] * 9 + [False] * 2
    with pytest.raises(ValueError, match="9 codes"):
        SequenceBuilder(v).scene(torch.arange(4))


def test_collate_pads_right(vocab):
    a = SequenceBuilder(vocab).text("go straight", True).build()
    b = SequenceBuilder(vocab).scene(CTX).build()
    batch = collate([a, b], vocab.pad_id)
    L = max(len(a), len(b))
    assert batch["input_ids"].shape == (2, L) and batch["attention_mask"].shape == (2, 1, L, L)
    assert batch["input_ids"][0, len(a) :].eq(vocab.pad_id).all() and batch["labels"][0, len(a) :].eq(IGNORE).all()
    assert batch["pad_mask"].sum(1).tolist() == [len(a), len(b)]
    # No real token attends to padding.
    assert not batch["attention_mask"][0, 0, : len(a), len(a) :].any()


def test_losses_split_text_and_scene(vocab):
    world = make_world(vocab, "next_scene")
    batch = collate([full_sequence(world.builder()), prompt(world.builder()).build()], vocab.pad_id)
    out = world(batch)
    labels, scene = batch["labels"], batch["scene_target_mask"]
    ce = F.cross_entropy(out.logits[scene], labels[scene])
    text = (labels != IGNORE) & ~scene
    assert torch.allclose(out.scene_loss, ce, atol=1e-5)
    assert torch.allclose(out.text_loss, F.cross_entropy(out.logits[text], labels[text]), atol=1e-5)
    assert torch.allclose(out.loss, F.cross_entropy(out.logits[labels != IGNORE], labels[labels != IGNORE]), atol=1e-5)
    assert int(scene.sum()) == 9 and int(text.sum()) > 9


def test_token_accuracy_by_hand():
    logits = torch.tensor([[[0.0, 1.0], [2.0, 0.0], [0.0, 3.0], [1.0, 0.0]]])
    labels = torch.tensor([[1, 1, IGNORE, 0]])
    assert float(OccWorldModel.token_accuracy(logits, labels)) == pytest.approx(2 / 3)
    assert float(OccWorldModel.token_accuracy(logits, labels, torch.tensor([[False, True, True, False]]))) == 0.0


@pytest.mark.parametrize(
    "mode,queries", [("next_scene", "learned"), ("next_scene", "last_scene"), ("next_token", "learned")]
)
def test_overfit_then_generate(vocab, mode, queries):
    """Training and generation agree: a model that memorised one sequence regenerates its
    answers greedily from the prompt (actions, then the scene, then the text)."""
    world = make_world(vocab, mode, queries=queries)
    batch = collate([full_sequence(world.builder())], vocab.pad_id)
    opt = torch.optim.Adam(world.parameters(), lr=3e-3)
    first = None
    for _ in range(150):
        out = world(batch)
        first = first if first is not None else float(out.loss.detach())
        opt.zero_grad()
        out.loss.backward()
        opt.step()
    world.eval()
    with torch.no_grad():
        final = world(batch)
    assert float(final.loss) < 0.02 * first
    assert float(world.token_accuracy(final.logits, batch["labels"])) == 1.0

    decoder = world.decoder(prompt(world.builder()).build().input_ids)
    assert torch.equal(decoder.actions(2), XY)
    assert torch.equal(decoder.scene(), TARGET)
    assert vocab.decode_text(decoder.text(20)) == "turn left then stop"
    # The generated stream is the training sequence with the queries replaced by the codes.
    seq = full_sequence(world.builder())
    assert torch.equal(decoder.flush(), seq.input_ids[seq.segment_ids >= 0])


@pytest.mark.parametrize("mode", ["next_scene", "next_token"])
def test_kv_cache_matches_recompute(vocab, mode):
    world = make_world(vocab, mode, seed=1).eval()
    prefix = prompt(world.builder()).build().input_ids
    outs = []
    for use_cache in (True, False):
        d = world.decoder(prefix, use_cache=use_cache)
        text, actions, scene, more = d.text(4), d.actions(2), d.scene(), d.text(3)
        d.flush()
        outs.append((text, actions, scene, more, d.last.logits))
    (t1, a1, s1, u1, l1), (t2, a2, s2, u2, l2) = outs
    assert t1 == t2 and torch.equal(a1, a2) and torch.equal(s1, s2) and u1 == u2
    assert torch.allclose(l1, l2, atol=1e-4)


@pytest.mark.parametrize("mode,forwards", [("next_scene", 1), ("next_token", 9)])
def test_scene_generation_cost_and_tokens(vocab, mode, forwards):
    """A scene costs one forward by next-scene prediction, h*w token by token, and
    exactly one scene's codes land between <occ> and </occ>."""
    world = make_world(vocab, mode).eval()
    calls = []
    world.llm.register_forward_hook(lambda *a: calls.append(1))
    prefix = prompt(world.builder()).build().input_ids
    d = world.decoder(prefix)
    codes = d.scene()
    assert len(calls) == forwards and codes.shape == (9,)
    tail = d.flush()[len(prefix) :]
    assert tail.tolist() == [vocab.occ_open_id, *vocab.occ_ids(codes).tolist(), vocab.occ_close_id]


def test_export_round_trip(vocab):
    world = make_world(vocab, "next_scene").eval()
    batch = collate([full_sequence(world.builder())], vocab.pad_id)
    from transformers import AutoModelForCausalLM

    llm = AutoModelForCausalLM.from_config(world.llm.config)
    inputs = WorldInputs(scene=SimpleNamespace(codebooks=[world.codebook]))
    again = OccWorldModel.from_export(world.export_config(), llm, vocab, inputs).eval()
    again.load_state_dict(world.state_dict())
    assert "codebook" not in world.state_dict()
    assert torch.allclose(world(batch).logits, again(batch).logits, atol=1e-6)
    assert again.scene_prediction == "next_scene"


def test_generation_sees_what_training_sees(vocab):
    """Untrained, exact: the query block's logits in generation equal the training forward's
    at the query positions, and after the real codes are fed, so do the next token's."""
    world = make_world(vocab, "next_scene", seed=2).eval()
    seq = full_sequence(world.builder())
    train_logits = world(collate([seq], vocab.pad_id)).logits[0]
    prefix = prompt(world.builder()).actions(XY).build().input_ids
    d = world.decoder(prefix)
    d.state.queue([vocab.occ_open_id])
    gen = d.answer(QueryBlock(vocab.query_ids())).logits
    assert torch.allclose(gen, train_logits[seq.scene_target], atol=1e-4)
    d.state.queue(vocab.occ_ids(TARGET), torch.full((9,), 9))
    d.state.queue([vocab.occ_close_id])
    d.flush()
    close = int((seq.input_ids == vocab.occ_close_id).nonzero()[-1])
    assert torch.allclose(d.last.logits, train_logits[close], atol=1e-4)


@pytest.mark.parametrize("mode", ["next_scene", "next_token"])
def test_batched_generation_equals_one_at_a_time(vocab, mode):
    """Prompts of different lengths, answers of every kind, generated as one batch: the
    same greedy tokens as each sequence decoded alone (padding and per-sequence positions
    must not leak into any sequence)."""
    from occtrain.core.decoding import ActionAnswer, SceneAnswer, TextAnswer, decode_batch

    world = make_world(vocab, mode, seed=3).eval()
    prefixes = [
        prompt(world.builder()).build().input_ids,
        world.builder().text("turn left then stop").build().input_ids,
        world.builder().scene(TARGET).scene(CTX).actions(XY).text("go straight").build().input_ids,
    ]
    plans = [
        [TextAnswer(7), ActionAnswer(2), SceneAnswer(), TextAnswer(5)],
        [ActionAnswer(3), SceneAnswer(), ActionAnswer(1), SceneAnswer()],
        [TextAnswer(4)],
    ]
    batched = decode_batch(world, prefixes, plans)
    for prefix, plan, got in zip(prefixes, plans, batched):
        d = world.decoder(prefix)
        want = []
        for answer in plan:
            if isinstance(answer, TextAnswer):
                want.append(d.text(answer.max_new_tokens))
            elif isinstance(answer, ActionAnswer):
                want.append(d.actions(answer.steps))
            else:
                want.append(d.scene())
        assert len(got) == len(want)
        for g, w in zip(got, want):
            assert (g == w) if isinstance(w, list) else torch.equal(g, w)
    # A batch of one is the single decoder too; an empty plan generates nothing.
    assert decode_batch(world, prefixes[2:], [[]]) == [[]]


def test_batched_generation_pads_little_and_takes_no_more_steps(vocab):
    """Batched decoding feeds the tokens each prompt fed alone plus little padding (at most
    one slot a row and step: a row that waits), in no more forwards than the longest alone
    per group of prompt lengths.
    Rows out of step (one at a scene's query block, one still writing text) and prompts of
    very different lengths would otherwise pad every row to the longest feed."""
    from occtrain.core.decoding import SceneAnswer, TextAnswer, decode_batch

    world = make_world(vocab, "next_scene", seed=4).eval()
    shapes = []
    world.llm.register_forward_hook(
        lambda m, a, kw, out: shapes.append(kw["inputs_embeds"].shape[:2]), with_kwargs=True
    )

    def check(prefixes, plans, groups=1):
        shapes.clear()
        batched = decode_batch(world, prefixes, plans)
        slots, forwards = sum(b * n for b, n in shapes), len(shapes)
        fed, most = 0, 0
        for prefix, plan, got in zip(prefixes, plans, batched):
            shapes.clear()
            assert [torch.as_tensor(x).tolist() for x in world.generate(prefix, plan)] == [
                torch.as_tensor(x).tolist() for x in got
            ]
            fed, most = fed + sum(n for _, n in shapes), max(most, len(shapes))
        assert forwards <= groups * most and slots - fed <= len(prefixes) * forwards

    same = [
        prompt(world.builder()).text(q).build().input_ids
        for q in ("go straight", "turn left then stop", "plan the route")
    ]
    # Texts of fixed, different lengths, then a scene: the rows reach their query blocks apart.
    check(same, [[TextAnswer(n, False), SceneAnswer(), TextAnswer(2, False)] for n in (1, 6, 12)])
    check(same, [[TextAnswer(3, False)]] * 3)  # short answers (QA)
    # A prompt twice as long as the others decodes apart from them.
    long = (
        world.builder()
        .text("go straight")
        .scene(CTX)
        .scene(TARGET)
        .scene(CTX)
        .text("the car turns left")
        .build()
        .input_ids
    )
    check([same[0], long, same[1]], [[TextAnswer(3, False)]] * 3, groups=2)


def test_branches_train_each_answer_exactly_as_alone(vocab):
    """Packed questions (branches over one context) give each answer the logits and loss it
    would get in its own sequence: branches neither see each other nor shift positions."""
    world = make_world(vocab, "next_scene").eval()
    questions = [("go straight", "turn left then stop"), ("plan the route", "the car turns left")]
    packed = prompt(world.builder())
    for q, a in questions:
        packed.branch().text(q).text(a, True)
    packed = packed.build()
    assert packed.branch_ids.max().item() == 2
    with torch.no_grad():
        out = world(collate([packed], vocab.pad_id))
        alone = [
            world(collate([prompt(world.builder()).text(q).text(a, True).build()], vocab.pad_id)) for q, a in questions
        ]
    sup = packed.labels != IGNORE
    got = out.logits[0][sup]
    want = torch.cat(
        [
            o.logits[0][b["labels"][0] != IGNORE]
            for o, b in zip(
                alone,
                [collate([prompt(world.builder()).text(q).text(a, True).build()], vocab.pad_id) for q, a in questions],
            )
        ]
    )
    assert torch.allclose(got, want, atol=1e-5)
    # Targets: each branch's answer tokens only; the trunk's last token predicts no branch.
    assert sup.sum().item() == sum(len(vocab.text_ids(a)) + 1 for _, a in questions)


def test_a_branch_cannot_start_with_an_answer(vocab):
    with pytest.raises(ValueError, match="branch must start"):
        prompt(SequenceBuilder(vocab)).branch().text("go straight", True)


def test_the_scene_cache_key_follows_the_encoder_export_and_the_dataset(tmp_path, hand_dataset):
    import shutil

    from occtrain.data.layout import DatasetIndex
    from occtrain.engine.world_engine import scene_cache_key

    class Encoder(torch.nn.Linear):
        """A scene encoder (``core.protocols.SceneEncoder``) loaded from an export."""

        discrete = True

        def encode(self, semantics: torch.Tensor) -> torch.Tensor:
            return semantics

        def decode(self, scenes: torch.Tensor) -> torch.Tensor:
            return scenes

    def exported(name: str, weights: bytes) -> torch.nn.Module:
        encoder = Encoder(2, 2)
        encoder.export_dir = tmp_path / name
        encoder.export_dir.mkdir()
        (encoder.export_dir / "config.json").write_text('{"arch": "x"}')
        (encoder.export_dir / "model.safetensors").write_bytes(weights)
        return encoder

    index = DatasetIndex.open(hand_dataset)
    a, same, other = exported("a", b"w1"), exported("b", b"w1"), exported("c", b"w2")
    # The files decide, not where the export lies (a world-model export copies its encoder's).
    assert scene_cache_key(a, index) == scene_cache_key(same, index)
    assert scene_cache_key(a, index) != scene_cache_key(other, index)
    # Another world, even a byte-identical copy elsewhere, has its own cache.
    shutil.copytree(hand_dataset, tmp_path / "copy")
    assert scene_cache_key(a, index) != scene_cache_key(a, DatasetIndex.open(tmp_path / "copy"))
    # An encoder built in memory is keyed by its weights.
    plain = torch.nn.Linear(2, 2)
    key = scene_cache_key(plain, index)
    with torch.no_grad():
        plain.weight[0, 0] += 1
    assert scene_cache_key(plain, index) != key


def test_gradient_checkpointing_gives_the_same_gradients_from_less_kept_memory(vocab):
    grads, kept = [], []
    for checkpointing in (False, True):
        world = make_world(vocab, "next_scene").train()
        if checkpointing:
            checkpoint_layers(world.llm)
        batch = collate([full_sequence(world.builder()), prompt(world.builder()).build()], vocab.pad_id)
        saved: dict[int, int] = {}

        def pack(t: torch.Tensor, saved: dict[int, int] = saved) -> torch.Tensor:
            saved.setdefault(t.data_ptr(), t.untyped_storage().nbytes())
            return t

        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            loss = world(batch).loss
        loss.backward()
        kept.append(sum(saved.values()))
        grads.append({n: p.grad for n, p in world.named_parameters() if p.grad is not None})
    assert grads[0].keys() == grads[1].keys() and len(grads[0]) > 10
    for name, g in grads[0].items():
        assert torch.allclose(g, grads[1][name], atol=1e-6), name
    assert kept[1] < 0.8 * kept[0], kept


def test_last_scene_queries_are_the_scene_before(vocab):
    """``scene_queries: last_scene``: a supervised scene's query block is the code tokens of
    the scene laid out before it (the learnable queries when none came before), at the new
    scene's positions, and the export keeps the setting."""
    v = vocab
    world = make_world(vocab, "next_scene", queries="last_scene")
    seq = world.builder().scene(CTX).actions(XY[:1], True).scene(TARGET, True).scene(CTX, True).build()
    queries = seq.input_ids[seq.segment_ids < 0].reshape(2, 9)
    assert queries[0].tolist() == v.occ_ids(CTX).tolist() and queries[1].tolist() == v.occ_ids(TARGET).tolist()
    assert seq.labels[seq.segment_ids < 0].tolist() == v.occ_ids(TARGET).tolist() + v.occ_ids(CTX).tolist()
    first = world.builder().scene(TARGET, True).build()
    assert first.input_ids[first.segment_ids < 0].tolist() == v.query_ids().tolist()
    assert world.export_config()["occllama"] == {
        "scene_queries": "last_scene",
        "patch_size": 0,
        "copy_bias": 4.0,
        "cell_dim": 64,
        "change_weight": 1.0,
        "mover_weight": 1.0,
    }
    inputs = WorldInputs(scene=SimpleNamespace(codebooks=[world.codebook]))
    old = {k: val for k, val in world.export_config().items() if k != "occllama"}  # an export from before the setting
    assert OccWorldModel.from_export(old, world.llm, vocab, inputs).cfg.scene_queries == "learned"


@pytest.mark.parametrize("queries", ["learned", "last_scene"])
def test_generated_scenes_read_the_queries_training_reads(vocab, queries):
    """Untrained, exact: each scene generated after a prompt is the greedy pick of the
    training forward at its query block, for a scene after the prompt's last scene and for
    the next one after the generated scene (generation keeps the last scene as it goes)."""
    world = make_world(vocab, "next_scene", seed=5, queries=queries).eval()
    d = world.decoder(world.builder().scene(TARGET).scene(CTX).build().input_ids)
    first, second = d.scene(), d.scene()
    seq = world.builder().scene(TARGET).scene(CTX).scene(first, True).scene(second, True).build()
    logits = world(collate([seq], vocab.pad_id)).logits[0][seq.segment_ids < 0]
    picked = torch.cat([vocab.pick_scene(logits[:9]), vocab.pick_scene(logits[9:])]) - vocab.occ_start
    assert torch.equal(picked, torch.cat([first, second]))


class ShiftingMover:
    """A scene mover that records what it is asked and answers each cell's next code."""

    def __init__(self, vocab):
        self.vocab, self.asked = vocab, []

    def __call__(self, code_ids, step):
        self.asked.append((self.vocab.codes_from_ids(code_ids).tolist(), step))
        return self.vocab.occ_ids((self.vocab.codes_from_ids(code_ids.cpu()) + 1) % 16)

    def labels(self, codes, step):
        return None  # its scenes are no dataset frame's: targets stay as they are


def test_moved_last_scene_queries_are_the_scene_before_moved_by_the_ego_step(vocab):
    """``scene_queries: moved_last_scene``: a predicted scene's query block is the scene
    before it moved by the waypoint laid out between them minus where the ego stood (the
    anchor's origin, then the last predicted waypoint); unmoved with no waypoint between."""
    v = vocab
    world = make_world(vocab, "next_scene", queries="moved_last_scene")
    world.scene_mover = mover = ShiftingMover(v)
    seq = (
        world.builder()
        .scene(CTX)
        .actions(XY[1:], False)  # the ego's past: replaced by the plan's first waypoint below
        .actions(XY[:1], True)
        .scene(TARGET, True)
        .actions(XY[1:], True)
        .scene(CTX, True)
        .scene(TARGET, True)
        .build()
    )
    assert mover.asked == [(CTX.tolist(), (2.0, -1.0)), (TARGET.tolist(), (2.0, 4.0))]
    queries = seq.input_ids[seq.segment_ids < 0].reshape(3, 9)
    assert queries[0].tolist() == v.occ_ids((CTX + 1) % 16).tolist()
    assert queries[1].tolist() == v.occ_ids((TARGET + 1) % 16).tolist()
    assert queries[2].tolist() == v.occ_ids(CTX).tolist()  # no waypoint between: the scene as it was
    world.scene_mover = None
    with pytest.raises(ValueError, match="through the engine"):
        world.builder().scene(CTX).actions(XY[:1], True).scene(TARGET, True)


def test_moved_observed_scene_queries_are_the_present_moved_by_the_ego_since_it(vocab):
    """``scene_queries: moved_observed_scene``: every predicted scene's query block is the
    last prompt scene moved by the ego's whole move since it (the waypoint before the new
    scene), never a predicted scene."""
    v = vocab
    world = make_world(vocab, "next_scene", queries="moved_observed_scene")
    world.scene_mover = mover = ShiftingMover(v)
    world.builder().scene(TARGET).scene(CTX).actions(XY[:1], True).scene(TARGET, True).actions(XY[1:], True).scene(
        TARGET, True
    ).build()
    assert mover.asked == [(CTX.tolist(), (2.0, -1.0)), (CTX.tolist(), (4.0, 3.0))]


@pytest.mark.parametrize("queries", ["moved_last_scene", "moved_observed_scene"])
def test_generated_scenes_read_the_moved_queries_training_reads(vocab, queries):
    """Generation moves the scene by the waypoints it generated, as training moves it by
    the laid-out ones: each generated scene is the greedy pick of the training forward of
    the generated sequence at its query block."""
    world = make_world(vocab, "next_scene", seed=5, queries=queries).eval()
    world.scene_mover = mover = ShiftingMover(vocab)
    d = world.decoder(world.builder().scene(TARGET).scene(CTX).build().input_ids)
    a1, first, a2, second = d.actions(1), d.scene(), d.actions(1), d.scene()
    seq = world.builder().scene(TARGET).scene(CTX).actions(a1, True).scene(first, True)
    seq = seq.actions(a2, True).scene(second, True).build()
    moves = [move for _, move in mover.asked]
    second_move = a2[0] - a1[0] if queries == "moved_last_scene" else a2[0]
    assert moves[:2] == [tuple(a1[0].tolist()), tuple(second_move.tolist())] and moves[2:] == moves[:2]
    logits = world(collate([seq], vocab.pad_id)).logits[0][seq.segment_ids < 0]
    picked = torch.cat([vocab.pick_scene(logits[:9]), vocab.pick_scene(logits[9:])]) - vocab.occ_start
    assert torch.equal(picked, torch.cat([first, second]))


def test_packed_sequences_train_as_they_would_alone(vocab):
    world = make_world(vocab, "next_scene")
    # The middle sequence holds two branches (instruct's packed questions): its branch ids
    # meet the other sequence's tokens in one row and must keep apart all the same.
    branched = prompt(world.builder())
    for q, a in [("go straight", "turn left then stop"), ("plan the route", "the car turns left")]:
        branched.branch().text(q).text(a, True)
    seqs = [full_sequence(world.builder()), branched.build(), full_sequence(world.builder())]
    rows = [[0, 1], [2]]
    with torch.no_grad():
        padded, packed = world(collate(seqs, vocab.pad_id)), world(collate(seqs, vocab.pad_id, rows))
    for name in ("loss", "text_loss", "scene_loss", "sample_loss"):
        torch.testing.assert_close(getattr(packed, name), getattr(padded, name), rtol=1e-5, atol=1e-6)
    assert collate(seqs, vocab.pad_id, rows)["input_ids"].shape[0] == 2  # two rows for three sequences


# -- OccLLaMA over the patches layout (model.occllama.patch_size)

PATCH_HW = (4, 4)
PRESENT = torch.tensor([3, 1, 4, 1, 5, 9, 2, 6, 5, 3, 5, 8, 9, 7, 9, 3])
FUTURE = torch.tensor([2, 7, 1, 8, 2, 8, 1, 8, 2, 8, 4, 5, 9, 0, 4, 5])


@pytest.fixture(scope="module")
def patch_vocab():
    return JointVocab(train_text_tokenizer(TEXTS, 300), 16, scene_hw=PATCH_HW, llm_cfg=CFG, patch=2)


class ShiftingCodes:
    """A scene mover over raw codes (the patches layout's) that records what it is asked
    and answers each cell's next code."""

    def __init__(self):
        self.asked = []

    def codes(self, codes, step):
        self.asked.append((codes.tolist(), step))
        return (codes + 1) % 16

    def __call__(self, code_ids, step):
        raise AssertionError("the patches layout moves raw codes, not ids")

    def labels(self, codes, step):
        return None


def make_patch_world(vocab, queries="moved_observed_scene", seed=0, copy_bias=4.0, mode="next_scene"):
    torch.manual_seed(seed)
    llm = build_llm(CFG, len(vocab))
    inputs = WorldInputs(scene=SimpleNamespace(codebooks=[torch.randn(16, 8)], latent_hw=PATCH_HW))
    cfg = OccLLaMAWorldConfig(queries, patch_size=2, copy_bias=copy_bias, cell_dim=8)
    world = OccWorldModel.create(llm, vocab, inputs, mode, cfg)
    world.scene_mover = ShiftingCodes()
    return world


def by_hand(codes: torch.Tensor) -> list:
    """The cells of a 4 x 4 scene's 2 x 2 patches: patch j covers rows 2(j // 2).. and
    columns 2(j % 2)..; its cells row-major, each with its one codebook's code."""
    g = codes.reshape(4, 4)
    rows = lambda j: (2 * (j // 2), 2 * (j // 2) + 1)  # noqa: E731
    cols = lambda j: (2 * (j % 2), 2 * (j % 2) + 1)  # noqa: E731
    return [[[int(g[r, c])] for r in rows(j) for c in cols(j)] for j in range(4)]


def test_patch_layout_queries_carry_the_moved_present_and_target_the_true_cells(patch_vocab):
    """``patch_size: 2`` over a 4 x 4 latent: a scene is 4 patch tokens; a predicted
    scene's query block carries the present moved by the ego's move since it (through the
    mover's raw codes) and targets the true cells, which the code block after it carries."""
    v = patch_vocab
    world = make_patch_world(v)
    seq = world.builder().scene(PRESENT).actions(XY[:1], True).scene(FUTURE, True).build()
    patches = list(range(v.occ_start, v.occ_start + 4))
    OPEN, CLOSE, ACT, END = v.occ_open_id, v.occ_close_id, v.act_open_id, v.act_close_id
    act = v.action_ids(XY[:1]).tolist()
    queries = v.query_ids().tolist()
    assert seq.input_ids.tolist() == [v.bos_id, OPEN, *patches, CLOSE, ACT, *act, END, OPEN, *queries, *patches, CLOSE]
    assert seq.segment_ids.tolist() == [0, 0] + [1] * 4 + [0] * 6 + [-2] * 4 + [2] * 4 + [0]
    q, block = seq.segment_ids < 0, seq.segment_ids == 2
    assert world.scene_mover.asked == [(PRESENT.tolist(), (2.0, -1.0))]
    assert seq.payload["cells"][q].tolist() == by_hand((PRESENT + 1) % 16)
    assert seq.payload["target"][q].tolist() == by_hand(FUTURE)
    assert seq.payload["cells"][block].tolist() == by_hand(FUTURE)
    assert seq.payload["cells"][seq.segment_ids == 1].tolist() == by_hand(PRESENT)
    assert bool((seq.payload["target"][~q] == IGNORE).all()) and seq.payload["carries"].tolist() == q.tolist()
    # The learned queries carry no scene: zero cells, nothing to copy.
    learned = make_patch_world(v, "learned").builder().scene(PRESENT).actions(XY[:1], True).scene(FUTURE, True).build()
    lq = learned.segment_ids < 0
    assert not bool(learned.payload["carries"].any()) and int(learned.payload["cells"][lq].abs().sum()) == 0
    assert learned.payload["target"][lq].tolist() == by_hand(FUTURE)


def test_patch_loss_is_finite_and_falls_under_adamw(patch_vocab):
    world = make_patch_world(patch_vocab).train()
    seqs = [
        world.builder().text("go straight").scene(PRESENT).actions(XY[:1], True).scene(FUTURE, True).build(),
        world.builder().scene(FUTURE).text("plan the route").actions(XY, True).scene(PRESENT, True).build(),
    ]
    batch = collate(seqs, patch_vocab.pad_id)
    opt = torch.optim.AdamW(world.parameters(), lr=3e-3)
    losses = []
    for _ in range(10):
        out = world(batch)
        losses.append(float(out.loss.detach()))
        assert torch.isfinite(out.scene_loss) and float(out.scene_loss.detach()) > 0
        opt.zero_grad()
        out.loss.backward()
        opt.step()
    assert all(torch.isfinite(torch.tensor(losses))) and losses[-1] < 0.7 * losses[0], losses
    assert world.copy_bias.grad is not None and float(world.copy_bias.grad.abs().sum()) > 0


@pytest.mark.parametrize("queries", ["moved_observed_scene", "moved_last_scene", "last_scene"])
def test_patch_generation_gives_the_queries_the_cells_training_gives(patch_vocab, queries):
    """Untrained, exact: generation asks the world model for each query block's payload
    with the context training lays out (the generated waypoints and scenes standing for
    the true ones), so the query cells are training's, and each generated scene is the
    training forward's pick at its query block (no copy bias: the picks follow the hidden
    states, which the fed query block decides); batched, the same."""
    from occtrain.core.decoding import ActionAnswer, SceneAnswer

    world = make_patch_world(patch_vocab, queries, seed=5, copy_bias=0.0).eval()
    seen = []
    ask = world.scene_query_payload
    world.scene_query_payload = lambda context: seen.append(ask(context)) or seen[-1]
    prompt_seq = world.builder().scene(FUTURE).scene(PRESENT).build()
    d = world.decoder(prompt_seq)
    a1, first, a2, second = d.actions(1), d.scene(), d.actions(1), d.scene()
    generated = torch.cat([p["cells"] for p in seen])
    seen.clear()
    seq = world.builder().scene(FUTURE).scene(PRESENT).actions(a1, True).scene(first, True)
    seq = seq.actions(a2, True).scene(second, True).build()
    q = seq.segment_ids < 0
    assert torch.equal(generated, seq.payload["cells"][q]) and bool(seq.payload["carries"][q].all())
    assert generated.abs().sum() > 0 and world.scene_mover.asked[:2] == world.scene_mover.asked[2:]
    with torch.no_grad():
        hidden = world(collate([seq], patch_vocab.pad_id), output_hidden_states=True).hidden[0][q]
        logits = world.patch_logits(hidden, {k: seq.payload[k][q] for k in ("cells", "carries")})
    picked = torch.stack([scores.argmax(-1) for scores in logits], -1)
    assert torch.equal(torch.cat([world.codes_of(picked[:4]), world.codes_of(picked[4:])]), torch.cat([first, second]))
    batched = world.generate_batch([prompt_seq], [[ActionAnswer(1), SceneAnswer(), ActionAnswer(1), SceneAnswer()]])
    for want, got in zip((a1, first, a2, second), batched[0]):
        assert torch.equal(want, got)


def test_the_copy_path_makes_an_untrained_model_write_its_queries_back(patch_vocab):
    """With a large ``copy_bias`` an untrained model forecasts its query block's scene (the
    moved present); without it, it does not; the learned queries carry nothing to copy."""

    def forecast(queries: str, copy_bias: float) -> torch.Tensor:
        world = make_patch_world(patch_vocab, queries, copy_bias=copy_bias).eval()
        d = world.decoder(world.builder().scene(FUTURE).scene(PRESENT).build())
        d.actions(1)
        return d.scene()

    moved = (PRESENT + 1) % 16
    assert torch.equal(forecast("moved_observed_scene", 50.0), moved)
    assert not torch.equal(forecast("moved_observed_scene", 0.0), moved)
    assert torch.equal(forecast("learned", 50.0), forecast("learned", 0.0))


@pytest.mark.parametrize("patch_size", [0, 5], ids=["codes", "patches"])
def test_an_engine_exports_loads_forecasts_plans_and_scores_in_either_layout(tmp_path, hand_dataset, patch_size):
    """Through the engine: the export loads back identical (class, settings, vocabulary,
    weights); forecasts decode through the scene encoder, plans come out, and the
    evaluator's forecast scorer runs, with moved queries moved through the frozen tokenizer."""
    from occtrain.core.tokenizer_exports import build_tokenizer, save_tokenizer
    from occtrain.data.layout import DatasetIndex
    from occtrain.engine import export_engine, load_world_model, new_world_model
    from occtrain.engine.evaluator import Evaluator, evaluation_clips
    from occtrain.engine.moved_scenes import MovedScenes
    from occtrain.families.occllama import TaskConfig
    from occtrain.families.occllama.world_model import OccLLaMAPatchWorldModel

    tiny = dict(num_codes=16, code_dim=8, class_embed_dim=4, base_channels=4, channel_mult=[1, 1, 1, 1],
                strides=[2, 2, 5], num_res_blocks=1, z_channels=8, latent_attention=False)  # fmt: skip
    torch.manual_seed(0)
    tok = save_tokenizer(build_tokenizer("occworld_vqvae", tiny).eval(), "occworld_vqvae", tiny, tmp_path / "tok")
    llm = LLMConfig(hidden_size=32, num_layers=1, num_heads=2, intermediate_size=64, text_vocab_size=300)
    cfg = OccLLaMAWorldConfig("moved_observed_scene", patch_size=patch_size, copy_bias=2.5, cell_dim=8)
    tasks = TaskConfig(weights={"forecasting": 1.0}, context_frames=2, forecast_frames=2)
    engine = new_world_model({"tokenizer": tok}, llm, tasks, hand_dataset, family="occllama", world_cfg=cfg)
    assert isinstance(engine.world, OccLLaMAPatchWorldModel) == bool(patch_size)
    assert engine.vocab.scene_len == (4 if patch_size else 100) and isinstance(engine.world.scene_mover, MovedScenes)
    loaded = load_world_model(export_engine(engine, tmp_path / "export", stage="pretrain")).eval()
    assert type(loaded.world) is type(engine.world) and loaded.vocab.to_json() == engine.vocab.to_json()
    assert loaded.world.export_config() == engine.world.export_config()
    assert loaded.world.export_config()["occllama"] == {
        "scene_queries": "moved_observed_scene",
        "patch_size": patch_size,
        "copy_bias": 2.5,
        "cell_dim": 8,
        "change_weight": 1.0,
        "mover_weight": 1.0,
    }
    saved, back = engine.world.state_dict(), loaded.world.state_dict()
    assert saved.keys() == back.keys()
    for name in saved:
        a, b = saved[name], back[name]
        if name.endswith("embed_tokens.weight") and not patch_size:
            # The codes layout's export writes its projected codebook into the scene tokens'
            # rows, for plain transformers; occtrain embeds them from the codebook.
            lo, hi = engine.vocab.occ_range
            a, b = torch.cat([a[:lo], a[hi:]]), torch.cat([b[:lo], b[hi:]])
        assert torch.equal(a, b), name

    loaded.prepare_inputs(hand_dataset)
    clip = evaluation_clips(DatasetIndex.open(hand_dataset), "val", "forecasting", 2)[0]
    assert loaded.operation("plan")(loaded, clip).shape[1] == 2
    evaluator = Evaluator(["forecasting"], loaded.task_specs, record=True)
    evaluator.run(loaded, hand_dataset, "val", samples=1)
    metrics = evaluator.compute("val")
    assert any(k.startswith("val/forecast_occworld") for k in metrics), sorted(metrics)
    # The forecast decoded through the scene encoder; its queries moved through the frozen tokenizer.
    (_, forecast), *_ = evaluator.predictions["forecast"].values()
    assert forecast.shape == (tasks.forecast_frames, 200, 200, 16) and loaded.world.scene_mover.computed > 0


def test_patch_size_must_divide_the_latent_grid():
    from occtrain.errors import ConfigError

    inputs = WorldInputs(scene=SimpleNamespace(latent_hw=(10, 10)))
    OccLLaMAWorldConfig(patch_size=5).validate("model.occllama", inputs)
    OccLLaMAWorldConfig(patch_size=0).validate("model.occllama", inputs)
    for bad in (3, -1):
        with pytest.raises(ConfigError, match=rf"^model\.occllama\.patch_size: {bad} must"):
            OccLLaMAWorldConfig(patch_size=bad).validate("model.occllama", inputs)
    with pytest.raises(ConfigError, match=r"^model\.occllama\.copy_bias"):
        OccLLaMAWorldConfig(copy_bias=float("nan")).validate("model.occllama", inputs)


def test_cell_weights_need_the_patch_head():
    """The codes layout's loss is the LLM's own cross-entropy: a cell weight there would be
    silently ignored, so the key is refused."""
    from occtrain.errors import ConfigError

    inputs = WorldInputs(scene=SimpleNamespace(latent_hw=(10, 10)))
    OccLLaMAWorldConfig(patch_size=5, mover_weight=4.0, change_weight=2.0).validate("model.occllama", inputs)
    for key in ("change_weight", "mover_weight"):
        with pytest.raises(ConfigError, match=rf"^model\.occllama\.{key}: weighs the patch head's cells"):
            OccLLaMAWorldConfig(patch_size=0, **{key: 4.0}).validate("model.occllama", inputs)
