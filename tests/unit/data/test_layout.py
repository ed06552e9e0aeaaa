"""The Occ3D layout: a real-format directory built by hand, round trips, and bad input."""

import json
import math

import numpy as np
import pytest

from conftest import hand_labels, write_hand_dataset
from occtrain.data.dataset_writer import DatasetWriter
from occtrain.data.labels import load_labels
from occtrain.data.layout import DatasetIndex
from occtrain.data.poses import quaternion_from_yaw, yaw_from_quaternion
from occtrain.errors import DataError
from occtrain.formats.occ3d import GRID_SHAPE


def make_real_format(root, tokens=("t2", "t0", "t1")):
    """What an Occ3D-nuScenes download looks like: annotations.json + gts, no occtrain sidecars.

    Tokens are deliberately listed out of time order: the reader must follow prev/next.
    """
    order = ["t0", "t1", "t2"]
    infos = {}
    for tok in tokens:
        i = order.index(tok)
        infos[tok] = {
            "timestamp": 1_000_000 + 500_000 * i,
            "ego_pose": {"translation": [10.0 * i, 2.0, 0.0], "rotation": quaternion_from_yaw(0.25 * i)},
            "prev": order[i - 1] if i else "",
            "next": order[i + 1] if i + 1 < len(order) else "",
            "gt_path": f"gts/scene-0061/{tok}/labels.npz",
        }
        path = root / "gts" / "scene-0061" / tok / "labels.npz"
        path.parent.mkdir(parents=True)
        np.savez_compressed(path, **hand_labels(i))
    (root / "annotations.json").write_text(
        json.dumps({"train_split": ["scene-0061"], "val_split": [], "scene_infos": {"scene-0061": infos}})
    )
    return root


def test_reads_hand_built_real_format(tmp_path):
    ds = DatasetIndex.open(make_real_format(tmp_path))
    assert ds.scenes == {"scene-0061": ["t0", "t1", "t2"]}
    assert ds.splits == {"train": ["scene-0061"], "val": []}
    x, y, yaw = ds.ego_pose("scene-0061", "t2")
    assert (x, y) == (20.0, 2.0) and yaw == pytest.approx(0.5)
    lab = ds.labels("scene-0061", "t1")
    assert lab["semantics"].shape == GRID_SHAPE and lab["mask_camera"].dtype == np.uint8
    # No sidecars: the reader says which tasks that rules out.
    tasks = ds.available_tasks()
    assert tasks["reconstruction"] == "" and tasks["forecasting"] == ""
    assert "sidecar" in tasks["detection"] and "NuScenes_<split>_questions.json" in tasks["qa"]
    assert ds.questions("train") is None
    with pytest.raises(DataError, match="no frame annotations"):
        ds.frames("scene-0061")


def test_opening_the_gts_dir_finds_the_root(tmp_path):
    make_real_format(tmp_path)
    assert DatasetIndex.open(tmp_path / "gts").root == tmp_path


def test_quaternion_yaw_round_trip():
    for yaw in (-3.0, -1.0, 0.0, 0.7, 3.1):
        assert yaw_from_quaternion(quaternion_from_yaw(yaw)) == pytest.approx(yaw)
    # nuScenes stores (w, x, y, z): a quarter turn to the left about +z, and one eighth.
    assert quaternion_from_yaw(math.pi / 2) == pytest.approx([math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)])
    assert yaw_from_quaternion([math.cos(math.pi / 8), 0.0, 0.0, math.sin(math.pi / 8)]) == pytest.approx(math.pi / 4)
    # With a little roll and pitch, as a real ego pose has: the heading is still about 2 atan2(z, w).
    assert yaw_from_quaternion([0.8738, -0.0046, 0.0040, -0.4862]) == pytest.approx(
        2 * math.atan2(-0.4862, 0.8738), abs=2e-4
    )


def test_writer_round_trip(tmp_path):
    root = write_hand_dataset(tmp_path / "ds", train=2, val=1, frames=5)
    ds = DatasetIndex.open(root)
    assert ds.splits == {"train": ["scene-0000", "scene-0001"], "val": ["scene-0002"]}
    frames = ds.frames("scene-0002")
    assert [f["token"] for f in frames] == ds.scenes["scene-0002"]
    assert len(ds.questions("val")) == 5
    assert all(v == "" for v in ds.available_tasks().values())


