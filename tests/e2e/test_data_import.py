"""The public releases in and out, through the CLI in-process: a tiny synthesized world is
exported as nuScenes v1.0 tables (+ CAN bus), the Occ3D layout, OmniDrive, DriveLM and
NuScenes-QA, imported back, and the import reproduces the world's own sidecars (boxes to
1 cm, meta actions exactly, the commands ST-P3's rule gives on the world's future, captions
and QA verbatim; the road context, which needs a map, stays absent). Then determinism,
resuming, and bad input under the contract of tests/e2e/test_bad_inputs.py: one line on
stderr ``error: ...`` naming the file and key (exit 2), no traceback, nothing that existed
changed and nothing created."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from builders import snapshot
from occtrain.cli import main
from occtrain.data.geometry import driving_command
from occtrain.data.layout import DatasetIndex
from occtrain.data.releases.nuscenes_import import ABSENT
from occtrain.formats.occ3d import FUTURE_STEPS

VERSION = "v1.0-trainval"


def cli(*argv: str) -> int:
    try:
        return main([str(a) for a in argv])
    except SystemExit as exit_:  # argparse
        return int(exit_.code or 0)


def import_all(rel: Path, ds: Path) -> None:
    """Every importer, as a user runs them, from an exported release into ``ds``."""
    nus = ["--nuscenes", rel / "nuscenes", "--version", VERSION, "--occ3d", rel / "occ3d"]
    assert cli("data", "import", "nuscenes", *nus, "--out", ds) == 0
    assert cli("data", "import", "omnidrive", rel / "omnidrive", "--into", ds) == 0
    assert cli("data", "import", "nuscenes-qa", rel / "nuscenes_qa", "--into", ds) == 0
    for split in ("train", "val"):
        assert cli("data", "import", "drivelm", rel / "drivelm" / f"v1_1_{split}_nus.json", "--into", ds) == 0


@pytest.fixture(scope="module")
def trip(synth_dataset: Path, tmp_path_factory) -> Path:
    """The session's tiny world (2 train + 1 val scenes of 12 frames) exported to rel/ and imported to ds/."""
    root = tmp_path_factory.mktemp("trip")
    assert cli("data", "export", "nuscenes", synth_dataset, "--out", root / "rel") == 0
    import_all(root / "rel", root / "ds")
    return root


def full_window(i: int, n: int) -> bool:
    """Whether frame ``i`` of ``n`` sees the 3 s its meta action looks ahead inside the scene."""
    return i + FUTURE_STEPS <= n - 1


# ----------------------------------------------------------------------------- the round trip


