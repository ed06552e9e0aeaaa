"""A stage behind the wheel: the per-frame closed-loop planner and the batched open-loop one see the same clips."""

from __future__ import annotations

import copy
from types import SimpleNamespace

import numpy as np
import pytest

from occtrain.core.protocols import Plans
from occtrain.data.clips import Clip
from occtrain.data.closed_loop_recording import DrivingWorld, EpisodeRecorder
from occtrain.engine.closed_loop import NonFinitePlan, OpenLoopPlanner, StageDriver, model_planner, planners
from occtrain.engine.closed_loop.episodes import drive_episode, shadow_episode

HISTORY = 2


class _Encoders:
    """The engine's side of the seam: what ``add_samples`` was given, and the prompts' history."""

    def __init__(self):
        self.tasks = SimpleNamespace(context_frames=HISTORY)
        self.cached: set[str] = set()

    def add_samples(self, index, samples):
        assert all(token in index.scenes[scene] for scene, token in samples)
        self.cached.update(token for _, token in samples)


def _driver(fall_back_every: int = 0, nan_at: int = -1) -> StageDriver:
    """A stage whose every ``fall_back_every``-th plan is its constant-velocity fallback and
    whose plan at recorded frame ``nan_at`` is NaN."""
    engine = _Encoders()
    asked = []

    def waypoints(clips: list[Clip]) -> Plans:
        # A plan that reads everything the clip holds: the frames it names must be encoded,
        # and its history's poses and its anchor's speed decide the answer.
        out = []
        for clip in clips:
            known = clip.ann["tokens"][: clip.ann["history"] + 1]
            assert set(known) <= engine.cached, "a clip read a frame nobody encoded"
            poses = np.asarray(clip.ann["ego_poses"], dtype=np.float64)
            out.append(poses[-6:, :2] - poses[0, :2] + clip.anchor["ego_speed"])
            asked.append(clip.anchor["token"])
        plans = Plans.own(np.stack(out))
        if fall_back_every:
            plans.fell_back[:] = [(len(asked) - len(clips) + i + 1) % fall_back_every == 0 for i in range(len(clips))]
        if nan_at >= 0 and len(asked) - len(clips) <= nan_at - HISTORY < len(asked):
            plans.xy[nan_at - HISTORY - (len(asked) - len(clips))] = np.nan
        return plans

    return StageDriver(engine, waypoints)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def built() -> DrivingWorld:
    return DrivingWorld(101, 6.0)


def test_the_batched_open_loop_plans_what_planning_frame_by_frame_would(built, tmp_path, monkeypatch):
    monkeypatch.setattr(planners, "CHUNK", 3)  # several chunks, one straddling the history
    recorder = EpisodeRecorder(tmp_path / "a", copy.deepcopy(built), None, "a")
    expected = [f.plans["stage"] for f in shadow_episode(recorder.world, {"stage": model_planner(_driver(), recorder)})]
    batched = OpenLoopPlanner(_driver(), EpisodeRecorder(tmp_path / "b", copy.deepcopy(built), None, "b"))
    shadow = shadow_episode(batched.recorder.world, {"stage": batched})
    assert all(f.plans["stage"] is None for f in shadow)  # nothing planned until asked
    plans = batched.plans(len(shadow))  # the frames with a whole logged future, in chunks of CHUNK
    assert len(batched.recorder.frames) == 13 and len(plans) == len(shadow) == 7
    assert plans[:HISTORY] == [None] * HISTORY and expected[:HISTORY] == [None] * HISTORY
    for got, want in zip(plans, expected):
        if want is not None:
            np.testing.assert_allclose(got, want)
    assert sum(p is not None for p in expected) == len(shadow) - HISTORY


def test_episodes_on_one_route_never_share_a_frame_token(built, tmp_path):
    tokens = {}
    for name in ("planner", "open-loop", "planner"):
        recorder = EpisodeRecorder(tmp_path / name, copy.deepcopy(built), None, name)
        recorder.record()
        tokens.setdefault(name, set()).add(recorder.token)
    assert len(tokens["planner"]) == 1  # the same episode again names its frames the same
    assert tokens["planner"].isdisjoint(tokens["open-loop"])


def test_the_closed_loop_counts_who_drove_each_planning_frame(built, tmp_path):
    planner = model_planner(_driver(fall_back_every=3), EpisodeRecorder(tmp_path, copy.deepcopy(built), None, "a"))
    drive_episode(planner.recorder.world, planner)
    counts, asked = planner.counts, len(planner.recorder.frames) - HISTORY
    assert counts.frames == len(planner.recorder.frames) and asked >= 3
    assert counts.expert == HISTORY and counts.fell_back == asked // 3 and counts.planned == asked - asked // 3


def test_a_non_finite_plan_is_named_as_the_stages(built, tmp_path):
    planner = model_planner(_driver(nan_at=5), EpisodeRecorder(tmp_path, copy.deepcopy(built), None, "a"))
    with pytest.raises(NonFinitePlan, match=r"^the stage planned non-finite waypoints \(\[nan, nan.*retrain the stage"):
        drive_episode(planner.recorder.world, planner)
    assert len(planner.recorder.frames) == 6  # refused at the frame it planned NaN, before following it
    batched = OpenLoopPlanner(_driver(nan_at=5), EpisodeRecorder(tmp_path / "b", copy.deepcopy(built), None, "b"))
    shadow = shadow_episode(batched.recorder.world, {"stage": batched})
    with pytest.raises(NonFinitePlan):
        batched.plans(len(shadow))
