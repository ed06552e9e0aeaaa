"""OccLLaMA's task builders on clips of a synthesized world."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from occtrain.core.shared_tasks import sample_task, validate_tasks
from occtrain.data.clips import Actions, Clip, Scene, Text, ego_future
from occtrain.data.shards import decode_sample, iter_raw, shard_urls, write_shards
from occtrain.data.text_formats import parse_meta_action
from occtrain.errors import ConfigError
from occtrain.families.occllama.tasks import OBJECT_CLASSES, TASKS, TaskConfig
from occtrain.formats.occ3d import CLASS_INDEX


@pytest.fixture(scope="module")
def clips(synth_dataset, tmp_path_factory) -> list[Clip]:
    out = tmp_path_factory.mktemp("shards")
    write_shards(synth_dataset, out, 64, history=2, future=6, kinds=("clips",))
    urls, _ = shard_urls(out, "clips", "train")
    samples = [decode_sample(s) for s in iter_raw(urls[0])]
    return [Clip(s["ann.json"], s["qa.json"], s["narration.txt"]) for s in samples]


def test_object_classes_are_occ3d_names():
    assert all(c in CLASS_INDEX for c in OBJECT_CLASSES)


def test_ego_steps_recover_the_pose_differences(clips):
    # A turning ego (a step taken in the wrong frame, the next pose's yaw or the global
    # axes, differs here), and the synthetic clips.
    turning = Clip(
        {"ego_poses": [[10.0, 5.0, 0.0], [14.0, 5.5, 0.4], [17.0, 8.0, 0.9], [18.5, 12.0, 1.4]], "history": 1}, [], ""
    )
    np.testing.assert_allclose(turning.ego_steps()[0], [4.0, 0.5])
    np.testing.assert_allclose(
        turning.ego_steps()[1], [np.cos(0.4) * 3 + np.sin(0.4) * 2.5, -np.sin(0.4) * 3 + np.cos(0.4) * 2.5]
    )
    for clip in (turning, clips[0]):
        _check_steps(clip)


def _check_steps(clip: Clip) -> None:
    poses = np.asarray(clip.ann["ego_poses"])
    steps = clip.ego_steps()
    assert steps.shape == (len(poses) - 1, 2)
    for k in range(len(steps)):
        (dx, dy), yaw = poses[k + 1, :2] - poses[k, :2], poses[k, 2]  # pose k -> k + 1 in pose k's frame
        np.testing.assert_allclose(
            steps[k], [np.cos(yaw) * dx + np.sin(yaw) * dy, -np.sin(yaw) * dx + np.cos(yaw) * dy], atol=1e-6
        )
    # The ego drives forwards: each step's x is non-negative and at most a fast car's 0.5 s.
    assert (steps[:, 0] > -0.05).all() and (steps[:, 0] < 12).all()


def test_every_task_builds_prompt_then_answer(clips):
    cfg = TaskConfig(context_frames=2, forecast_frames=3)
    rng = np.random.default_rng(0)
    built = {name: [p for c in clips if (p := fn.build(c, cfg, rng)) is not None] for name, fn in TASKS.items()}
    for name, outputs in built.items():
        assert outputs, f"task {name} never applies to the synthetic clips"
        for parts in outputs:
            first_answer = next(i for i, p in enumerate(parts) if p.supervise)
            # The prompt starts with the context scenes, is not supervised, and ends before
            # the first answer part; the answer is supervised to its end.
            assert isinstance(parts[0], Scene) and first_answer > 0
            assert not any(p.supervise for p in parts[:first_answer]), name
            assert all(p.supervise for p in parts[first_answer:]), name


def test_forecasting_alternates_waypoints_and_future_scenes(clips):
    clip = clips[0]
    parts = TASKS["forecasting"].build(clip, TaskConfig(context_frames=2, forecast_frames=3), np.random.default_rng(0))
    answer = [p for p in parts if p.supervise]
    assert [type(p) for p in answer] == [Actions, Scene] * 3
    assert [p.frame for p in answer if isinstance(p, Scene)] == [3, 4, 5]  # anchor is clip frame 2
    np.testing.assert_allclose(answer[0].xy, [clip.anchor["ego_future"][0]])
    context_scenes = [p.frame for p in parts if isinstance(p, Scene) and not p.supervise]
    assert context_scenes == [0, 1, 2]


def test_counting_answer_matches_the_boxes(clips):
    counted = []
    for clip in clips:
        for seed in range(12):  # each draw picks an object class
            parts = TASKS["counting"].build(clip, TaskConfig(), np.random.default_rng(seed))
            question, answer = parts[-2].text, parts[-1].text
            noun = question.removeprefix("Task: count the ").removesuffix(" objects.").replace(" ", "_")
            assert noun in OBJECT_CLASSES
            assert int(answer) == sum(b["category"] == noun for b in clip.anchor["boxes"])
            counted.append(int(answer))
    assert sum(n > 0 for n in counted) >= 5 and max(counted) >= 2  # counts, not only zeros


def test_sampling_is_deterministic_and_follows_weights(clips):
    cfg = TaskConfig(weights={"planning": 1.0, "qa": 0.0})
    drawn = [sample_task(c, cfg, 0, c.anchor["token"], TASKS) for c in clips]
    assert {d[0] for d in drawn if d} == {"planning"}
    # A clip no configured task applies to is skipped (None), never given a made-up task.
    assert [d is None for d in drawn] == [not ego_future(c.anchor)[1].all() for c in clips]
    cfg = TaskConfig(weights={"counting": 1.0, "detection": 1.0})
    a = [sample_task(c, cfg, 7, c.anchor["token"], TASKS)[0] for c in clips]
    b = [sample_task(c, cfg, 7, c.anchor["token"], TASKS)[0] for c in clips]
    assert a == b and set(a) == {"counting", "detection"}
    # Drawn in proportion to the weights (both apply to every clip): 9 to 1.
    cfg = TaskConfig(weights={"counting": 9.0, "detection": 1.0})
    draws = [sample_task(c, cfg, seed, c.anchor["token"], TASKS)[0] for c in clips for seed in range(40)]
    assert 0.85 < draws.count("counting") / len(draws) < 0.95, draws.count("counting") / len(draws)


def test_cot_answer_ends_with_the_meta_action_then_trajectory(clips):
    parts = TASKS["cot_planning"].build(clips[0], TaskConfig(), np.random.default_rng(0))
    text, traj = parts[-2], parts[-1]
    assert isinstance(text, Text) and text.supervise
    assert parse_meta_action(text.text) == clips[0].anchor["meta_action"]
    assert isinstance(traj, Actions) and len(traj.xy) == 6


def test_the_repeat_last_prior_states_the_last_meta_action_and_says_as_before(clips):
    """tasks.meta_action_prior: repeat_last: the prompt names the last past meta action and
    the chain of thought ends "as before" exactly when the frame's equals it; read back
    through the clip, the answer is the frame's meta action either way."""
    from occtrain.core.scorers import last_past_meta_action, said_meta_action

    cfg = TaskConfig(meta_action_prior="repeat_last")
    kinds = set()
    for clip in clips:
        parts = TASKS["cot_planning"].build(clip, cfg, np.random.default_rng(0))
        if parts is None:
            continue
        last, meta = last_past_meta_action(clip), clip.anchor["meta_action"]
        prompt = [p.text for p in parts if isinstance(p, Text) and not p.supervise]
        assert sum(t.startswith("Last meta action: ") for t in prompt) == 1
        answer = parts[-2].text
        assert answer.endswith("Meta action: as before.") == (last is not None and dict(last) == dict(meta))
        assert answer.count("Meta action:") == 1  # the narration's own line is replaced, not kept
        assert said_meta_action(answer, clip) == meta
        kinds.add(answer.endswith("as before."))
    assert kinds == {True, False}  # both cases occur in this world
    with pytest.raises(
        ConfigError, match=r"tasks.meta_action_prior: 'always' is not one of none, repeat_last \(paper: none\)"
    ):
        TaskConfig(meta_action_prior="always").validate("tasks")