def test_the_round_trip_reproduces_the_worlds_sidecars(synth_dataset: Path, trip: Path) -> None:
    world, back = DatasetIndex.open(synth_dataset), DatasetIndex.open(trip / "ds")
    assert back.splits == world.splits and back.scenes == world.scenes
    velocity_errors = []
    for scene in world.scenes:
        ours, theirs = world.frames(scene), back.frames(scene)
        tracks: dict[int, int] = {}
        for i, (w, b) in enumerate(zip(ours, theirs)):
            for key in ("scene", "token", "index", "timestamp", "ego_future_mask", "ego_past_mask"):
                assert b[key] == w[key], (scene, i, key)
            # The world's command comes from its route, which no release holds: an import takes
            # it from the logged future poses, as ST-P3 does, and so does this check.
            assert b["command"] == driving_command(np.asarray(w["ego_future"]), w["ego_future_mask"]), (scene, i)
            assert "road" in w and "road" not in b  # a map and a tracker would give it: the import has neither
            if full_window(i, len(ours)):  # nearer the end the world saw past it, a release does not
                assert b["meta_action"] == w["meta_action"], (scene, i)
            assert b["ego_speed"] == w["ego_speed"] and b["ego_yaw_rate"] == w["ego_yaw_rate"]  # the CAN bus
            assert b["ego_accel"] == pytest.approx(w["ego_accel"], abs=2e-3)  # from 0.1 mm poses
            for key in ("ego_future", "ego_past"):
                assert np.allclose(b[key], w[key], atol=1e-3), (scene, i, key)
            assert b["ego_pose"]["translation"] == w["ego_pose"]["translation"]
            # Headings along -x read as pi or -pi, whichever the rounding of each side lands on.
            assert np.angle(np.exp(1j * (b["ego_pose"]["yaw"] - w["ego_pose"]["yaw"]))) == pytest.approx(0, abs=1e-6)
            assert len(b["boxes"]) == len(w["boxes"]), (scene, i)
            for wb, bb, wf, bf, wm, bm in zip(
                w["boxes"],
                b["boxes"],
                w["agent_futures"],
                b["agent_futures"],
                w["agent_future_mask"],
                b["agent_future_mask"],
            ):
                assert tracks.setdefault(wb["track_id"], bb["track_id"]) == bb["track_id"]  # one id per track
                assert (bb["category"], bb["attribute"]) == (wb["category"], wb["attribute"])
                assert np.allclose(bb["center"], wb["center"], atol=0.01) and np.allclose(
                    bb["size"], wb["size"], atol=0.01
                )
                assert np.angle(np.exp(1j * (bb["yaw"] - wb["yaw"]))) == pytest.approx(0, abs=1e-3)
                assert bm == wm and np.allclose(
                    np.asarray(bf)[np.asarray(bm, bool)], np.asarray(wf)[np.asarray(wm, bool)], atol=0.01
                )
                velocity_errors.append(float(np.linalg.norm(np.subtract(bb["velocity"], wb["velocity"]))))
            assert b["caption"] == w["caption"]  # OmniDrive's desc
            assert b["narration"] == ""  # no release holds it
        assert len(set(tracks.values())) == len(tracks)  # distinct tracks stay distinct
    for split in ("train", "val"):
        assert back.questions(split) == world.questions(split)
    # nuScenes has no velocities: the import derives them from the instance's neighbouring
    # annotations (the devkit's rule), the world's are the simulator's, so they agree only
    # where the motion is steady over a second.
    errors = np.asarray(velocity_errors)
    assert np.median(errors) < 0.01 and np.mean(errors < 0.5) > 0.97, np.percentile(errors, [50, 95, 99, 100])


def test_the_record_says_what_an_import_leaves_absent_and_the_tasks_follow(trip: Path) -> None:
    rel, ds = trip / "rel", trip / "ds"
    before = snapshot(ds)  # imported again: nothing to do, and the captions stay present
    assert cli("data", "import", "nuscenes", "--nuscenes", rel / "nuscenes", "--occ3d", rel / "occ3d", "--out", ds) == 0
    assert snapshot(ds) == before
    record = json.loads((trip / "ds" / "occtrain" / "dataset.json").read_text())
    assert record["generator"] == "occtrain.import.nuscenes" and record["nuscenes_version"] == VERSION
    assert set(record["absent"]) == set(ABSENT) - {"caption"}  # the OmniDrive import brought the captions
    tasks = DatasetIndex.open(trip / "ds").available_tasks()
    assert "narration" in tasks["chain_of_thought"] and tasks["caption"] == "" and tasks["qa"] == ""
    assert tasks["detection"] == tasks["meta_action"] == tasks["planning"] == ""


def test_drivelm_and_omnidrive_come_back_as_exported(trip: Path) -> None:
    rel, ds = trip / "rel", trip / "ds"
    for split in ("train", "val"):
        exported = json.loads((rel / "drivelm" / f"v1_1_{split}_nus.json").read_text())
        imported = json.loads((ds / "drivelm" / f"DriveLM_{split}_qa.json").read_text())["frames"]
        frames = {tok: f["QA"] for scene in exported.values() for tok, f in scene["key_frames"].items()}
        assert imported == frames
        report = json.loads((ds / "occtrain" / "imports" / f"drivelm-v1_1_{split}_nus.json").read_text())
        assert report["matched"] == len(frames) and report["unmatched"] == report["skipped"] == 0
    for path in sorted((rel / "omnidrive").rglob("*.json")):
        assert json.loads((ds / "omnidrive" / path.relative_to(rel / "omnidrive")).read_text()) == json.loads(
            path.read_text()
        )
    from occtrain.families.sparseoccvla.omnidrive import OmniDriveText  # the reader SparseOccVLA's tasks use

    index = DatasetIndex.open(ds)
    scene = index.splits["val"][0]
    frame = index.frames(scene)[0]
    assert OmniDriveText(ds / "omnidrive").description(frame["token"]) == frame["caption"]


