"""The frame's road context through the dataset's reader and ``occtrain data check``: written by
the synthesis, read back as declared, optional (real data and older worlds lack it), and a
malformed one named by its key path."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from occtrain.cli import main
from occtrain.data.layout import FRAMES_DIR, DatasetIndex
from occtrain.data.schema import LIGHT_STATES, ROUTE_ARC, FrameAnnotation, RoadContext
from occtrain.data.validate import problems


def test_the_road_round_trips_through_the_sidecar_and_data_check(synth_dataset: Path, tmp_path: Path, capsys):
    root = tmp_path / "world"
    shutil.copytree(synth_dataset, root)
    index = DatasetIndex.open(root)
    scene = index.splits["train"][0]
    frames = index.frames(scene)
    for frame in frames:
        road = frame["road"]
        assert problems(road, RoadContext) == []
        assert len(road["route"]) == len(ROUTE_ARC) and road["route"][0] == [0.0, 0.0]
        assert road["stop_line"] is None or road["stop_line"]["light"] in LIGHT_STATES
    assert any(f["road"]["lead"] for f in frames)
    assert main(["data", "check", str(root)]) == 0
    capsys.readouterr()

    # A frame without it (an import, an older world) is a frame; a malformed one is named.
    sidecar = root / FRAMES_DIR / f"{scene}.json"
    written = json.loads(sidecar.read_text())
    del written[0]["road"]
    written[1]["road"]["route"] = written[1]["road"]["route"][:-1]
    written[2]["road"]["stop_line"] = {"distance": 12.0, "light": "blue", "green_left": -1.0}
    sidecar.write_text(json.dumps(written))
    assert problems(written[0], FrameAnnotation) == []
    assert main(["data", "check", str(root)]) == 1
    out = capsys.readouterr().out
    assert "[1].road.route" in out and "24 items" in out
    assert "[2].road.stop_line" in out and '"blue"' in out
    assert "[0].road" not in out
