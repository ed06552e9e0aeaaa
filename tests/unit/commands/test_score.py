"""``occtrain score ...`` through ``occtrain.cli.main`` on files in tmp_path, with hand-computed expectations."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from builders import planning_files, qa_questions, straight
from occtrain.cli import main
from occtrain.data.layout import DatasetIndex
from occtrain.formats.io import atomic_write_npz
from occtrain.formats.occ3d import FREE

needs_java = pytest.mark.skipif(
    shutil.which("java") is None, reason="pycocoevalcap's PTB tokeniser and METEOR need Java"
)


def score(capsys, *argv: str) -> tuple[int, dict | None, str]:
    """Run ``occtrain score ...``; return (exit code, parsed stdout or None, stderr)."""
    code = main(["score", *map(str, argv)])
    out, err = capsys.readouterr()
    return code, (json.loads(out) if out.strip() else None), err


def one_line_error(capsys, *argv: str) -> str:
    code, out, err = score(capsys, *argv)
    assert code == 2 and out is None
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


# ----------------------------------------------------------------------------- occupancy


def val_samples(ds: Path) -> list[tuple[str, str]]:
    return list(DatasetIndex.open(ds).samples("val"))


def ground_halved(sem: np.ndarray) -> np.ndarray:
    """The prediction: the ground truth with the ground layer (class 11, z = 1) erased where x >= 100."""
    pred = sem.copy()
    pred[100:, :, 1] = FREE
    return pred


@pytest.fixture(scope="module")
def occ_preds(hand_dataset, tmp_path_factory) -> Path:
    """Predictions for the val split of the hand dataset (``ground_halved`` of each ground truth)."""
    root = tmp_path_factory.mktemp("occ_pred")
    index = DatasetIndex.open(hand_dataset)
    for scene, token in val_samples(hand_dataset):
        atomic_write_npz(
            root / scene / token / "labels.npz", {"semantics": ground_halved(index.labels(scene, token)["semantics"])}
        )
    return root


def test_occupancy_occ3d_masked_hand_case(hand_dataset, occ_preds, capsys, tmp_path):
    out_file = tmp_path / "occ.json"
    code, r, _ = score(
        capsys, "occupancy", "--pred", occ_preds, "--gt", hand_dataset, "--split", "val", "--out", out_file
    )
    assert code == 0
    n = len(val_samples(hand_dataset))
    # hand_labels: ground (11) fills z = 1 (40000 voxels), mask_camera hides x, y < 50 (2500 of them);
    # a 10 x 5 x 3 car (4) above. The prediction erases the ground at x >= 100: 20000 voxels, all visible.
    # driveable: TP = 37500 - 20000 = 17500, FN = 20000 -> 17500 / 37500 per sample, and so summed
    assert r["convention"] == "occ3d" and r["mask"] == "mask_camera" and r["samples"] == n
    assert r["per_class"]["driveable_surface"] == pytest.approx(100 * 17500 / 37500)
    assert r["per_class"]["car"] == pytest.approx(100.0)
    assert r["per_class"]["bus"] is None  # absent from both: NaN, printed as null
    assert r["mIoU"] == pytest.approx((100 * 17500 / 37500 + 100) / 2)
    index = DatasetIndex.open(hand_dataset)
    cars = sum(
        int(((lab := index.labels(s, t))["semantics"] == 4)[lab["mask_camera"] == 1].sum())
        for s, t in val_samples(hand_dataset)
    )
    # geometry: TP = 17500 n + visible car voxels, FN = 20000 n, FP = 0
    assert r["IoU"] == pytest.approx(100 * (17500 * n + cars) / (37500 * n + cars))
    assert json.loads(out_file.read_text()) == r


def test_occupancy_no_mask_and_occworld(hand_dataset, occ_preds, capsys):
    code, r, _ = score(capsys, "occupancy", "--pred", occ_preds, "--gt", hand_dataset, "--split", "val", "--no-mask")
    assert code == 0 and r["mask"] == "none"
    # every voxel: driveable 20000 / 40000; car 150 / 150; IoU = (20000 + 150) / (40000 + 150) per sample
    assert r["per_class"]["driveable_surface"] == pytest.approx(50.0)
    assert r["mIoU"] == pytest.approx(75.0)
    assert r["IoU"] == pytest.approx(100 * 20150 / 40150)
    code, r, _ = score(
        capsys, "occupancy", "--pred", occ_preds, "--gt", hand_dataset, "--split", "val", "--convention", "occworld"
    )
    # occworld: the 15 classes without ground truth score 1: mIoU = (1/2 + 1 + 15) / 17
    assert code == 0 and r["convention"] == "occworld"
    assert r["mIoU"] == pytest.approx(100 * 16.5 / 17)


def test_occupancy_missing_prediction_and_plain_gts_tree(hand_dataset, occ_preds, capsys, tmp_path):
    pred = tmp_path / "pred"
    shutil.copytree(occ_preds, pred)
    scene, token = val_samples(hand_dataset)[3]
    shutil.rmtree(pred / scene / token)
    line = one_line_error(capsys, "occupancy", "--pred", pred, "--gt", hand_dataset, "--split", "val")
    assert f"no labels.npz prediction for sample {scene}/{token}" in line and "--allow-missing" in line
    code, r, _ = score(capsys, "occupancy", "--pred", pred, "--gt", hand_dataset, "--split", "val", "--allow-missing")
    assert code == 0 and r["samples"] == len(val_samples(hand_dataset)) - 1
    # a plain <scene>/<token>/labels.npz tree (no annotations.json) holding two samples
    plain = tmp_path / "plain"
    for s, t in val_samples(hand_dataset)[:2]:
        shutil.copytree(hand_dataset / "gts" / s / t, plain / s / t)
    code, r, _ = score(capsys, "occupancy", "--pred", occ_preds, "--gt", plain)
    assert code == 0 and r["samples"] == 2
    assert r["per_class"]["driveable_surface"] == pytest.approx(100 * 17500 / 37500)


def test_occupancy_bad_input(hand_dataset, capsys, tmp_path):
    scene, token = val_samples(hand_dataset)[0]
    bad = tmp_path / "bad"
    atomic_write_npz(bad / scene / token / "labels.npz", {"semantics": np.zeros((200, 200, 8), np.uint8)})
    line = one_line_error(capsys, "occupancy", "--pred", bad, "--gt", hand_dataset, "--split", "val", "--allow-missing")
    assert "shape (200, 200, 8)" in line and str(bad / scene / token / "labels.npz") in line
    assert "prediction directory not found" in one_line_error(
        capsys, "occupancy", "--pred", tmp_path / "nope", "--gt", hand_dataset
    )
    assert "no samples found" in one_line_error(
        capsys, "occupancy", "--pred", bad, "--gt", tmp_path / "bad" / scene / token
    )


# ----------------------------------------------------------------------------- forecasting


def test_forecast_hand_case(hand_dataset, capsys, tmp_path):
    index = DatasetIndex.open(hand_dataset)
    scene = index.splits["val"][0]
    tokens = index.scenes[scene]
    future = np.stack([index.labels(scene, t)["semantics"] for t in tokens[1:7]])
    atomic_write_npz(tmp_path / scene / tokens[0] / "forecast.npz", {"semantics": future})  # exact
    atomic_write_npz(
        tmp_path / scene / tokens[1] / "forecast.npz", {"semantics": np.full_like(future, FREE)}
    )  # all free
    # 2 frames left: at 1 s (its last frame) the ground is exact and the car (10 x 5 x 3 voxels
    # of class 4) sits 80+ voxels away from the true one.
    near_end = future.copy()
    last = index.labels(scene, tokens[-1])["semantics"].copy()
    xs = np.nonzero(last == 4)[0]
    assert len(xs) == 150
    last[last == 4] = FREE
    x = 5 if xs.min() >= 100 else 180
    last[x : x + 10, 50:55, 2:5] = 4
    near_end[1] = last
    atomic_write_npz(tmp_path / scene / tokens[-3] / "forecast.npz", {"semantics": near_end})
    code, r, _ = score(capsys, "forecast", "--pred", tmp_path, "--gt", hand_dataset)
    assert code == 0 and r["convention"] == "occworld" and r["samples"] == 3
    assert r["frames"] == {"1s": 3, "2s": 2, "3s": 2}
    # 1 s sees all three: ground TP 40000 + 0 + 40000, FN 40000 -> 2/3; car TP 150, FN 150 + 150,
    # FP 150 -> 1/4; the 15 classes without ground truth count 1 (OccWorld) -> mIoU (2/3 + 1/4 + 15) / 17.
    # Occupied vs free: TP 40150 + 40000, FN 40150 + 150, FP 150.
    assert r["mIoU"]["1s"] == pytest.approx(100 * (2 / 3 + 1 / 4 + 15) / 17)
    assert r["IoU"]["1s"] == pytest.approx(100 * 80150 / 120600)
    # 2 s and 3 s see only the first two: ground TP 40000, FN 40000 -> 1/2; car TP 150, FN 150 -> 1/2;
    # 15 classes without ground truth -> 1: mIoU = 16 / 17; IoU = 40150 / 80300 = 1/2
    assert r["mIoU"]["2s"] == pytest.approx(100 * 16 / 17) and r["mIoU"]["3s"] == pytest.approx(100 * 16 / 17)
    assert r["IoU"]["2s"] == pytest.approx(50.0) and r["IoU"]["3s"] == pytest.approx(50.0)
    assert r["mIoU"]["avg"] == pytest.approx((r["mIoU"]["1s"] + 2 * 100 * 16 / 17) / 3)


def test_forecast_bad_input(hand_dataset, capsys, tmp_path):
    index = DatasetIndex.open(hand_dataset)
    scene = index.splits["val"][0]
    short = tmp_path / "short"
    atomic_write_npz(
        short / scene / index.scenes[scene][0] / "forecast.npz", {"semantics": np.zeros((4, 200, 200, 16), np.uint8)}
    )
    assert "holds 4 future frames" in one_line_error(capsys, "forecast", "--pred", short, "--gt", hand_dataset)
    stranger = tmp_path / "stranger"
    atomic_write_npz(
        stranger / scene / "not-a-token" / "forecast.npz", {"semantics": np.zeros((6, 200, 200, 16), np.uint8)}
    )
    assert "is not in the ground truth" in one_line_error(capsys, "forecast", "--pred", stranger, "--gt", hand_dataset)
    assert "dataset root" in one_line_error(capsys, "forecast", "--pred", short, "--gt", hand_dataset / "gts" / scene)


# ----------------------------------------------------------------------------- planning


def test_planning_hand_case(capsys, tmp_path):
    p, g = planning_files(tmp_path)
    code, r, _ = score(capsys, "planning", "--pred", p, "--gt", g)
    assert code == 0 and r["samples"] == 2 and r["samples_stp3"] == 1
    # L2 stp3: only tok-a (fully valid), 3 m everywhere
    assert r["L2_stp3"] == pytest.approx({"1s": 3.0, "2s": 3.0, "3s": 3.0, "avg": 3.0})
    # L2 uniad: (3 + 1) / 2 = 2 at waypoints 2 and 4; (3 + 0) / 2 = 1.5 at waypoint 6 (tok-b's is invalid)
    assert r["L2_uniad"] == pytest.approx({"1s": 2.0, "2s": 2.0, "3s": 1.5, "avg": 5.5 / 3})
    # collision, tok-a only (tok-b has no agents): the plan hits the box at step 1; at step 3 the gt hits too
    assert r["collision_uniad"] == pytest.approx({"1s": 100.0, "2s": 0.0, "3s": 0.0, "avg": 100 / 3})
    assert r["collision_stp3"] == pytest.approx({"1s": 50.0, "2s": 25.0, "3s": 100 / 6, "avg": (50 + 25 + 100 / 6) / 3})


def test_planning_bad_input(capsys, tmp_path):
    p, g = planning_files(tmp_path)
    preds = json.loads(p.read_text())
    extra = tmp_path / "extra.json"
    extra.write_text(json.dumps(preds | {"tok-z": straight()}))
    assert "sample tok-z is not in the ground truth" in one_line_error(capsys, "planning", "--pred", extra, "--gt", g)
    fewer = tmp_path / "fewer.json"
    fewer.write_text(json.dumps({"tok-a": preds["tok-a"]}))
    assert "no planned trajectory for sample tok-b" in one_line_error(capsys, "planning", "--pred", fewer, "--gt", g)
    code, r, _ = score(capsys, "planning", "--pred", fewer, "--gt", g, "--allow-missing")
    assert code == 0 and r["samples"] == 1
    short = tmp_path / "short.json"
    short.write_text(json.dumps(preds | {"tok-a": straight()[:5]}))
    assert "tok-a holds 5 items, expected a list of 6 lists of 2 numbers" in one_line_error(
        capsys, "planning", "--pred", short, "--gt", g
    )
    gts = json.loads(g.read_text())
    gts["tok-a"]["agents"][1] = [[5.0, 3.0, 2.0, 1.0]] * 5  # 4 numbers per box
    bad_agents = tmp_path / "bad_agents.json"
    bad_agents.write_text(json.dumps(gts))
    assert "tok-a.agents[1][0] holds 4 items, expected a list of 5 numbers" in one_line_error(
        capsys, "planning", "--pred", p, "--gt", bad_agents
    )
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    assert "is not valid JSON" in one_line_error(capsys, "planning", "--pred", broken, "--gt", g)
    assert "not found" in one_line_error(capsys, "planning", "--pred", tmp_path / "missing.json", "--gt", g)


# ----------------------------------------------------------------------------- captions


@pytest.mark.slow
@needs_java
def test_captions_identical_text_scores_one(capsys, tmp_path):
    text = {"a": "a red car waits at the traffic light", "b": "two pedestrians cross the road ahead of the ego car"}
    (tmp_path / "p.json").write_text(json.dumps(text))
    (tmp_path / "r.json").write_text(json.dumps({k: [v, "something else entirely"] for k, v in text.items()}))
    code, r, _ = score(capsys, "captions", "--pred", tmp_path / "p.json", "--ref", tmp_path / "r.json")
    assert code == 0
    assert list(r) == ["convention", "Bleu_1", "Bleu_2", "Bleu_3", "Bleu_4", "METEOR", "ROUGE_L", "CIDEr", "samples"]
    # each caption has itself among its references: BLEU (clipped counts) and ROUGE-L (max over refs) are 1
    assert [r[f"Bleu_{n}"] for n in (1, 2, 3, 4)] == pytest.approx([1.0] * 4)
    assert r["ROUGE_L"] == pytest.approx(1.0)
    assert r["samples"] == 2


def test_captions_bad_input(capsys, tmp_path):
    (tmp_path / "p.json").write_text(json.dumps({"a": "x", "z": "y"}))
    (tmp_path / "r.json").write_text(json.dumps({"a": ["x"], "b": ["y"]}))
    assert "id z has no references" in one_line_error(
        capsys, "captions", "--pred", tmp_path / "p.json", "--ref", tmp_path / "r.json"
    )
    (tmp_path / "p.json").write_text(json.dumps({"a": "x"}))
    assert "no caption for sample b" in one_line_error(
        capsys, "captions", "--pred", tmp_path / "p.json", "--ref", tmp_path / "r.json"
    )
    (tmp_path / "p.json").write_text(json.dumps(["x"]))
    assert "expected a JSON object" in one_line_error(
        capsys, "captions", "--pred", tmp_path / "p.json", "--ref", tmp_path / "r.json"
    )


# ----------------------------------------------------------------------------- QA


def test_qa_hand_case(capsys, tmp_path):
    q = qa_questions(tmp_path / "q.json")
    (tmp_path / "p.json").write_text(json.dumps(["yes", "2", "one", "car"]))
    code, r, _ = score(capsys, "qa", "--pred", tmp_path / "p.json", "--questions", q)
    # correct: yes, 2, car; "one" is not "1": overall 3/4; count 1/2 (H0 right, H1 wrong)
    assert code == 0 and r["questions"] == 4
    assert r["overall"] == pytest.approx(75.0)
    assert r["by_type"] == pytest.approx({"exist": 100.0, "count": 50.0, "object": 100.0})
    assert r["by_type_hop"] == pytest.approx(
        {"exist_H0": 100.0, "count_H0": 100.0, "count_H1": 0.0, "object_H1": 100.0}
    )


def test_qa_bad_input(capsys, tmp_path):
    q = qa_questions(tmp_path / "q.json")
    (tmp_path / "p.json").write_text(json.dumps(["yes", "2"]))
    assert "holds 2 answers but" in one_line_error(capsys, "qa", "--pred", tmp_path / "p.json", "--questions", q)
    (tmp_path / "p.json").write_text(json.dumps({"0": "yes"}))
    assert "expected a JSON list" in one_line_error(capsys, "qa", "--pred", tmp_path / "p.json", "--questions", q)
    (tmp_path / "q2.json").write_text(json.dumps([]))
    assert "NuScenes-QA format" in one_line_error(
        capsys, "qa", "--pred", tmp_path / "p.json", "--questions", tmp_path / "q2.json"
    )


def test_version(capsys):
    from occtrain import __version__

    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0 and capsys.readouterr().out.strip() == f"occtrain {__version__}"
