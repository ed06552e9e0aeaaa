"""Caches, shards and metrics are keyed by what they were made from, not by names: the
dataset fingerprint follows every file shards are built from, two worlds in folders of one
name never share an eval directory, and the metrics of one world are never merged into
another's."""

from __future__ import annotations

import json
import os
import shutil
import tarfile
from pathlib import Path

import pytest

from conftest import write_hand_dataset
from occtrain.commands.evaluate import _save, eval_metrics_file
from occtrain.data.layout import DatasetIndex
from occtrain.data.shards import dataset_fingerprint, make_pipeline, shard_urls, world_key, write_shards
from occtrain.errors import DataError
from occtrain.formats.metrics_file import Provenance, StageAttempt, read_metrics
from occtrain.stages.stage import stage_cache_dir


@pytest.fixture
def world(tmp_path: Path) -> Path:
    return write_hand_dataset(tmp_path / "a" / "world", train=1, val=1, frames=6)


def fingerprint(root: Path) -> str:
    return dataset_fingerprint(DatasetIndex.open(root))


def touch_later(path: Path) -> None:
    """Rewrite ``path`` with its own bytes, one second later (an edit that keeps the size)."""
    st = path.stat()
    path.write_bytes(path.read_bytes())
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))


@pytest.mark.parametrize("edited", ["labels", "sidecar", "qa"])
def test_the_fingerprint_follows_every_source_file(world: Path, edited: str) -> None:
    before = fingerprint(world)
    index = DatasetIndex.open(world)
    scene, token = next(index.samples("train"))
    path = {
        "labels": index.labels_path(scene, token),
        "sidecar": world / "occtrain" / "frames" / f"{scene}.json",
        "qa": world / "nuscenes_qa" / "NuScenes_val_questions.json",
    }[edited]
    touch_later(path)
    assert fingerprint(world) != before


def test_a_copy_keeps_its_fingerprint_and_gets_its_own_key(world: Path, tmp_path: Path) -> None:
    twin = tmp_path / "b" / "world"  # same folder name, same content (mtimes kept), another place
    shutil.copytree(world, twin)
    assert fingerprint(twin) == fingerprint(world)
    assert world_key(twin) != world_key(world) and world_key(world) == world_key(world)


def test_two_worlds_of_one_folder_name_keep_apart(world: Path, tmp_path: Path) -> None:
    other = write_hand_dataset(tmp_path / "b" / "world", train=1, val=1, frames=7)
    stage = tmp_path / "run" / "instruct"
    assert eval_metrics_file(stage, "val", world) != eval_metrics_file(stage, "val", other)
    assert stage_cache_dir(stage, world) != stage_cache_dir(stage, other)
    key = world_key(world)
    index = DatasetIndex.open(world)
    touch_later(index.labels_path(*next(index.samples())))
    assert world_key(world) != key  # the world edited since: a fresh cache directory


def _provenance(dataset: str, attempt: int = 1, **coverage: list[int]) -> Provenance:
    return Provenance("occtrain eval", "val", coverage, dataset=dataset, stage=StageAttempt("hash", attempt, 1.0))


def test_metrics_of_another_world_or_model_are_not_merged(tmp_path: Path) -> None:
    out = tmp_path / "eval" / "val" / "metrics.json"
    _save(out, {"qa_accuracy": 0.5}, _provenance("aaa", qa=[4, 4]))
    _save(out, {"cider": 0.9}, _provenance("aaa", cot_planning=[2, 9]))
    both = read_metrics(out)
    assert both.metrics == {"qa_accuracy": 0.5, "cider": 0.9}
    assert both.provenance is not None and both.provenance.coverage == {"qa": [4, 4], "cot_planning": [2, 9]}
    assert both.provenance.subset and "cot_planning 2 of 9" in both.provenance.describe()
    _save(out, {"cider": 0.7}, _provenance("bbb"))  # the run's dataset changed since the first eval
    assert read_metrics(out).metrics == {"cider": 0.7}
    _save(out, {"qa_accuracy": 0.6}, _provenance("bbb", attempt=2))  # the stage was retrained since
    assert read_metrics(out).metrics == {"qa_accuracy": 0.6}
    assert json.loads(out.read_text())["provenance"]["stage"]["attempt"] == 2


def test_a_shard_cut_between_members_is_refused_by_its_count(world: Path, tmp_path: Path) -> None:
    write_shards(world, tmp_path / "shards", samples_per_shard=2, kinds=["frames"])
    urls, total = shard_urls(tmp_path / "shards", "frames", "val")
    last = Path(urls[-1])
    data = last.read_bytes()
    # Cut where the second sample's first member begins: a valid, shorter tar.
    with tarfile.open(last) as tar:
        members = tar.getmembers()
    keys = [m.name.split(".")[0] for m in members]
    cut = next(m for m, k in zip(members, keys) if k != keys[0])
    last.write_bytes(data[: cut.offset])
    with pytest.raises(DataError, match=f"its split holds {total - 1} samples, index.json says {total}"):
        list(make_pipeline(urls, train=False, total=total))


def test_shards_made_before_an_edit_are_refused(world: Path, tmp_path: Path) -> None:
    write_shards(world, tmp_path / "shards", samples_per_shard=2, kinds=["frames"])
    index = DatasetIndex.open(world)
    touch_later(index.labels_path(*next(index.samples("val"))))
    with pytest.raises(DataError, match="its shards were made before .* changed"):
        write_shards(world, tmp_path / "shards", samples_per_shard=2, kinds=["frames"])
    assert (tmp_path / "shards" / "index.json").is_file()  # left as they are: the user deletes them


def test_a_torn_tar_is_one_message_not_a_tuple(world: Path, tmp_path: Path) -> None:
    """webdataset appends its stream and url to the args of what passes its handler; the
    error that reaches the user is the message alone."""
    write_shards(world, tmp_path / "shards", samples_per_shard=2, kinds=["frames"])
    urls, total = shard_urls(tmp_path / "shards", "frames", "train")
    data = Path(urls[0]).read_bytes()
    Path(urls[0]).write_bytes(data[: len(data) // 3])
    for train in (False, True):
        with pytest.raises(DataError) as err:
            for i, _ in enumerate(make_pipeline(urls, train=train, total=total)):
                assert i < 50
        assert (
            len(err.value.args) == 1
            and "corrupt or truncated shard" in err.value.args[0]
            and "<_io" not in err.value.args[0]
        )


def test_validate_checks_without_writing(world: Path, tmp_path: Path, capsys) -> None:
    from occtrain.cli import main

    recipe = tmp_path / "r.yaml"
    recipe.write_text(f"""name: tiny
runs_root: {tmp_path}/runs
data: {{root: {world}, batch_size: 2, samples_per_shard: 4, history: 1, future: 1}}
stages:
  - name: tokenizer
    kind: tokenizer
    model: {{arch: occworld_vqvae}}
    trainer: {{max_steps: 3}}
""")
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    assert main(["validate", str(recipe)]) == 0
    out = capsys.readouterr().out
    assert "ok, 1 stage; nothing was written" in out and "tokenizer    tokenizer, occworld: 3 steps [pending]" in out
    assert f"shards to be written in {world}/shards" in out and f"run directory: {tmp_path}/runs/tiny" in out
    assert main(["run", str(recipe), "--dry-run"]) == 0
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before