def test_an_import_is_deterministic_resumes_and_refuses_another_release(trip: Path, tmp_path: Path) -> None:
    rel, first = trip / "rel", trip / "ds"
    nus = ["--nuscenes", rel / "nuscenes", "--version", VERSION, "--occ3d", rel / "occ3d"]
    again = tmp_path / "again"
    assert cli("data", "import", "nuscenes", *nus, "--out", again) == 0
    frames = sorted(p.name for p in (again / "occtrain" / "frames").iterdir())
    for name in frames:  # the first import's sidecars carry the OmniDrive captions: compare the rest
        a = json.loads((again / "occtrain" / "frames" / name).read_text())
        b = json.loads((first / "occtrain" / "frames" / name).read_text())
        assert [dict(f, caption="") for f in a] == [dict(f, caption="") for f in b]
    # Cut off after the first scene: its sidecar stays, the rest is written again, the same.
    before = snapshot(again)
    (again / "annotations.json").unlink()
    for name in frames[1:]:
        (again / "occtrain" / "frames" / name).unlink()
    assert cli("data", "import", "nuscenes", *nus, "--out", again) == 0
    assert snapshot(again) == before
    # Another release into the same directory is refused.
    other = tmp_path / "other-nuscenes"
    shutil.copytree(rel / "nuscenes", other, symlinks=True)
    assert cli("data", "import", "nuscenes", "--nuscenes", other, "--occ3d", rel / "occ3d", "--out", again) == 2
    assert snapshot(again) == before


def test_data_check_passes_on_the_import(trip: Path, capsys) -> None:
    assert cli("data", "check", trip / "ds") == 0
    assert capsys.readouterr().out.strip().endswith(": ok")


# ----------------------------------------------------------------------------- the real recipes


@pytest.fixture(scope="module")
def long_trip(tmp_path_factory) -> Path:
    """A world of 1 train + 1 val scene of 14 frames (OccVLA's clips span 6 + 1 + 6),
    exported and imported with its text: a tiny imported release."""
    from occtrain.config import SynthConfig
    from occtrain.data.synthesize import synthesize

    root = tmp_path_factory.mktemp("long")
    synthesize(root / "world", SynthConfig(train_scenes=1, val_scenes=1, frames_per_scene=14, seed=2), verbose=False)
    assert cli("data", "export", "nuscenes", root / "world", "--out", root / "rel") == 0
    import_all(root / "rel", root / "ds")
    return root / "ds"


@pytest.mark.parametrize("family", ["occllama", "occvla", "occllm", "sparseoccvla"])
def test_the_real_recipes_validate_on_an_imported_release(family: str, long_trip: Path, capsys, monkeypatch) -> None:
    from conftest import REPO

    monkeypatch.chdir(REPO)
    capsys.readouterr()
    assert cli("validate", f"recipes/real/{family}.yaml", f"data.root={long_trip}") == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert f"recipes/real/{family}.yaml: ok" in out and str(long_trip) in out


def test_a_real_recipe_weighting_the_narration_is_refused_on_an_import(long_trip: Path, capsys, monkeypatch) -> None:
    from conftest import REPO

    monkeypatch.chdir(REPO)
    capsys.readouterr()
    weight = "stages.instruct.model.tasks.weights.cot_planning=1"
    assert cli("validate", "recipes/real/occllama.yaml", f"data.root={long_trip}", weight) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: task cot_planning needs the frames' narration") and err.count("\n") == 1


# ----------------------------------------------------------------------------- bad input


@dataclass(frozen=True)
class Case:
    id: str
    setup: Callable[[Path], None]
    argv: list[str]
    says: tuple[str, ...]


NUS = ["data", "import", "nuscenes", "--nuscenes", "{tmp}/rel/nuscenes", "--version", VERSION]
IMPORT = [*NUS, "--occ3d", "{tmp}/rel/occ3d", "--out", "{tmp}/out"]
TABLES = "{tmp}/rel/nuscenes/" + VERSION


