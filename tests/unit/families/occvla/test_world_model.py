"""OccVLA: the occupancy query block's visibility and positions, greedy generations with
and without it, gradients through the frozen OccWorld decoder, bottleneck adapters saved
and loaded, the meta-action labeller and accuracy on hand cases, and the prompts."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from occtrain.config.llm import LLMConfig
from occtrain.core.builder import collate
from occtrain.core.decoding import TextAnswer
from occtrain.core.tokenizer_exports import build_tokenizer
from occtrain.core.vocab import JointVocab
from occtrain.data.clips import Clip, Text
from occtrain.data.meta_actions import KMH_PER_S, MetaActionConfig, label, past_labels
from occtrain.errors import ConfigError
from occtrain.families.occvla import OccVLAWorldConfig, OccVLAWorldModel
from occtrain.families.occvla.config import TaskConfig
from occtrain.families.occvla.parts import Images, Occupancy
from occtrain.families.occvla.tasks import META_PROMPT, META_QUESTION, meta_action
from occtrain.formats.occ3d import GRID_SHAPE
from occtrain.metrics import MetaActionAccuracy
from occtrain.models.adapters import AdapterConfig, add_adapters, load_adapters, save_adapters, without_adapters
from occtrain.models.llm import build_llm
from occtrain.models.text_tokenizer import train_text_tokenizer

TEXTS = [
    "Past meta actions: maintain speed, go straight. What is the next meta action?",
    "Meta action: decelerate, turn left.",
]
VISION_DIM = 8
IMAGES = 6


def tokenizer_model():
    cfg = OmegaConf.to_container(OmegaConf.load("configs/model/occworld_vqvae_tiny.yaml"))["occworld_vqvae"]
    return build_tokenizer("occworld_vqvae", cfg).eval().requires_grad_(False)


def llm_cfg() -> LLMConfig:
    return LLMConfig(
        hidden_size=32,
        num_layers=2,
        num_heads=2,
        intermediate_size=64,
        action_bins=4,
        action_range=[[-10.0, 10.0], [-10.0, 10.0]],
    )


def world(seed: int = 0, query_patch: int = 2) -> OccVLAWorldModel:
    torch.manual_seed(seed)
    scene_tok = tokenizer_model()
    vocab = JointVocab(
        train_text_tokenizer(TEXTS, 300),
        scene_tok.codebook_sizes,
        tuple(scene_tok.latent_hw),
        llm_cfg(),
        patch=query_patch,
        image=True,
    )
    cfg = OccVLAWorldConfig(query_patch=query_patch, projector_hidden=16)
    return OccVLAWorldModel(build_llm(llm_cfg(), len(vocab)), vocab, scene_tok, VISION_DIM, cfg).eval()


def features(seed: int) -> torch.Tensor:
    return torch.randn(IMAGES, VISION_DIM, generator=torch.Generator().manual_seed(seed))


def voxels(seed: int) -> torch.Tensor:
    return torch.randint(0, 18, GRID_SHAPE, generator=torch.Generator().manual_seed(seed)).to(torch.uint8)


def sequence(w: OccVLAWorldModel, with_queries: bool, answer: bool = True):
    b = w.builder().images(features(1))
    if with_queries:
        b.occupancy(voxels(2), 1.0)
    b.text("Past meta actions: maintain speed, go straight.")
    if answer:
        b.text("Meta action: decelerate, turn left.", True)
    return b.build()


def test_text_never_sees_the_queries_which_see_the_images_and_keep_the_text_positions():
    w = world()
    seq = sequence(w, with_queries=True)
    batch = collate([seq], w.vocab.pad_id)
    allowed = batch["attention_mask"][0, 0]
    ids = batch["input_ids"][0]
    queries = w.vocab.is_query(ids)
    images = w.vocab.is_image(ids)
    text = ~queries & ~images
    assert queries.sum() == w.vocab.scene_len == 25 and images.sum() == IMAGES
    assert not allowed[text][:, queries].any()  # text never attends to a query
    assert allowed[queries][:, images].all()  # every query sees every image token
    assert allowed[queries][:, queries].all()  # and the whole query block
    later_text = text & (torch.arange(len(ids)) > int(queries.nonzero().max()))
    assert not allowed[queries][:, later_text].any()  # nor anything after it
    plain = sequence(w, with_queries=False)
    # The queries take no positions of their own: every other token keeps its position.
    assert torch.equal(seq.position_ids[~queries], plain.position_ids)
    assert torch.equal(seq.input_ids[~queries], plain.input_ids)
    # And so the text's outputs are the same with or without the block.
    with torch.no_grad():
        a = w(batch).logits[0][~queries]
        b = w(collate([plain], w.vocab.pad_id)).logits[0]
    torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_greedy_generations_are_identical_with_and_without_the_occupancy_block():
    w = world(seed=3)
    prompt = sequence(w, with_queries=False, answer=False)
    answers = [TextAnswer(12)]
    skipped, none = w.generate_with_occupancy(prompt, answers, occupancy=False)
    with_occ, logits = w.generate_with_occupancy(prompt, answers, occupancy=True)
    assert none is None and logits.shape == (1, 18, *GRID_SHAPE)
    assert skipped == with_occ and len(skipped[0]) > 0
    assert w.generate_batch([prompt, prompt], [answers, answers]) == [skipped, skipped]
    # The query branch at inference equals the one training reads (teacher forcing).
    batch = collate([sequence(w, with_queries=True, answer=False)], w.vocab.pad_id)
    with torch.no_grad():
        out = w._run(
            batch["input_ids"],
            batch["attention_mask"],
            batch["position_ids"],
            hidden=True,
            payload={"image": batch["payload_image"]},
        )
    hidden = out.hidden_states[-1][0][w.vocab.is_query(batch["input_ids"][0])]
    torch.testing.assert_close(w.occupancy_logits(hidden[None]), logits, rtol=1e-4, atol=1e-4)


def test_gradients_reach_the_projector_through_the_decoder_which_stays_unchanged():
    w = world().train()
    decoder_before = {k: v.clone() for k, v in w.decoder_model.state_dict().items()}
    batch = collate([sequence(w, with_queries=True)], w.vocab.pad_id)
    out = w(batch)
    assert out.scene_loss > 0 and out.loss > out.text_loss
    out.loss.backward()
    assert w.occ_proj.weight.grad is not None and w.occ_proj.weight.grad.abs().sum() > 0
    assert w.occ_queries.grad.abs().sum() > 0
    assert w.llm.get_input_embeddings().weight.grad.abs().sum() > 0  # through the shared LLM weights
    assert all(p.grad is None for p in w.decoder_model.parameters())
    proj_before = w.occ_proj.weight.detach().clone()
    torch.optim.AdamW([p for p in w.parameters() if p.requires_grad], lr=1e-2).step()
    assert not torch.equal(w.occ_proj.weight, proj_before)
    for k, v in w.decoder_model.state_dict().items():
        assert torch.equal(v, decoder_before[k]), k


def test_the_loss_is_text_plus_lambda_times_the_voxel_cross_entropy():
    w = world()
    weighted = w.builder().images(features(1)).occupancy(voxels(2), 2.0).text("go", True).build()
    with torch.no_grad():
        out = w(collate([weighted], w.vocab.pad_id))
    assert out.loss.item() == pytest.approx(out.text_loss.item() + 2.0 * out.scene_loss.item(), rel=1e-5)
    # A fresh decoder's voxel CE is near log(18) for near-uniform logits, never zero.
    assert 0.5 < out.scene_loss.item() < 3 * math.log(18)


def test_a_stage_that_gives_occupancy_no_weight_freezes_that_branch_alone():
    """``unused_parameters``: the occupancy queries and projector when ``occupancy_weight``
    is 0 (no loss reaches them, so DDP must not wait for their gradients), nothing
    otherwise, and nothing for the base world model's other task settings."""
    from occtrain.core.shared_tasks import TaskConfig as BaseTaskConfig

    w = world()
    frozen = {id(p) for p in w.unused_parameters(TaskConfig(occupancy_weight=0.0))}
    assert frozen == {id(p) for p in [w.occ_queries, *w.occ_proj.parameters()]}
    assert w.unused_parameters(TaskConfig()) == []
    assert w.unused_parameters(BaseTaskConfig()) == []


