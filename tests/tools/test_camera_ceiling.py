"""tools/camera_ceiling.py: what a point budget and a world's cameras can carry, scored on
the same frames; a mistake is one line and nothing is written."""

from __future__ import annotations

from pathlib import Path

import pytest

from conftest import load_tool


@pytest.fixture()
def tool():
    return load_tool("camera_ceiling")


def test_the_rows_bound_a_reader_of_the_cameras(tool, synth_dataset, tmp_path, capsys):
    """Over the same frames: a point budget covering every occupied voxel at one voxel each
    reconstructs them exactly; the lifted pixels over the prior beat the prior alone and
    their free-elsewhere twin on IoU; the table is written where asked."""
    out = tmp_path / "ceiling.md"
    code = tool.main(
        [str(synth_dataset), "--samples", "2", "--points", "500000", "--extents", "1,1,1", "--out", str(out)]
    )
    assert code == 0
    lines = [line for line in out.read_text().splitlines() if line.startswith("| ")][1:]
    rows = {line.split(" | ")[1]: line.split(" | ")[2:] for line in lines}
    assert set(rows) == {
        "the per-voxel prior",
        "500000 points, 1x1x1 voxels each, free elsewhere",
        "500000 points, 1x1x1 voxels each, the prior elsewhere",
        "72x128 pixels lifted, free elsewhere",
        "72x128 pixels lifted, the prior elsewhere",
    }
    assert rows["500000 points, 1x1x1 voxels each, free elsewhere"][:2] == ["100.0", "100.0"]
    iou = {name: float(cells[1]) for name, cells in rows.items()}
    assert iou["72x128 pixels lifted, the prior elsewhere"] > iou["the per-voxel prior"]
    assert iou["72x128 pixels lifted, the prior elsewhere"] > iou["72x128 pixels lifted, free elsewhere"]
    assert str(synth_dataset) not in out.read_text()  # a world by what it is, not where it lies
    assert "occtrain world v" in lines[0] and "72x128 cameras" in lines[0]
    assert out.read_text().endswith(capsys.readouterr().out) and "tools/camera_ceiling.py" in out.read_text()


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["{tmp}/nowhere"], "{tmp}/nowhere: no such dataset"),
        (["{hand}"], "has no camera_sensor"),
    ],
)
def test_a_mistake_is_one_line_and_writes_nothing(tool, hand_dataset, tmp_path, capsys, args, says):
    out = tmp_path / "ceiling.md"
    argv = [a.format(tmp=tmp_path, hand=hand_dataset) for a in args] + ["--out", str(out)]
    assert tool.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and says.format(tmp=tmp_path) in err, err
    assert not out.exists() and not Path(tmp_path / "nowhere").exists()


def test_an_extent_is_three_voxel_counts(tool, synth_dataset, capsys):
    with pytest.raises(SystemExit) as exit_:
        tool.main([str(synth_dataset), "--extents", "3,3"])
    assert exit_.value.code == 2
    assert "'3,3': an extent is x,y,z voxels" in capsys.readouterr().err