def edit(rel: str, change: Callable[[Any], Any]) -> Callable[[Path], None]:
    def setup(tmp: Path) -> None:
        path = tmp / rel
        data = json.loads(path.read_text())
        change(data)
        path.write_text(json.dumps(data))

    return setup


def _rename_sample(ann: dict) -> None:
    scene = ann["val_split"][0]
    infos = ann["scene_infos"][scene]
    order = list(infos)
    old, new = order[2], "f" * 32
    infos[new] = infos.pop(old)
    infos[order[1]]["next"] = new
    infos[order[3]]["prev"] = new


def _drop_lidar_pose(tmp: Path) -> None:
    """Remove the ego pose of a LIDAR_TOP key frame (the pose the import reads for its sample)."""
    rows = json.loads((tmp / f"rel/nuscenes/{VERSION}/sample_data.json").read_text())
    lidar = next(r for r in rows if r["filename"].startswith("samples/LIDAR_TOP/"))
    edit(
        f"rel/nuscenes/{VERSION}/ego_pose.json",
        lambda poses: poses.remove(next(p for p in poses if p["token"] == lidar["ego_pose_token"])),
    )(tmp)


def _drop_key_frame(tmp: Path) -> None:
    edit(
        f"rel/nuscenes/{VERSION}/sample_data.json",
        lambda rows: rows.remove(next(r for r in rows if r["filename"].startswith("samples/LIDAR_TOP/"))),
    )(tmp)


def _zero_quaternion(rows: list) -> None:
    rows[3]["rotation"] = [0.0, 0.0, 0.0, 0.0]


def write(rel: str, text: str) -> Callable[[Path], None]:
    return lambda tmp: (tmp / rel).write_text(text)


def remove(rel: str) -> Callable[[Path], None]:
    return lambda tmp: (tmp / rel).unlink()