def test_bottleneck_adapters_round_trip_through_safetensors_and_json(tmp_path):
    torch.manual_seed(0)
    llm = build_llm(llm_cfg(), 50)
    base_state = {k: v.clone() for k, v in llm.state_dict().items()}
    ids = torch.randint(0, 50, (1, 9))
    with torch.no_grad():
        plain = llm(ids).logits
    adapters = add_adapters(llm, AdapterConfig(reduction_factor=4))
    assert len(adapters) == 2
    with torch.no_grad():
        torch.testing.assert_close(llm(ids).logits, plain)  # zero-initialised: identity at the start
        for a in adapters:
            a.up.weight.normal_()
        adapted = llm(ids).logits
    assert not torch.allclose(adapted, plain)
    out = save_adapters(llm, tmp_path / "adapter")
    assert {p.name for p in out.iterdir()} == {"adapter.safetensors", "adapter_config.json"}
    assert without_adapters(llm.state_dict()).keys() == base_state.keys()
    fresh = build_llm(llm_cfg(), 50)
    fresh.load_state_dict(base_state)
    cfg = load_adapters(fresh, out)
    assert cfg.reduction_factor == 4
    with torch.no_grad():
        torch.testing.assert_close(fresh(ids).logits, adapted)


def _poses(speeds: list[float], yaw_rate_deg: float = 0.0, lateral: float = 0.0) -> np.ndarray:
    """Global poses at 0.5 s steps: the given speed over each step, a constant yaw rate,
    and an optional sideways shift spread over the last 6 steps."""
    x = y = yaw = 0.0
    out = [(x, y, yaw)]
    for k, v in enumerate(speeds):
        yaw += math.radians(yaw_rate_deg) * 0.5
        x += v * 0.5 * math.cos(yaw)
        y += v * 0.5 * math.sin(yaw)
        if k >= len(speeds) - 6:
            y += lateral / 6
        out.append((x, y, yaw))
    return np.asarray(out)