def test_bad_task_names_are_one_line_errors():
    with pytest.raises(ConfigError, match="unknown task 'planing'"):
        validate_tasks(TaskConfig(weights={"planing": 1.0}), "stages[1].model.tasks", TASKS)
    with pytest.raises(ConfigError, match="no task has a positive weight"):
        validate_tasks(TaskConfig(weights={"planning": 0.0}), "stages[1].model.tasks", TASKS)


def test_missing_sidecar_fields_are_left_out_of_the_prompt(clips):
    """Real Occ3D data without occtrain's sidecar has no command or speed: the prompt says
    nothing about them instead of inventing "go straight" at 0 m/s."""
    cfg = TaskConfig(context_frames=2)
    anchor = {k: v for k, v in clips[0].anchor.items() if k not in ("command", "ego_speed")}
    bare = Clip({**clips[0].ann, "anchor": anchor}, clips[0].qa, clips[0].narration)
    texts = [p.text for p in TASKS["planning"].build(bare, cfg, np.random.default_rng(0)) if isinstance(p, Text)]
    assert not any("Command" in t or "Ego speed" in t for t in texts)
    full = [p.text for p in TASKS["planning"].build(clips[0], cfg, np.random.default_rng(0)) if isinstance(p, Text)]
    assert any(t.startswith(f"Command: {clips[0].anchor['command']}. Ego speed") for t in full)