@pytest.mark.parametrize(
    "arrays, message",
    [
        ({"semantics": np.zeros((200, 200, 8), np.uint8)}, "has shape (200, 200, 8)"),
        ({"semantics": np.zeros(GRID_SHAPE, np.int64)}, "dtype int64, expected uint8"),
        ({"semantics": np.full(GRID_SHAPE, 18, np.uint8)}, "holds class 18"),
        ({"semantics": np.zeros(GRID_SHAPE, np.uint8)}, "missing array 'mask_lidar'"),
    ],
)
def test_bad_labels_name_the_file(tmp_path, arrays, message):
    path = tmp_path / "labels.npz"
    np.savez(path, **arrays)
    with pytest.raises(DataError) as err:
        load_labels(path)
    assert str(path) in str(err.value) and message in str(err.value)


def test_object_array_is_refused_not_unpickled(tmp_path):
    path = tmp_path / "labels.npz"
    np.savez(path, semantics=np.array([{"evil": 1}], dtype=object))
    with pytest.raises(DataError, match="pickled"):
        load_labels(path)


def test_a_header_claiming_a_huge_array_is_refused_before_anything_is_inflated(tmp_path):
    """A labels.npz of a few hundred bytes whose 'semantics' header claims 640 MB: refused
    from the header, without allocating the array (numpy reports its allocations to tracemalloc)."""
    import io
    import tracemalloc
    import zipfile

    path = tmp_path / "labels.npz"
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "|u1", "fortran_order": False, "shape": (2000, 2000, 160)})
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("semantics.npy", header.getvalue() + bytes(64))
    tracemalloc.start()
    try:
        with pytest.raises(DataError) as err:
            load_labels(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert str(err.value) == f"{path}: 'semantics' has shape (2000, 2000, 160), expected (200, 200, 16)"
    assert peak < 16 * 2**20, f"{peak / 2**20:.0f} MB allocated to refuse it"


def test_truncated_npz(tmp_path):
    path = tmp_path / "labels.npz"
    np.savez_compressed(path, **hand_labels(0))
    path.write_bytes(path.read_bytes()[:300])
    with pytest.raises(DataError, match="corrupt or truncated"):
        load_labels(path)


def test_missing_annotations_and_bad_qa(tmp_path):
    (tmp_path / "gts").mkdir()
    with pytest.raises(DataError, match="annotations.json: annotations file not found"):
        DatasetIndex.open(tmp_path)
    root = write_hand_dataset(tmp_path / "ds", train=1, val=1, frames=3)
    (root / "nuscenes_qa/NuScenes_val_questions.json").write_text("{not json")
    with pytest.raises(DataError, match="NuScenes_val_questions.json: not valid JSON"):
        DatasetIndex.open(root).questions("val")
    (root / "nuscenes_qa/NuScenes_val_questions.json").write_text('{"questions": [{"question": "q"}]}')
    with pytest.raises(DataError, match=r"questions\[0\]\.answer is missing, expected a string"):
        DatasetIndex.open(root).questions("val")


def test_writer_refuses_a_different_dataset(tmp_path):
    root = write_hand_dataset(tmp_path / "ds", train=1, val=1, frames=3)
    before = (root / "annotations.json").read_bytes()
    with pytest.raises(DataError, match="already holds a different dataset"):
        DatasetWriter(root, {"generator": "tests", "train": 9, "val": 1, "frames": 3})
    assert (root / "annotations.json").read_bytes() == before
    other = tmp_path / "other"
    other.mkdir()
    (other / "mine.txt").write_text("keep me")
    with pytest.raises(DataError, match="not an occtrain dataset"):
        DatasetWriter(other, {"generator": "tests"})
    assert (other / "mine.txt").read_text() == "keep me"


def test_a_sidecar_is_checked_against_its_schema_once_per_text(tmp_path, monkeypatch):
    """Frames read again (every stage does) are not walked through the schema again while
    their text is the same; a text changed in place, even to the same length, is checked
    anew and its problem reported."""
    from occtrain.data import layout

    root = write_hand_dataset(tmp_path / "ds", train=1, val=0, frames=3)
    index = DatasetIndex.open(root)
    scene = index.splits["train"][0]
    checks = []
    real = layout.first_problem
    monkeypatch.setattr(layout, "first_problem", lambda data, schema: checks.append(schema) or real(data, schema))
    monkeypatch.setattr(layout, "_CONFORMING", set())
    first = index.frames(scene)
    assert index.frames(scene) == first and len(checks) == 1
    sidecar = root / "occtrain" / "frames" / f"{scene}.json"
    text = sidecar.read_text()
    bad = text.replace('"ego_speed": 5.0', '"ego_speed": "5"', 1)
    assert bad != text and len(bad) == len(text)
    sidecar.write_text(bad)
    with pytest.raises(DataError, match=r"frames/scene-0000\.json: .*ego_speed"):
        index.frames(scene)
    assert len(checks) == 2