def test_the_meta_action_labeller_on_hand_made_trajectories():
    cfg = MetaActionConfig()  # the paper's: +-1 km/h/s at the current step
    steady = _poses([10.0] * 10)
    assert label(steady, 2, cfg) == {"speed": "maintain", "direction": "straight"}
    # 10 -> 10.5 m/s over one 0.5 s step: 1 m/s^2 = 3.6 km/h/s, above the threshold.
    assert label(_poses([10.0] * 2 + [10.5] * 8), 2, cfg)["speed"] == "accelerate"
    assert label(_poses([10.0] * 2 + [9.5] * 8), 2, cfg)["speed"] == "decelerate"
    # 0.06 m/s per step: 0.12 m/s^2 = 0.43 km/h/s, below it; above a 0.3 km/h/s threshold.
    gentle = _poses([10.0] * 2 + [10.06] * 8)
    assert label(gentle, 2, cfg)["speed"] == "maintain"
    assert label(gentle, 2, MetaActionConfig(accel_threshold_kmh_s=0.3))["speed"] == "accelerate"
    assert 0.12 / KMH_PER_S == pytest.approx(0.432)
    assert label(_poses([8.0] * 10, yaw_rate_deg=20.0), 2, cfg)["direction"] == "left"  # 60 degrees in 3 s
    assert label(_poses([8.0] * 10, yaw_rate_deg=-20.0), 2, cfg)["direction"] == "right"
    assert label(_poses([8.0] * 10, yaw_rate_deg=4.0), 2, cfg)["direction"] == "bear left"  # 12 degrees
    assert label(_poses([8.0] * 8, lateral=-2.0), 2, cfg)["direction"] == "bear right"  # a lane change to the right
    assert label(_poses([0.0] * 10), 2, cfg) == {"speed": "maintain", "direction": "stop"}
    assert label(steady, 0, cfg) is None  # no step before frame 0 to read the acceleration from


def test_past_meta_actions_read_nothing_after_the_anchor():
    cfg = MetaActionConfig()
    a = 6
    straight = _poses([10.0] * 12)
    turning = straight.copy()
    turning[a + 1 :] = _poses([10.0] * 12, yaw_rate_deg=25.0)[a + 1 :]
    assert past_labels(straight, a, 5, cfg) == past_labels(turning, a, 5, cfg)
    assert len(past_labels(straight, a, 5, cfg)) == 5 and len(past_labels(straight, 3, 5, cfg)) == 2
    assert label(straight, a, cfg) != label(turning, a, cfg)  # the future one does see the turn


def test_meta_action_accuracy_by_hand():
    m = MetaActionAccuracy()
    ref = {"speed": "maintain", "direction": "straight"}
    m.update(
        [ref, {"speed": "maintain", "direction": "left"}, {"speed": "accelerate", "direction": "straight"}, None],
        [ref, ref, ref, ref],
    )
    r = m.compute()
    assert (r["speed"], r["direction"], r["overall"], r["samples"]) == (50.0, 50.0, 25.0, 4)
    assert r["mean"] == 50.0