def test_packed_questions_are_branches_of_distinct_questions(clips):
    from occtrain.data.clips import Branch, clip_rng
    from occtrain.families.occllama.tasks import every_question, qa

    clip = next(c for c in clips if len(c.qa) >= 3)
    parts = qa(clip, TaskConfig(questions_per_sample=3), clip_rng(0, clip.anchor["token"]))
    first = parts.index(Branch())
    assert not any(p.supervise for p in parts[:first])  # the shared context is prompt only
    branches = [parts[i + 1 : i + 3] for i, p in enumerate(parts) if isinstance(p, Branch)]
    assert len(branches) == 3 and len({b[0].text for b in branches}) == 3
    asked = {q["question"]: q["answer"] for q in clip.qa}
    for question, answer in branches:
        assert (
            asked[question.text.removeprefix("Question: ").removesuffix(" Answer:")] == answer.text and answer.supervise
        )
    # One question per sample (the paper's setting) has no branch; evaluation asks them all.
    assert not any(isinstance(p, Branch) for p in qa(clip, TaskConfig(), clip_rng(0, "x")))
    every = every_question(clip, TaskConfig())
    assert [p[-1].text for p in every] == [q["answer"] for q in clip.qa]
    with pytest.raises(ConfigError, match="questions_per_sample"):
        validate_tasks(TaskConfig(weights={"qa": 1}, questions_per_sample=0), "stages 'x'.model.tasks", TASKS)


def test_a_packed_draw_generates_one_question_at_a_time(clips):
    """Generation asks a packed draw's questions one by one, each as its own prompt: one
    decoder cannot keep branches apart, and generated as one sequence every later question
    became text to generate and every Branch a scene (the QA benchmark's 40x)."""
    from occtrain.core.shared_tasks import unpacked
    from occtrain.data.clips import Branch, clip_rng
    from occtrain.engine.world_engine import WorldModelEngine
    from occtrain.families.occllama.tasks import qa

    clip = next(c for c in clips if len(c.qa) >= 3)
    rng = lambda: clip_rng(0, clip.anchor["token"])  # noqa: E731
    packed = qa(clip, TaskConfig(questions_per_sample=3), rng())
    prompts = unpacked(packed)
    trunk = packed[: packed.index(Branch())]
    assert len(prompts) == 3 and len({p[-2].text for p in prompts}) == 3
    for p in prompts:  # the context, one question, its answer: the only supervised part, last
        assert (
            p[: len(trunk)] == trunk and len(p) == len(trunk) + 2 and [q.supervise for q in p].index(True) == len(p) - 1
        )
    assert unpacked(qa(clip, TaskConfig(), rng())) == [qa(clip, TaskConfig(), rng())]
    engine = SimpleNamespace(task_specs=TASKS, tasks=TaskConfig(questions_per_sample=3))
    assert WorldModelEngine.task_items(engine, "qa", clip) == prompts
    with pytest.raises(ValueError, match="one branch at a time"):
        WorldModelEngine.prompt_and_plan(engine, packed, {})


