"""A metrics file keeps each number with the items it was scored on, through merges."""

from __future__ import annotations

from pathlib import Path

from occtrain.formats.metrics_file import Provenance, SampleSet, digest_items, read_metrics, write_metrics


def _set(tasks: list[str], items: list[str], keys: list[str], total: int = 64) -> SampleSet:
    return SampleSet(digest_items(items), len(items), total, tasks, keys)


def _eval(coverage: dict[str, list[int]], *sets: SampleSet, code: str = "0.1.0+abc") -> Provenance:
    return Provenance("occtrain eval", "val", coverage, "w", "v5", "world", code_version=code, sample_sets=list(sets))


def test_the_digest_names_the_items_whatever_their_order() -> None:
    assert digest_items(["b", "a", "a"]) == digest_items(["a", "b"]) != digest_items(["a", "c"])


def test_a_merged_eval_keeps_each_number_with_its_own_items(tmp_path: Path) -> None:
    four, one = [f"t{i}" for i in range(4)], ["t0"]
    earlier = _eval(
        {"forecasting": [4, 64], "planning": [4, 64]},
        _set(["forecasting"], four, ["plan_alternate_L2_stp3_avg"]),
        _set(["forecasting", "planning"], four, ["baseline_constant_velocity_L2_stp3_avg"]),
        _set(["planning"], four, ["plan_direct_L2_stp3_avg"]),
    )
    now = _eval(
        {"planning": [1, 64]},
        _set(["planning"], one, ["baseline_constant_velocity_L2_stp3_avg", "plan_direct_L2_stp3_avg"]),
    )
    merged = now.merged(earlier)
    assert merged.coverage == {"forecasting": [4, 64], "planning": [1, 64]}
    plan, velocity = (
        merged.sample_set("plan_alternate_L2_stp3_avg"),
        merged.sample_set("baseline_constant_velocity_L2_stp3_avg"),
    )
    assert plan is not None and velocity is not None
    assert plan.digest == digest_items(four) and velocity.digest == digest_items(one)
    assert [s.keys for s in merged.sample_sets] == [
        ["plan_alternate_L2_stp3_avg"],
        ["baseline_constant_velocity_L2_stp3_avg", "plan_direct_L2_stp3_avg"],
    ]
    # ... and reads back as written.
    path = write_metrics(tmp_path / "metrics.json", {"plan_alternate_L2_stp3_avg": 0.2}, merged)
    assert read_metrics(path).provenance == merged


def test_scores_of_other_code_are_not_merged() -> None:
    a, b = _eval({"qa": [4, 4]}), _eval({"qa": [4, 4]}, code="0.1.0+def")
    assert a.same_model_and_data(_eval({"qa": [2, 4]})) and not a.same_model_and_data(b)


def test_numbers_of_other_items_than_the_split_say_what_they_are() -> None:
    rollouts = SampleSet("d", 4, 4, ["rollouts"], ["round0_rollout_score"], on="round 0's 4 training routes")
    provenance = Provenance(
        "validation at the end of training", "val", {"validation": [60, 64]}, sample_sets=[rollouts]
    )
    assert provenance.describe() == (
        "a subset of the val split (validation 60 of 64); rollouts: round 0's 4 training routes"
    )
