"""Shards: round trip through a DataLoader, the allow-list decoder, corrupt input."""

import io
import json
import os
import pickle
import socket
import tarfile

import numpy as np
import pytest
import torch

from conftest import hand_labels
from occtrain.commands.data_check import check_shards
from occtrain.config import DataConfig
from occtrain.data.datamodule import COLLATE, ResumableLoader, ShardDataModule
from occtrain.data.layout import DatasetIndex
from occtrain.data.shards import decode_sample, make_pipeline, read_index, shard_urls, write_shards
from occtrain.errors import DataError
from occtrain.formats.occ3d import GRID_SHAPE


@pytest.fixture(scope="module")
def shards(hand_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("shards") / "s"
    write_shards(hand_dataset, out, samples_per_shard=5, history=2, future=3)
    return out


def test_index_counts(hand_dataset, shards):
    idx = read_index(shards)
    # 2 train scenes x 12 frames; clips need 2 history + 3 future: 12 - 5 = 7 anchors per scene.
    assert sum(e["samples"] for e in idx["kinds"]["frames"]["train"]) == 24
    assert sum(e["samples"] for e in idx["kinds"]["clips"]["train"]) == 14
    assert sum(e["samples"] for e in idx["kinds"]["clips"]["val"]) == 7
    assert [e["samples"] for e in idx["kinds"]["frames"]["train"]] == [5, 5, 5, 5, 4]
    assert check_shards(shards) == []


def test_frames_round_trip_through_dataloader_with_two_workers(hand_dataset, shards):
    ds = DatasetIndex.open(hand_dataset)
    cfg = DataConfig(root=str(hand_dataset), shards=str(shards), batch_size=4, num_workers=2)
    dm = ShardDataModule(cfg, "frames")
    seen, order = {}, []
    for batch in dm.val_dataloader():
        assert batch["semantics"].dtype == torch.uint8 and batch["semantics"].shape[1:] == GRID_SHAPE
        for i, tok in enumerate(batch["token"]):
            seen[tok] = (batch["semantics"][i].numpy(), batch["mask_camera"][i].numpy())
            order.append(tok)
    val_tokens = [t for _, t in ds.samples("val")]
    assert sorted(order) == sorted(val_tokens)  # every val sample exactly once across workers, none twice
    for scene, tok in ds.samples("val"):
        want = ds.labels(scene, tok)
        assert np.array_equal(seen[tok][0], want["semantics"])
        assert np.array_equal(seen[tok][1], want["mask_camera"].astype(bool))


def test_clip_content_matches_the_dataset(hand_dataset, shards):
    ds = DatasetIndex.open(hand_dataset)
    urls, total = shard_urls(shards, "clips", "val")
    samples = list(make_pipeline(urls, train=False, total=total))
    assert len(samples) == total == 7
    first = samples[0]
    scene = ds.splits["val"][0]
    tokens = ds.scenes[scene]
    assert first["__key__"] == tokens[2]
    assert first["ann.json"]["tokens"] == tokens[0:6]
    sem = first["occ.npz"]["semantics"]
    assert sem.shape == (6, *GRID_SHAPE)
    assert np.array_equal(sem[4], ds.labels(scene, tokens[4])["semantics"])
    assert first["caption.txt"] == "caption 2" and first["qa.json"][0]["answer"] == "yes"


def test_train_pipeline_streams_forever_and_shuffles(hand_dataset, shards):
    urls, _ = shard_urls(shards, "frames", "train")

    def keys(buffer: int) -> list[str]:
        it = iter(make_pipeline(urls, train=True, shuffle_buffer=buffer, seed=1))
        return [next(it)["__key__"] for _ in range(60)]  # more than the 24 train frames

    shuffled, in_order = keys(8), keys(1)
    assert len(set(shuffled)) > 12
    assert shuffled != in_order  # the buffer reorders samples...
    assert shuffled == keys(8)  # ...the same way every time (seeded)
    # Without the buffer, samples come in shard order: runs of consecutive keys of one shard.
    stored = [s["__key__"] for url in urls for s in make_pipeline([url], train=False)]
    follows = sum(stored.index(b) == stored.index(a) + 1 for a, b in zip(in_order, in_order[1:]))
    assert follows > 40
    assert sum(stored.index(b) == stored.index(a) + 1 for a, b in zip(shuffled, shuffled[1:])) < follows


def test_the_default_order_is_a_fresh_permutation_of_every_sample_each_epoch():
    """``shuffle_buffer: -1``: each epoch holds every position once, in an order of its own
    that the seed fixes; an empty shard is skipped. Shards written in scene order then still
    give batches from across the whole split, which a buffer of a few shards does not."""
    from itertools import islice

    from occtrain.data.shards.positions import train_order

    counts = [5, 0, 7, 4]
    positions = {(shard, i) for shard, n in enumerate(counts) for i in range(n)}
    first, second = (list(islice(train_order(counts, seed=3, shuffle_buffer=-1), k * 16, (k + 1) * 16)) for k in (0, 1))
    assert set(first) == set(second) == positions and len(first) == 16
    assert first != second and first != sorted(first)
    assert list(islice(train_order(counts, seed=3, shuffle_buffer=-1), 32)) == first + second
    assert list(islice(train_order(counts, seed=4, shuffle_buffer=-1), 16)) != first
    # The shards the first 8 samples come from: all three, where a buffer of 4 samples in
    # front of whole shards of 20 draws them from one.
    counts = [20, 0, 20, 20]
    assert len({shard for shard, _ in islice(train_order(counts, seed=3, shuffle_buffer=-1), 8)}) == 3
    assert len({shard for shard, _ in islice(train_order(counts, seed=3, shuffle_buffer=4), 8)}) == 1


def _train_keys(
    urls: list[str], steps: int, batch_size: int, rank_and_world=(0, 1), workers: int = 0, **kw
) -> list[list[str]]:
    """Batches of keys a training DataLoader gives, as one rank of ``rank_and_world``."""
    from torch.utils.data import DataLoader

    pipeline = make_pipeline(
        urls, train=True, batch_size=batch_size, rank_and_world=rank_and_world, entries=["meta.json"], **kw
    )
    loader = DataLoader(
        pipeline, batch_size=batch_size, num_workers=workers, collate_fn=lambda s: [x["__key__"] for x in s]
    )
    return [batch for _, batch in zip(range(steps), loader)]


def test_two_ranks_of_b_train_on_the_batches_of_one_process_of_2b(shards):
    # Each rank through two loader workers: the global batch is the same set, in the same order.
    urls, _ = shard_urls(shards, "frames", "train")
    one = _train_keys(urls, 15, batch_size=4, seed=2, shuffle_buffer=8)
    ranks = [
        _train_keys(urls, 15, batch_size=2, rank_and_world=(r, 2), workers=2, seed=2, shuffle_buffer=8) for r in (0, 1)
    ]
    assert [a + b for a, b in zip(*ranks)] == one
    assert one != _train_keys(urls, 15, batch_size=4, seed=3, shuffle_buffer=8)  # the seed orders it


def test_each_rank_reads_only_its_own_samples(shards):
    urls, total = shard_urls(shards, "frames", "train")

    def bytes_read(rank: int, world: int) -> int:
        pipeline = make_pipeline(
            urls, train=True, batch_size=4 // world, rank_and_world=(rank, world), seed=1, shuffle_buffer=1
        )
        for _, _ in zip(range(2 * total // world), pipeline):  # two epochs: each sample twice
            pass
        return pipeline.pipeline[0].bytes_read

    one, halves = bytes_read(0, 1), [bytes_read(r, 2) for r in (0, 1)]
    assert halves[0] + halves[1] == one  # no sample read by both ranks
    assert all(0.35 < h / one < 0.65 for h in halves), (halves, one)
    # Entries a stage does not ask for are never read.
    meta = make_pipeline(urls, train=True, entries=["meta.json"], seed=1)
    next(iter(meta))
    assert 0 < meta.pipeline[0].bytes_read < 1000


def test_an_epoch_resumed_mid_way_with_workers_sees_each_sample_once(hand_dataset, shards):
    # Stopped after 2 of the 6 batches of an epoch (24 frames / 4), and resumed by a new
    # loader from the state a checkpoint keeps: the same 6 batches as without the stop.
    cfg = DataConfig(root=str(hand_dataset), shards=str(shards), batch_size=4, num_workers=2, shuffle_buffer=1, seed=5)
    ds = DatasetIndex.open(hand_dataset)

    def keys(loader, steps: int) -> list[list[str]]:
        return [batch["token"] for _, batch in zip(range(steps), loader)]

    whole = keys(ShardDataModule(cfg, "frames").train_dataloader(), 6)
    assert sorted(k for batch in whole for k in batch) == sorted(t for _, t in ds.samples("train"))
    first = ShardDataModule(cfg, "frames").train_dataloader()
    before = keys(first, 2)
    first.consumed = lambda: 2
    state = first.state_dict()
    del first  # the killed process's loader is gone; only its checkpointed state remains
    resumed = ShardDataModule(cfg, "frames").train_dataloader()
    resumed.load_state_dict(state)
    assert before + keys(resumed, 4) == whole
    # Resumed as two ranks of 2 (the same global batch): the rest of the epoch, split.
    urls, total = shard_urls(shards, "frames", "train")
    ranks = []
    for rank in (0, 1):
        pipeline = make_pipeline(
            urls, train=True, total=total, batch_size=2, rank_and_world=(rank, 2), seed=5, shuffle_buffer=1
        )
        loader = ResumableLoader(
            pipeline.pipeline[0], pipeline, batch_size=2, num_workers=2, collate_fn=COLLATE["frames"]
        )
        loader.load_state_dict(state)
        ranks.append(keys(loader, 4))
    assert [a + b for a, b in zip(*ranks)] == whole[2:]


def test_validation_is_split_evenly_over_ranks(shards):
    urls, total = shard_urls(shards, "frames", "val")
    keys = [
        [s["__key__"] for s in make_pipeline(urls, train=False, total=total, rank_and_world=(rank, 2))]
        for rank in (0, 1)
    ]
    assert len(keys[0]) == len(keys[1]) == total // 2
    assert not set(keys[0]) & set(keys[1])


def test_an_odd_validation_split_pads_the_shorter_rank_once(tmp_path):
    import occtrain.data.shards.positions as sh
    from conftest import write_hand_dataset

    out = tmp_path / "s"
    write_shards(
        write_hand_dataset(tmp_path / "ds", train=1, val=1, frames=9),
        out,
        samples_per_shard=4,
        history=0,
        future=0,
        kinds=["frames"],
    )
    urls, odd = shard_urls(out, "frames", "val")
    assert odd == 9
    samples = [list(make_pipeline(urls, train=False, total=odd, rank_and_world=(rank, 2))) for rank in (0, 1)]
    pads = [[bool(s.get(sh.PAD_KEY)) for s in rank] for rank in samples]
    # Rank 1 holds one sample fewer: it starts with one padding sample, so both run alike.
    assert pads == [[False] * 5, [True] + [False] * 4]
    real = [[s["__key__"] for s in rank if not s.get(sh.PAD_KEY)] for rank in samples]
    assert len(real[0]) + len(real[1]) == odd and not set(real[0]) & set(real[1])


def _tar_with(tmp_path, entries: dict[str, bytes]) -> str:
    path = tmp_path / "evil-000000.tar"
    with tarfile.open(path, "w") as tar:
        for name, data in entries.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return str(path)


class Boom:
    def __reduce__(self):
        return (print, ("pickle was executed",))


def test_pickled_payload_is_refused(tmp_path, capsys):
    url = _tar_with(tmp_path, {"k1.meta.json": b"{}", "k1.payload.pyd": pickle.dumps(Boom())})
    with pytest.raises(DataError, match="'payload.pyd' is not an allowed format"):
        list(make_pipeline([url], train=False))
    assert "pickle was executed" not in capsys.readouterr().out


def test_object_npy_is_refused(tmp_path):
    buf = io.BytesIO()
    np.save(buf, np.array([Boom()], dtype=object), allow_pickle=True)
    url = _tar_with(tmp_path, {"k1.arr.npy": buf.getvalue()})
    with pytest.raises(DataError, match="pickled object array"):
        list(make_pipeline([url], train=False))


def test_wrong_shape_in_shard(tmp_path):
    buf = io.BytesIO()
    np.savez(buf, semantics=np.zeros((10, 10, 16), np.uint8))
    url = _tar_with(tmp_path, {"k1.occ.npz": buf.getvalue()})
    with pytest.raises(DataError, match="semantics has shape"):
        list(make_pipeline([url], train=False))


def test_truncated_shard(tmp_path, shards):
    src = shards / "frames" / "train-000000.tar"
    bad = tmp_path / "train-000000.tar"
    bad.write_bytes(src.read_bytes()[: src.stat().st_size // 3])
    with pytest.raises(DataError) as err:
        list(make_pipeline([str(bad)], train=False))
    assert "train-000000.tar" in str(err.value)


def test_check_lists_corrupt_shards(tmp_path, shards):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(shards, copy)
    victim = copy / "clips" / "val-000000.tar"
    victim.write_bytes(victim.read_bytes()[:5000])
    problems = check_shards(copy)
    assert problems and all("val-000000.tar" in p for p in problems)


def test_shards_refuse_to_overwrite_different_shards(hand_dataset, shards):
    before = (shards / "index.json").read_text()
    assert write_shards(hand_dataset, shards, samples_per_shard=5, history=2, future=3)["source"]["history"] == 2
    with pytest.raises(DataError, match="different dataset or layout"):
        write_shards(hand_dataset, shards, samples_per_shard=7, history=2, future=3)
    assert (shards / "index.json").read_text() == before
    assert json.loads(before)["source"]["samples_per_shard"] == 5


def _copy_of(shards, tmp_path):
    """A copy of the module's shards this test may replace (the module's stay as they are)."""
    import shutil

    copy = tmp_path / "s"
    shutil.copytree(shards, copy)
    return copy


def test_shards_of_a_moved_dataset_are_accepted_and_of_a_plain_copy_refused(hand_dataset, shards, tmp_path):
    import os
    import shutil

    from occtrain.data.shards import dataset_fingerprint

    out = _copy_of(shards, tmp_path)
    before = (out / "index.json").read_text()
    # mv, cp -a, copytree: the same files with their times, so the same fingerprint: the
    # shards hold no path and are exactly what the copy would write.
    moved = tmp_path / "moved"
    shutil.copytree(hand_dataset, moved)
    os.remove(moved / "nuscenes_qa" / "NuScenes_val_questions.json")  # a missing file, named from the root
    missing = tmp_path / "missing"
    shutil.copytree(moved, missing)
    assert dataset_fingerprint(DatasetIndex.open(moved), 3) == dataset_fingerprint(DatasetIndex.open(missing), 3)
    assert dataset_fingerprint(DatasetIndex.open(moved), 2) != dataset_fingerprint(DatasetIndex.open(missing), 2)
    assert write_shards(hand_dataset, out, samples_per_shard=5, history=2, future=3) == json.loads(before)
    renamed = tmp_path / "renamed"
    shutil.copytree(hand_dataset, renamed)
    assert write_shards(renamed, out, samples_per_shard=5, history=2, future=3) == json.loads(before)
    assert (out / "index.json").read_text() == before  # accepted as they are, not re-pointed
    # cp -r: the same bytes with new times; not told from an edit without reading them all.
    copied = tmp_path / "copied"
    shutil.copytree(hand_dataset, copied, copy_function=shutil.copy)
    with pytest.raises(DataError) as err:
        write_shards(copied, out, samples_per_shard=5, history=2, future=3)
    assert str(err.value) == (
        f"{out}: its shards were made from {hand_dataset.resolve()}, and {copied} is not that dataset as it was then "
        "(another dataset, a copy whose files got new times as `cp -r` gives them, or one edited since); "
        f"delete {out} and they are written again, or replace them with "
        f"`occtrain data shards {copied} --out {out} --samples-per-shard 5 --history 2 --future 3 --rebuild`"
    )
    assert (out / "index.json").read_text() == before


def test_shards_indexed_by_an_earlier_fingerprint_stay_current_where_they_were_made(hand_dataset, shards, tmp_path):
    from occtrain.data.shards import dataset_fingerprint

    out = _copy_of(shards, tmp_path)
    index = json.loads((out / "index.json").read_text())
    index["source"].update(fingerprint=dataset_fingerprint(DatasetIndex.open(hand_dataset), 2), fingerprint_version=2)
    (out / "index.json").write_text(json.dumps(index))
    assert write_shards(hand_dataset, out, samples_per_shard=5, history=2, future=3) == index


def test_rebuild_replaces_the_shards_and_a_failure_leaves_the_old_ones(hand_dataset, shards, tmp_path, monkeypatch):
    import occtrain.data.shards.writer as shard_module

    out = _copy_of(shards, tmp_path)
    before = {p.name: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    real = shard_module._frame_sample
    calls = []

    def fails_halfway(*args):
        calls.append(1)
        if len(calls) > 12:
            raise DataError("a bad label halfway")
        return real(*args)

    monkeypatch.setattr(shard_module, "_frame_sample", fails_halfway)
    with pytest.raises(DataError, match="a bad label halfway"):
        write_shards(hand_dataset, out, samples_per_shard=7, history=2, future=3, rebuild=True)
    assert {p.name: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before and check_shards(out) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]  # nothing left beside it
    monkeypatch.setattr(shard_module, "_frame_sample", real)

    out.chmod(0o750)
    index = write_shards(hand_dataset, out, samples_per_shard=7, history=2, future=3, rebuild=True)
    assert index["source"]["samples_per_shard"] == 7 and read_index(out) == index
    assert [e["samples"] for e in index["kinds"]["frames"]["train"]] == [7, 7, 7, 3] and check_shards(out) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"] and out.stat().st_mode & 0o777 == 0o750
    assert write_shards(hand_dataset, out, samples_per_shard=7, history=2, future=3) == index  # current now


def test_a_killed_rebuilds_folder_is_named_by_check_and_removed_by_the_next_write(
    hand_dataset, shards, tmp_path, monkeypatch, capsys
):
    """kill -9 leaves a rebuild's staging folder beside --out (its cleanup never runs): `data
    check` names it while its process is gone, and the next write removes it. The folder of
    a rebuild whose process lives (here: this one) is neither named nor touched."""
    import occtrain.data.shards.writer as shard_module

    out = _copy_of(shards, tmp_path)

    def killed(pid: int) -> None:  # a rebuild by process `pid` that dies halfway, leaving its folder
        with monkeypatch.context() as m:
            m.setattr(shard_module.os, "getpid", lambda: pid)
            m.setattr(shard_module, "remove_inside", lambda *args: True)
            m.setattr(shard_module, "_frame_sample", _raises)
            with pytest.raises(DataError):
                write_shards(hand_dataset, out, samples_per_shard=7, history=2, future=3, rebuild=True)

    dead = 2**22  # above Linux's largest pid: no process has it
    killed(os.getpid())
    killed(dead)
    (stale,) = tmp_path.glob(f".s.rebuild-{dead}.*")
    (live,) = tmp_path.glob(f".s.rebuild-{os.getpid()}.*")
    unknown = tmp_path / ".s.rebuild-k2j4h1b0"  # named before the owner was: whose it is, nobody knows
    unknown.mkdir()
    assert stale.is_dir() and live.is_dir()
    assert check_shards(out) == [
        f"{stale}: left by an `occtrain data shards --rebuild` of {out} that was stopped (pid {dead} on "
        f"{socket.gethostname()} is gone); remove it with `rm -r {stale}` (the next `occtrain data shards` of "
        f"{out} removes it too)",
        f"{unknown}: left by an `occtrain data shards --rebuild` of {out} that has not finished; unless that "
        f"rebuild is still running, remove it with `rm -r {unknown}`",
    ]
    capsys.readouterr()
    write_shards(hand_dataset, out, samples_per_shard=5, history=2, future=3)  # current: nothing else to write
    assert not stale.exists() and live.is_dir() and unknown.is_dir() and len(check_shards(out)) == 1
    assert f"removed {stale}" in capsys.readouterr().err


def _raises(*args):
    raise DataError("a bad label halfway")


def test_frames_alone_when_no_clip_fits_and_a_note_says_who_cannot_train(hand_dataset, tmp_path, capsys):
    from occtrain.cli import main
    from occtrain.data.datamodule import check_data, ensure_data

    out = tmp_path / "s"
    assert main(["data", "shards", str(hand_dataset), "--out", str(out), "--history", "6", "--future", "6"]) == 0
    err = capsys.readouterr().err
    note = [line for line in err.splitlines() if line.startswith("note: ")]
    assert note == [
        f"note: {hand_dataset}: its longest train scene has 12 frames and a clip spans history 6 + 1 + future 6 = 13, "
        "so no clip fits: frame shards only, which tokenizer stages train on; the world-model stages (pretrain, "
        "instruct, "
        "planner, distill) read clips and cannot train on this dataset (use longer scenes or a shorter history/future)"
    ]
    index = read_index(out)
    assert list(index["kinds"]) == ["frames"] and index["source"]["kinds"] == ["frames"]
    with pytest.raises(DataError, match=r"has no 'clips' shards: .* = 13, so no clip fits; use longer scenes"):
        shard_urls(out, "clips", "train")
    # Asked for by name, clips that cannot fit are refused, as before.
    assert (
        main(
            [
                "data",
                "shards",
                str(hand_dataset),
                "--out",
                str(tmp_path / "c"),
                "--kinds",
                "clips",
                "--history",
                "6",
                "--future",
                "6",
            ]
        )
        == 2
    )
    assert "so there would be no clip to train on" in capsys.readouterr().err and not (tmp_path / "c").exists()

    # A run shards the dataset alike, and says so before it writes them.
    cfg = DataConfig(root=str(hand_dataset), shards=str(tmp_path / "run-shards"), history=6, future=6)
    line = check_data(cfg)
    assert line.endswith(
        "frames; shards to be written in " + str(tmp_path / "run-shards") + "; " + note[0].removeprefix("note: ")
    )
    with pytest.raises(
        DataError, match=r"^stage 'pretrain' reads clips, and .* = 13, so no clip fits; use longer scenes"
    ):
        check_data(cfg, clip_readers=["pretrain"])
    assert read_index(ensure_data(cfg))["source"]["kinds"] == ["frames"]
    assert note[0] in capsys.readouterr().err
    assert "shards ready" in check_data(cfg)


def test_an_unwritable_out_fails_before_any_shard(hand_dataset, tmp_path, capsys, monkeypatch):
    import errno

    import occtrain.formats.io
    from occtrain.cli import main

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    opened = []
    monkeypatch.setattr(occtrain.formats.io.tempfile, "mkstemp", read_only)
    monkeypatch.setattr(DatasetIndex, "open", lambda *a: opened.append(a))  # the dataset is never even read
    assert main(["data", "shards", str(hand_dataset), "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err  # what to do after the ';' is io.check_output's to say
    assert (
        err.startswith(f"error: cannot write {tmp_path / 's'}: the file system is read-only; ") and err.count("\n") == 1
    )
    assert opened == [] and list(tmp_path.iterdir()) == []


def test_decode_sample_unpacks_masks():
    mask = (np.arange(np.prod(GRID_SHAPE)).reshape(GRID_SHAPE) % 3 == 0).astype(np.uint8)
    buf = io.BytesIO()
    np.savez(buf, semantics=hand_labels(1)["semantics"], mask_camera=np.packbits(mask, axis=-1))
    out = decode_sample({"__key__": "k", "occ.npz": buf.getvalue()})
    assert np.array_equal(out["occ.npz"]["mask_camera"], mask)


def test_a_world_synthesized_with_other_settings_is_refused(synth_dataset, tmp_path):
    from occtrain.config import SynthConfig
    from occtrain.config.groups import DataConfig
    from occtrain.data.datamodule import ensure_data
    from occtrain.errors import DataError

    same = SynthConfig(train_scenes=2, val_scenes=1, frames_per_scene=12, seed=3)
    cfg = DataConfig(root=str(synth_dataset), shards=str(tmp_path / "shards"), synth=same)
    assert (ensure_data(cfg, verbose=False) / "index.json").is_file()
    cfg.synth.train_scenes = 4
    with pytest.raises(DataError, match=r"synthesized with train_scenes=2 \(recipe: 4\)"):
        ensure_data(cfg, verbose=False)