CASES = [
    Case(
        "missing table",
        remove(f"rel/nuscenes/{VERSION}/ego_pose.json"),
        IMPORT,
        (f"{TABLES}/ego_pose.json", "not found"),
    ),
    Case(
        "unknown version",
        lambda tmp: None,
        [*NUS[:-1], "v1.0-test", "--occ3d", "{tmp}/rel/occ3d", "--out", "{tmp}/out"],
        ("--version v1.0-test", "v1.0-mini or v1.0-trainval"),
    ),
    Case(
        "missing version",
        lambda tmp: None,
        [
            "data",
            "import",
            "nuscenes",
            "--nuscenes",
            "{tmp}/rel/nuscenes",
            "--version",
            "v1.0-mini",
            "--occ3d",
            "{tmp}/rel/occ3d",
            "--out",
            "{tmp}/out",
        ],
        ("{tmp}/rel/nuscenes/v1.0-mini", "v1.0-trainval"),
    ),
    Case(
        "missing split",
        edit("rel/occ3d/annotations.json", lambda a: a.pop("val_split")),
        IMPORT,
        ("annotations.json", "'val_split'"),
    ),
    Case(
        "mismatched tokens",
        edit("rel/occ3d/annotations.json", _rename_sample),
        IMPORT,
        ("annotations.json", "f" * 32, "frame 2"),
    ),
    Case(
        "broken JSON",
        write(f"rel/nuscenes/{VERSION}/sample_annotation.json", '[{"token": '),
        IMPORT,
        (f"{TABLES}/sample_annotation.json", "not valid JSON"),
    ),
    Case(
        "sample without an ego pose",
        _drop_lidar_pose,
        IMPORT,
        (f"{TABLES}/sample_data.json", "ego_pose_token", "not in ego_pose.json"),
    ),
    Case(
        "sample without a lidar key frame",
        _drop_key_frame,
        IMPORT,
        (f"{TABLES}/sample_data.json", "no key-frame LIDAR_TOP"),
    ),
    Case(
        "box with a zero quaternion",
        edit(f"rel/nuscenes/{VERSION}/sample_annotation.json", _zero_quaternion),
        IMPORT,
        (f"{TABLES}/sample_annotation.json", ".rotation", "zero quaternion"),
    ),
    Case(
        "a record missing a key",
        edit(f"rel/nuscenes/{VERSION}/sample.json", lambda rows: rows[1].pop("timestamp")),
        IMPORT,
        (f"{TABLES}/sample.json", "[1]", "timestamp"),
    ),
    Case(
        "a dangling reference",
        edit(f"rel/nuscenes/{VERSION}/instance.json", lambda rows: rows[0].update(category_token="nope")),
        IMPORT,
        (f"{TABLES}/instance.json", "category_token 'nope'"),
    ),
    Case(
        "labels missing",
        lambda tmp: shutil.rmtree(tmp / "rel" / "occ3d" / "gts") or (tmp / "rel" / "occ3d" / "gts").mkdir(),
        IMPORT,
        ("labels.npz", "gt_path"),
    ),
    Case(
        "omnidrive broken JSON",
        lambda tmp: write(str(next((tmp / "rel/omnidrive/desc/val").iterdir()).relative_to(tmp)), "{")(tmp),
        ["data", "import", "omnidrive", "{tmp}/rel/omnidrive", "--into", "{tmp}/ds"],
        ("{tmp}/rel/omnidrive/desc/val/", "not valid JSON"),
    ),
    Case(
        "omnidrive pair without an answer",
        lambda tmp: write(
            str(next((tmp / "rel/omnidrive/vqa/train").iterdir()).relative_to(tmp)), '[{"question": "q"}]'
        )(tmp),
        ["data", "import", "omnidrive", "{tmp}/rel/omnidrive", "--into", "{tmp}/ds"],
        ("{tmp}/rel/omnidrive/vqa/train/", "answer"),
    ),
    Case(
        "drivelm item without an answer",
        edit(
            "rel/drivelm/v1_1_val_nus.json",
            lambda d: next(iter(next(iter(d.values()))["key_frames"].values()))["QA"]["behavior"][0].pop("A"),
        ),
        ["data", "import", "drivelm", "{tmp}/rel/drivelm/v1_1_val_nus.json", "--into", "{tmp}/ds"],
        ("v1_1_val_nus.json", "QA.behavior[0].A is missing"),
    ),
    Case(
        "nuscenes-qa bad template",
        edit("rel/nuscenes_qa/NuScenes_val_questions.json", lambda d: d["questions"][4].update(template_type="color")),
        ["data", "import", "nuscenes-qa", "{tmp}/rel/nuscenes_qa", "--into", "{tmp}/ds"],
        ("NuScenes_val_questions.json", "questions[4].template_type"),
    ),
    Case(
        "nuscenes-qa renamed file",
        lambda tmp: (tmp / "rel/nuscenes_qa/NuScenes_val_questions.json").rename(tmp / "rel/nuscenes_qa/val.json"),
        ["data", "import", "nuscenes-qa", "{tmp}/rel/nuscenes_qa/val.json", "--into", "{tmp}/ds"],
        ("val.json", "NuScenes_<split>_questions.json"),
    ),
    Case(
        "export into a full directory",
        lambda tmp: None,
        ["data", "export", "nuscenes", "{tmp}/ds", "--out", "{tmp}/rel"],
        ("{tmp}/rel", "not empty"),
    ),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_is_one_line_and_changes_nothing(case: Case, trip: Path, tmp_path: Path, capsys) -> None:
    shutil.copytree(trip / "rel", tmp_path / "rel", symlinks=True)
    shutil.copytree(trip / "ds", tmp_path / "ds", symlinks=True)
    case.setup(tmp_path)
    before = snapshot(tmp_path)
    capsys.readouterr()
    code = cli(*(a.format(tmp=tmp_path) for a in case.argv))
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    assert code == 2, out + err
    assert err.startswith("error: ") and err.endswith("\n") and err.count("\n") == 1, err
    assert all(s.format(tmp=tmp_path) in err for s in case.says), err
    assert out == ""
    assert snapshot(tmp_path) == before


def test_the_table_covers_the_issues_cases() -> None:
    ids = {c.id for c in CASES}
    assert len(ids) == len(CASES)
    wanted = {
        "missing table",
        "missing split",
        "mismatched tokens",
        "broken JSON",
        "sample without an ego pose",
        "box with a zero quaternion",
    }
    assert wanted <= ids