def test_frame_clips_cover_every_frame_with_its_questions(synth_dataset):
    from occtrain.data.clips import frame_clips
    from occtrain.data.layout import DatasetIndex
    from occtrain.engine.evaluator import evaluation_clips, fixed_subset

    index = DatasetIndex.open(synth_dataset)
    clips = list(frame_clips(index, "val", history=2))
    tokens = [t for _, t in index.samples("val")]
    assert [c.anchor["token"] for c in clips] == tokens
    assert [c.anchor_index for c in clips[:4]] == [0, 1, 2, 2]  # shorter history at the scene's start
    assert sum(len(c.qa) for c in clips) == len(index.questions("val"))
    # Plans and chains of thought: every frame with a whole 3 s future.
    planned = evaluation_clips(index, "val", "planning", 2)
    assert [c.anchor["token"] for c in planned] == tokens[2 : len(tokens) - 6]
    keys = [f"k{i}" for i in range(100)]
    chosen = fixed_subset(keys, 10, seed=0)
    assert len(chosen) == 10 and chosen == fixed_subset(list(reversed(keys)), 10, seed=0)
    assert chosen != fixed_subset(keys, 10, seed=1) and fixed_subset(keys, -1) == set(keys)


def test_a_constant_velocity_prior_writes_the_plan_as_offsets_and_reads_it_back(clips):
    import torch

    from occtrain.core.builder import SequenceBuilder
    from occtrain.core.decoding import ActionAnswer
    from occtrain.models.planning_heads import constant_velocity

    clip = next(c for c in clips if TASKS["planning"].build(c, TaskConfig(context_frames=2), np.random.default_rng(0)))
    cv = constant_velocity([clip.anchor])[0].numpy()
    paper = TASKS["planning"].build(clip, TaskConfig(context_frames=2), np.random.default_rng(0))[-1]
    prior = TASKS["planning"].build(
        clip, TaskConfig(context_frames=2, plan_prior="constant_velocity"), np.random.default_rng(0)
    )[-1]
    assert paper.base is None and paper.xy == prior.xy
    np.testing.assert_allclose(prior.base, cv, atol=1e-6)
    forecast = TASKS["forecasting"].build(
        clip, TaskConfig(context_frames=2, forecast_frames=3, plan_prior="constant_velocity"), np.random.default_rng(0)
    )
    np.testing.assert_allclose(
        [p.base[0] for p in forecast if isinstance(p, Actions) and p.supervise], cv[:3], atol=1e-6
    )
    with pytest.raises(ConfigError, match="tasks.plan_prior"):
        TaskConfig(plan_prior="cv").validate("tasks")
    # The builder writes xy - base; generation reads the bins back and adds the base again.
    from occtrain.core.vocab import JointVocab
    from occtrain.models.text_tokenizer import train_text_tokenizer

    vocab = JointVocab(train_text_tokenizer(["plan the ego trajectory"] * 10, 300), 4, (1, 1))
    builder = SequenceBuilder(vocab)
    builder.lay(prior, None, {})
    offsets = torch.tensor(prior.xy, dtype=torch.float32) - torch.tensor(prior.base, dtype=torch.float32)
    ids = builder.build().input_ids.tolist()
    assert ids[1:] == [vocab.act_open_id, *vocab.action_ids(offsets).tolist(), vocab.act_close_id]  # after bos
    assert ActionAnswer(6, prior.base).base == prior.base
