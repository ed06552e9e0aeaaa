"""The data commands through the real CLI in a subprocess, on a tmp dir."""

import json

import numpy as np
import pytest
from PIL import Image

from conftest import run_cli

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli") / "world"
    res = run_cli(
        "data", "synth", "--out", str(root), "--scenes", "1", "--val-scenes", "1", "--frames", "12", "--seed", "4"
    )
    assert res.returncode == 0, res.stderr
    assert "wrote 2 scenes" in res.stderr
    return root


def test_synth_again_reuses_and_a_different_request_is_refused(world):
    stamp = (world / "annotations.json").stat().st_mtime_ns
    res = run_cli(
        "data", "synth", "--out", str(world), "--scenes", "1", "--val-scenes", "1", "--frames", "12", "--seed", "4"
    )
    assert res.returncode == 0 and "already complete" in res.stderr
    res = run_cli(
        "data", "synth", "--out", str(world), "--scenes", "1", "--val-scenes", "1", "--frames", "12", "--seed", "5"
    )
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        f"error: {world}: already holds a different dataset (differs in seed); choose another --out or delete that "
        "directory"
    ]
    assert (world / "annotations.json").stat().st_mtime_ns == stamp


def test_check_dataset_ok_then_lists_problems(world, tmp_path):
    res = run_cli("data", "check", str(world))
    assert res.returncode == 0, res.stdout + res.stderr
    assert res.stdout.strip().endswith(": ok")
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(world, bad)
    victims = sorted((bad / "gts").rglob("labels.npz"))[:2]
    np.savez(victims[0], semantics=np.zeros((200, 200, 8), np.uint8))
    victims[1].write_bytes(b"garbage")
    res = run_cli("data", "check", str(bad))
    assert res.returncode == 1
    lines = res.stdout.strip().splitlines()
    assert any(str(victims[0]) in line and "shape" in line for line in lines)
    assert any(str(victims[1]) in line and "corrupt" in line for line in lines)


def test_show_writes_a_picture(world, tmp_path):
    out = tmp_path / "bev.png"
    res = run_cli("data", "show", str(world), "--frames", "3", "--out", str(out))
    assert res.returncode == 0, res.stderr
    assert "(the first val scene; --scene picks another)" in res.stderr  # which scene it drew, when not told
    img = Image.open(out)
    assert img.width > 3 * 600 and img.height > 600
    assert len(np.unique(np.asarray(img).reshape(-1, 3), axis=0)) > 8  # many classes drawn
    res = run_cli("data", "show", str(world), "--scene", "scene-9999", "--out", str(tmp_path / "other.png"))
    assert res.returncode == 2 and "no scene 'scene-9999'" in res.stderr
    before = out.read_bytes()
    res = run_cli("data", "show", str(world), "--index", "2", "--out", str(out))
    assert res.returncode == 2 and "exists; pass --overwrite" in res.stderr and out.read_bytes() == before
    res = run_cli("data", "show", str(world), "--index", "2", "--out", str(out), "--overwrite")
    assert res.returncode == 0 and out.read_bytes() != before


def test_shards_and_check_them(world, tmp_path):
    out = tmp_path / "shards"
    res = run_cli("data", "shards", str(world), "--out", str(out), "--samples-per-shard", "8")
    assert res.returncode == 0, res.stderr
    index = json.loads((out / "index.json").read_text())
    assert sum(e["samples"] for e in index["kinds"]["frames"]["train"]) == 12
    assert sum(e["samples"] for e in index["kinds"]["clips"]["val"]) == 12 - 4 - 6
    res = run_cli("data", "check", str(out))
    assert res.returncode == 0 and "shards" in res.stdout
    tar = out / "frames" / "train-000000.tar"
    tar.write_bytes(tar.read_bytes()[:4000])
    res = run_cli("data", "check", str(out))
    assert res.returncode == 1 and "train-000000.tar" in res.stdout


def test_shards_rebuild_replaces_shards_of_another_layout(world, tmp_path):
    out = tmp_path / "shards"
    res = run_cli("data", "shards", str(world), "--out", str(out), "--kinds", "frames", "--samples-per-shard", "8")
    assert res.returncode == 0, res.stderr
    res = run_cli("data", "shards", str(world), "--out", str(out), "--kinds", "frames", "--samples-per-shard", "5")
    assert res.returncode == 2 and "--samples-per-shard 5 --kinds frames --rebuild`" in res.stderr
    res = run_cli(
        "data", "shards", str(world), "--out", str(out), "--kinds", "frames", "--samples-per-shard", "5", "--rebuild"
    )
    assert res.returncode == 0, res.stderr
    index = json.loads((out / "index.json").read_text())
    assert [e["samples"] for e in index["kinds"]["frames"]["train"]] == [5, 5, 2]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shards"]  # no staging left beside it
    assert run_cli("data", "check", str(out)).returncode == 0


def test_config_show_and_a_typo(tmp_path):
    res = run_cli("config", "show", "configs/data/quickstart.yaml", "synth.seed=3")
    assert res.returncode == 0, res.stderr
    assert "seed: 3" in res.stdout and "root: data/quickstart" in res.stdout
    res = run_cli("config", "show", "configs/trainer/cpu.yaml", "max_step=10")
    assert res.returncode == 2
    assert res.stderr.strip() == "error: unknown key 'max_step' in override 'max_step=10'; did you mean 'max_steps'?"
    bad = tmp_path / "trainer" / "cpu.yaml"
    bad.parent.mkdir()
    bad.write_text("max_step: 3\n")
    res = run_cli("config", "show", str(bad))
    assert res.stderr.strip() == f"error: unknown key 'max_step' in {bad}; did you mean 'max_steps'?"


def test_missing_dataset_is_one_line(tmp_path):
    res = run_cli("data", "shards", str(tmp_path / "nowhere"), "--out", str(tmp_path / "s"))
    assert res.returncode == 2
    assert len(res.stderr.strip().splitlines()) == 1 and "dataset directory not found" in res.stderr