def test_the_prompt_lists_past_meta_actions_and_the_answer_reasons_first():
    poses = _poses([10.0] * 6 + [9.0] * 7)  # the step after the anchor (frame 6) slows by 1 m/s
    clip = Clip(
        {"anchor": {"token": "tok", "caption": "A straight road."}, "ego_poses": poses.tolist(), "history": 6}, [], ""
    )
    parts = meta_action(clip, TaskConfig(), np.random.default_rng(0))
    assert isinstance(parts[0], Images) and isinstance(parts[1], Occupancy) and parts[1].weight == 1.0
    assert parts[2].text == f"{META_PROMPT} " + "; ".join(["maintain speed, go straight"] * 5) + f". {META_QUESTION}"
    answer = parts[3]
    assert isinstance(answer, Text) and answer.supervise
    assert answer.text.startswith(
        "Scene: A straight road. History: over the last 2.5 s the ego mostly kept its speed and went straight"
    )
    assert answer.text.endswith("Meta action: decelerate, go straight.")
    short = meta_action(clip, TaskConfig(chain_of_thought=False, occupancy_weight=0.0), np.random.default_rng(0))
    assert [type(p) for p in short] == [Images, Text, Text] and short[
        -1
    ].text == "Meta action: decelerate, go straight."


def test_the_chain_of_thought_does_not_state_the_answer_in_its_scene_step():
    """The synthetic caption opens with the ego's motion over the next seconds, which is the
    meta action itself; the default scene step leaves it out, "caption" keeps it."""
    poses = _poses([10.0] * 6 + [9.0] * 7)
    caption = (
        "The ego car is driving straight at 10 m/s and slowing down, with a moving car nearby. A cone is also around."
    )
    clip = Clip({"anchor": {"token": "tok", "caption": caption}, "ego_poses": poses.tolist(), "history": 6}, [], "")
    answer = meta_action(clip, TaskConfig(occupancy_weight=0.0), np.random.default_rng(0))[-1].text
    assert answer.startswith("Scene: Nearby: a moving car. A cone is also around. History:")
    assert "slowing down" not in answer
    whole = meta_action(clip, TaskConfig(occupancy_weight=0.0, cot_scene="caption"), np.random.default_rng(0))[-1].text
    assert whole.startswith(f"Scene: {caption} History:")
    with pytest.raises(ConfigError, match=r"tasks.cot_scene: 'narration' is not one of surroundings, caption"):
        TaskConfig(cot_scene="narration").validate("tasks")


def test_the_repeat_last_prior_writes_an_unchanged_meta_action_as_before():
    """tasks.meta_action_prior: repeat_last: the answer says "as before" when the future
    meta action equals the last past one (the prompt's last entry), its words otherwise;
    reading it back gives the same meta action either way."""
    from occtrain.core.scorers import last_past_meta_action
    from occtrain.families.occvla.tasks import past_meta_actions, read_meta_action

    cfg = TaskConfig(occupancy_weight=0.0, meta_action_prior="repeat_last")
    steady = Clip({"anchor": {"token": "t"}, "ego_poses": _poses([10.0] * 13).tolist(), "history": 6}, [], "")
    slowing = Clip(
        {"anchor": {"token": "t"}, "ego_poses": _poses([10.0] * 6 + [9.0] * 7).tolist(), "history": 6}, [], ""
    )
    for clip, sentence, meta in (
        (steady, "Meta action: as before.", {"speed": "maintain", "direction": "straight"}),
        (slowing, "Meta action: decelerate, go straight.", {"speed": "decelerate", "direction": "straight"}),
    ):
        answer = meta_action(clip, cfg, np.random.default_rng(0))[-1].text
        assert answer.endswith(sentence) and read_meta_action(answer, clip, cfg) == meta
        # The last past meta action the scorer repeats is the prompt's last entry.
        assert last_past_meta_action(clip, cfg.meta_actions) == past_meta_actions(clip, cfg)[-1]
    # The paper's form by default.
    assert meta_action(steady, TaskConfig(occupancy_weight=0.0), np.random.default_rng(0))[-1].text.endswith(
        "Meta action: maintain speed, go straight."
    )
    with pytest.raises(
        ConfigError, match=r"tasks.meta_action_prior: 'always' is not one of none, repeat_last \(paper: none\)"
    ):
        TaskConfig(meta_action_prior="always").validate("tasks")
