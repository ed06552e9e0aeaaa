"""The language releases, each written by hand in its own layout and key names, joined to a
small dataset by sample token: what is matched, unmatched and skipped, and where it lands."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import hand_frames, write_hand_dataset
from occtrain.data.layout import DatasetIndex
from occtrain.data.releases.text_import import import_drivelm, import_nuscenes_qa, import_omnidrive
from occtrain.errors import DataError

#: write_hand_dataset(train=1, val=1, frames=3): scene s is seeded with s.
TRAIN = [f["token"] for f in hand_frames("scene-0000", 3, 0)]
VAL = [f["token"] for f in hand_frames("scene-0001", 3, 1)]
STRANGER = "0" * 32


@pytest.fixture
def ds(tmp_path: Path) -> Path:
    return write_hand_dataset(tmp_path / "ds", train=1, val=1, frames=3)


def put(path: Path, data: object) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


def test_omnidrive(ds: Path, tmp_path: Path) -> None:
    src = tmp_path / "OmniDrive"
    put(src / "desc" / "train" / f"{TRAIN[0]}.json", {"description": "A wet road; a bus waits at the stop."})
    put(src / "desc" / "val" / f"{VAL[1]}.json", {"description": "Night, an empty junction."})
    put(src / "desc" / "train" / f"{TRAIN[1]}.json", {"description": "  "})  # skipped: empty
    put(src / "desc" / "val" / f"{TRAIN[2]}.json", {"description": "x"})  # skipped: the dataset's train split
    put(src / "desc" / "train" / f"{STRANGER}.json", {"description": "elsewhere"})  # unmatched
    put(src / "conv" / "train" / f"{TRAIN[0]}.json", [{"question": "Is it safe?", "answer": "Yes.", "extra": 1}])
    put(src / "vqa" / "val" / f"{VAL[1]}.json", [{"question": "What is ahead?", "answer": "A junction."}])
    put(src / "keywords" / "val" / f"{VAL[1]}.json", "slow down")
    report = import_omnidrive(src, ds)
    assert (report.matched, report.unmatched, report.skipped) == (5, 1, 2)
    assert report.unmatched_examples == [STRANGER]
    assert report.line().startswith("omnidrive: 5 matched, 1 unmatched, 2 skipped (report: ")
    index = DatasetIndex.open(ds)
    assert index.frames("scene-0000")[0]["caption"] == "A wet road; a bus waits at the stop."
    assert index.frames("scene-0000")[1]["caption"] == "caption 1"  # the skipped one left as it was
    assert index.frames("scene-0001")[1]["caption"] == "Night, an empty junction."
    assert json.loads((ds / "omnidrive" / "conv" / "train" / f"{TRAIN[0]}.json").read_text())[0]["extra"] == 1
    assert json.loads((ds / "omnidrive" / "keywords" / "val" / f"{VAL[1]}.json").read_text()) == "slow down"
    assert not (ds / "omnidrive" / "desc" / "train" / f"{STRANGER}.json").exists()
    saved = json.loads((ds / "occtrain" / "imports" / "omnidrive.json").read_text())
    assert saved["skipped_why"] == {"desc: empty": 1, "desc: release split is not the dataset's": 1}
    from occtrain.families.sparseoccvla.omnidrive import OmniDriveText  # what SparseOccVLA's tasks read

    assert OmniDriveText(ds / "omnidrive").pairs(VAL[1]) == [{"question": "What is ahead?", "answer": "A junction."}]


def test_omnidrive_refuses_a_folder_that_is_not_one(ds: Path, tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="not an OmniDrive-nuScenes root"):
        import_omnidrive(tmp_path / "empty", ds)


def test_drivelm(ds: Path, tmp_path: Path) -> None:
    qa = {
        "perception": [{"Q": "What are the important objects?", "A": "A car ahead.", "C": None, "con_up": []}],
        "prediction": [],
        "planning": [{"Q": "What should the ego do?", "A": "Keep going."}],
        "behavior": [{"Q": "Predict the behavior of the ego vehicle.", "A": "The ego vehicle is going straight."}],
    }
    data = {
        "scene-token-a": {
            "scene_description": "a street",
            "key_frames": {
                TRAIN[0]: {"key_object_infos": {}, "QA": qa, "image_paths": {}},
                VAL[2]: {"QA": {"perception": qa["perception"]}},
                TRAIN[1]: {"QA": {"perception": [], "behavior": []}},  # skipped: no QA
            },
        },
        "scene-token-b": {"key_frames": {STRANGER: {"QA": qa}}},  # unmatched
    }
    put(tmp_path / "v1_1_train_nus.json", data)
    report = import_drivelm(tmp_path / "v1_1_train_nus.json", ds)
    assert (report.matched, report.unmatched, report.skipped) == (2, 1, 1)
    train = json.loads((ds / "drivelm" / "DriveLM_train_qa.json").read_text())["frames"]
    val = json.loads((ds / "drivelm" / "DriveLM_val_qa.json").read_text())["frames"]
    assert train == {TRAIN[0]: qa}  # items verbatim, extra keys and all
    assert val[VAL[2]] == {"perception": qa["perception"], "prediction": [], "planning": [], "behavior": []}
    # A second file merges into what the first wrote.
    put(tmp_path / "v1_1_val_nus.json", {"s": {"key_frames": {VAL[0]: {"QA": {"behavior": qa["behavior"]}}}}})
    import_drivelm(tmp_path / "v1_1_val_nus.json", ds)
    val = json.loads((ds / "drivelm" / "DriveLM_val_qa.json").read_text())["frames"]
    assert set(val) == {VAL[0], VAL[2]}
    assert (ds / "occtrain" / "imports" / "drivelm-v1_1_val_nus.json").is_file()


def test_drivelm_refuses_a_category_it_does_not_define(ds: Path, tmp_path: Path) -> None:
    put(tmp_path / "d.json", {"s": {"key_frames": {TRAIN[0]: {"QA": {"perceptions": []}}}}})
    with pytest.raises(DataError, match=r"s\.key_frames\.\w+\.QA\.perceptions is not a DriveLM category"):
        import_drivelm(tmp_path / "d.json", ds)


def question(token: str, answer: str = "yes", template: str = "exist") -> dict:
    return {
        "sample_token": token,
        "question": "Are there any cars?",
        "answer": answer,
        "num_hop": 0,
        "template_type": template,
        "scene_token": "s",  # NuScenes-QA's files carry more keys than occtrain reads
    }


def test_nuscenes_qa(ds: Path, tmp_path: Path) -> None:
    src = tmp_path / "questions"
    put(
        src / "NuScenes_train_questions.json", {"info": {}, "questions": [question(TRAIN[0], "no"), question(STRANGER)]}
    )
    put(
        src / "NuScenes_val_questions.json",
        {"questions": [question(VAL[0], "2", "count"), question(TRAIN[1])]},  # the second: dataset's train split
    )
    report = import_nuscenes_qa(src, ds)
    assert (report.matched, report.unmatched, report.skipped) == (2, 1, 1)
    index = DatasetIndex.open(ds)
    assert [q["answer"] for q in index.questions("train")] == ["no"]
    assert index.questions("val") == [
        {
            "question": "Are there any cars?",
            "answer": "2",
            "sample_token": VAL[0],
            "template_type": "count",
            "num_hop": 0,
        }
    ]
    # One split's file alone replaces that split's questions and leaves the other's.
    put(tmp_path / "NuScenes_val_questions.json", {"questions": [question(VAL[2])]})
    import_nuscenes_qa(tmp_path / "NuScenes_val_questions.json", ds)
    assert [q["sample_token"] for q in DatasetIndex.open(ds).questions("val")] == [VAL[2]]
    assert len(DatasetIndex.open(ds).questions("train")) == 1


def test_nuscenes_qa_names_the_bad_key(ds: Path, tmp_path: Path) -> None:
    put(
        tmp_path / "NuScenes_train_questions.json",
        {"questions": [question(TRAIN[0]), {**question(TRAIN[1]), "num_hop": 2}]},
    )
    with pytest.raises(DataError, match=r"questions\[1\]\.num_hop"):
        import_nuscenes_qa(tmp_path / "NuScenes_train_questions.json", ds)
    assert [q["answer"] for q in DatasetIndex.open(ds).questions("train")] == ["yes"] * 3  # unchanged
