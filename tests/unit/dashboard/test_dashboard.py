"""The run dashboard: charts, tables, paper figures, samples, graceful degradation, Chromium rendering."""

from __future__ import annotations

import argparse
import base64
import csv
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from conftest import REPO
from occtrain.cli.dashboard import register
from occtrain.core.published import REAL_DATA, all_figures, figures_for, metric_words
from occtrain.dashboard import bev_comparison, read_samples, write_dashboard, write_samples
from occtrain.dashboard.svg import Frame, nice_ticks, tick_labels
from occtrain.errors import OcctrainError
from occtrain.formats.manifest import Manifest
from occtrain.formats.occ3d import CLASS_COLORS, FREE, GRID_SHAPE

CHROMIUM = Path("/usr/bin/chromium")
SEEDS = REPO.parent / "shared" / "seeds"


def _write_csv(path: Path, rows: list[dict]) -> None:
    """A Lightning CSVLogger-like file: every column in the header, each row sets only some."""
    cols = ["epoch", "step"] + sorted({k for r in rows for k in r} - {"epoch", "step"})
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, cols)
        w.writeheader()
        w.writerows(rows)


def _scene(car_x: int) -> np.ndarray:
    sem = np.full(GRID_SHAPE, FREE, np.uint8)
    sem[:, 80:120, 0] = 11  # a road along x
    sem[car_x : car_x + 10, 90:95, 1:3] = 4  # a car on it
    sem[:, 130:140, 0:6] = 15  # a wall
    return sem


def make_run(tmp_path: Path) -> Path:
    """Three stages: a finished tokenizer with logs, metrics and samples; a failed pretrain; a pending instruct."""
    run = tmp_path / "runs" / "quick"
    m = Manifest.load(run)
    m.name = "quick"
    for name, kind in (("tokenizer", "tokenizer"), ("pretrain", "pretrain"), ("instruct", "instruct")):
        m.entry(name, kind)
    m.mark_running("tokenizer", "abc123", {"kind": "tokenizer"})
    final = {
        "val/occworld_mIoU": 41.5,
        "val/occworld_IoU": 55.25,
        "val/occ3d_mIoU": 38.0,
        "val/loss": 0.3,
        "params": 1.2e6,
    }
    m.mark_done("tokenizer", final, {"export": str(run / "tokenizer" / "export")}, 95.0)
    m.mark_running("pretrain", "def456", {"kind": "pretrain"})
    m.mark_failed("pretrain", "RuntimeError: out of memory", 12.5)
    (run / "pipeline.yaml").write_text("name: quick\nstages: []\n")
    (run / "tokenizer").mkdir(parents=True)
    (run / "tokenizer" / "metrics.json").write_text(json.dumps(final))
    _write_csv(
        run / "tokenizer" / "logs" / "csv" / "metrics.csv",
        [
            {"epoch": 0, "step": 0, "train/loss": 1.0, "train/recon": 0.8, "lr-AdamW": 1e-3},
            {"epoch": 0, "step": 10, "train/loss": 0.6, "train/recon": 0.5, "lr-AdamW": 8e-4},
            {"epoch": 0, "step": 10, "val/loss": 0.7, "val/occworld_mIoU": 20.0, "val/occworld_IoU": 30.0},
            {"epoch": 0, "step": 20, "train/loss": 0.2, "train/recon": 0.1, "lr-AdamW": 5e-4},
            {"epoch": 0, "step": 20, "val/loss": 0.3, "val/occworld_mIoU": 41.5, "val/occworld_IoU": 55.25},
        ],
    )
    gt, recon = _scene(100), _scene(102)
    picture = bev_comparison([("ground truth", gt), ("reconstruction", recon), ("forecast +1s", _scene(110))])
    texts = [
        {"task": "qa", "prompt": "Are there any cars?", "prediction": "yes", "reference": "yes"},
        {"task": "cot", "prompt": "Plan.", "prediction": "slow down <b>now</b>", "reference": "keep speed"},
    ]
    write_samples(run / "tokenizer", [("val scene-0002 frame 4", picture)], texts)
    _write_csv(run / "pretrain" / "logs" / "csv" / "metrics.csv", [{"epoch": 0, "step": 0, "train/loss": 5.0}])
    return run


@pytest.fixture
def run_dir(tmp_path: Path) -> Path:
    return make_run(tmp_path)


# ----------------------------------------------------------------------------- charts


def test_nice_ticks_are_round_and_cover_the_range():
    assert nice_ticks(0, 20) == [0, 5, 10, 15, 20]
    # range 0.74 / 5 = 0.148 -> step 0.2; 0.23 rounds down to 0.2, 0.97 up to 1.0
    assert nice_ticks(0.23, 0.97) == [0.2, 0.4, 0.6, 0.8, 1.0]
    assert nice_ticks(3.0, 3.0)[0] < 3.0 < nice_ticks(3.0, 3.0)[-1]


def test_tick_labels_share_one_format():
    assert tick_labels([0.0, 2.5, 5.0]) == ["0.0", "2.5", "5.0"]
    assert tick_labels([0, 5, 10]) == ["0", "5", "10"]
    assert tick_labels([0.2, 0.4, 0.6]) == ["0.2", "0.4", "0.6"]
    assert tick_labels([0.0, 5e-5, 1e-4]) == ["0", "5.0e-05", "1.0e-04"]


def _polylines(html: str) -> dict[str, list[str]]:
    found: dict[str, list[str]] = {}
    for label, pts in re.findall(r'<polyline data-series="([^"]*)" points="([^"]*)"', html):
        found.setdefault(label, []).append(pts)
    return found


def test_page_has_every_stage_and_charts_drawn_from_the_csv(run_dir: Path):
    html = write_dashboard(run_dir).read_text()
    assert (run_dir / "dashboard.html").is_file()
    for name in ("tokenizer", "pretrain", "instruct"):
        assert f'id="stage-{name}"' in html
    # tokenizer: train loss (loss), val loss, lr, train/recon (no "loss" in its name), the val/occworld
    # family; pretrain: train loss
    assert html.count("<svg") == 6
    f = Frame()
    assert (f.width, f.left, f.right, f.height, f.top, f.bottom) == (560, 64, 16, 280, 30, 44)
    # train/loss (0,1.0) (10,0.6) (20,0.2): x ticks 0..20 over 480 px from x=64; y ticks 0.2..1.0
    # over 206 px up from y=236: 0.6 is half way -> 236 - 103 = 133.
    assert "64.0,30.0 304.0,133.0 544.0,236.0" in _polylines(html)["loss"]
    # val/occworld_mIoU (10, 20) (20, 41.5) and IoU (10, 30) (20, 55.25) share the reconstruction chart: y ticks 20..60
    # (range 35.25/5 = 7.05 -> step 10); x ticks 10..20 (step 2). 41.5 -> 236 - 21.5/40*206 = 125.3
    lines = _polylines(html)
    assert lines["occworld mIoU"] == ["64.0,236.0 544.0,125.3"]
    # 30 -> 236 - 10/40*206 = 184.5; 55.25 -> 236 - 35.25/40*206 = 236 - 181.54 = 54.46
    assert lines["occworld IoU"] == ["64.0,184.5 544.0,54.5"]
    assert "learning rate" in html and "validation loss" in html


def test_page_is_self_contained(run_dir: Path):
    html = write_dashboard(run_dir).read_text()
    assert "http" not in html.lower()
    assert "<script" not in html and "<link" not in html and "@import" not in html
    srcs = re.findall(r'src="([^"]*)"', html)
    assert srcs and all(s.startswith("data:image/png;base64,") for s in srcs)
    png = base64.b64decode(srcs[0].split(",", 1)[1])
    assert png == (run_dir / "tokenizer" / "samples" / "sample_0.png").read_bytes()


def test_stage_table_statuses_and_failures(run_dir: Path):
    html = write_dashboard(run_dir).read_text()
    table = html.split("<h2>Stages</h2>", 1)[1].split("</table>", 1)[0]
    assert table.index("tokenizer") < table.index("pretrain") < table.index("instruct")
    assert '<span class="badge" style="background:#2e7d32">done</span>' in table
    assert '<span class="badge" style="background:#c62828">failed</span>' in table
    assert '<span class="badge" style="background:#757575">pending</span>' in table
    assert "1m 35s" in table and "12.5s" in table  # wall times 95 s and 12.5 s
    assert "RuntimeError: out of memory" in table
    assert "not run yet" in table
    assert "pending: this stage has not run yet" in html


def test_metrics_grouped_by_convention_with_paper_figures(run_dir: Path):
    html = write_dashboard(run_dir).read_text()
    tok = html.split('id="stage-tokenizer"', 1)[1].split("</section>", 1)[0]
    occ3d, occworld, other = (
        tok.index(h) for h in ("<h3>Occ3D convention", "<h3>OccWorld convention", "<h3>Other metrics")
    )
    assert occ3d < occworld < other
    row = re.search(r"<tr><td>val/occworld_mIoU</td>.*?</tr>", tok).group(0)
    assert '<td class="num">41.5</td>' in row
    assert REAL_DATA in row and "OccLLaMA 75.2" in row and "Occ-LLM 71.08" in row
    occ3d_row = re.search(r"<tr><td>val/occ3d_mIoU</td>.*?</tr>", tok).group(0)
    assert REAL_DATA not in occ3d_row  # no paper reports the camera-masked reconstruction
    # texts are escaped, and exact matches are marked
    assert "slow down &lt;b&gt;now&lt;/b&gt;" in tok
    assert tok.count('<td class="ok">') == 1 and tok.count('<td class="bad">') == 1


def test_paper_figures_match_by_words_and_convention():
    assert metric_words("val/forecast/occworld_mIoU_1s") == metric_words("val/occworld_forecast_mIoU_1s")
    l2 = {f.paper: f.value for f in figures_for("val/plan/L2_stp3_1s")}
    assert l2 == {"OccLLaMA": 0.25, "Occ-LLM": 0.12, "OccVLA": 0.18, "SparseOccVLA": 0.14}
    assert {f.value for f in figures_for("val/L2_uniad_avg")} == {0.80, 0.28, 0.23}
    assert {f.value for f in figures_for("val/plan/collision_uniad_3s")} == {0.96, 0.41}
    assert figures_for("val/occ3d_mIoU") == [] and figures_for("val/loss") == []
    fc = {(f.paper, f.where): f.value for f in figures_for("val/forecast/occworld_mIoU_avg")}
    assert fc[("OccLLaMA", "Table II, Ours-O")] == 19.93 and fc[("Occ-LLM", "Table I, Ours (Occ.)")] == 20.99
    assert {f.value for f in figures_for("val/qa/overall")} == {53.0, 59.5, 60.8}
    assert {f.value for f in figures_for("val/qa/by_type_hop/exist_H0")} == {87.4, 82.9}


def test_meta_action_accuracy_is_one_chart_of_four_parts_beside_its_baseline():
    from occtrain.dashboard.run_view import _measure

    title = "meta-action accuracy: speed, direction, their mean, overall (%)"
    assert _measure("val/meta_action_speed") == (title, "meta_action speed")
    assert _measure("val/baseline_prior_meta_action_overall") == (title, "baseline_prior_meta_action overall")
    assert _measure("val/meta_action_samples") is None
    # OccVLA's Table 4 row sits beside ours: "Avg." is the mean, "Overall" both parts right.
    assert {f.value for f in figures_for("val/meta_action_mean")} == {66.39}
    assert {f.value for f in figures_for("val/meta_action_overall")} == {43.08}


@pytest.mark.skipif(not SEEDS.is_dir(), reason=f"the seed papers are not at {SEEDS} (outside the repository)")
def test_every_paper_figure_is_printed_in_its_paper():
    files = {"OccLLaMA": "000_", "OccVLA": "002_", "Occ-LLM": "003_", "SparseOccVLA": "004_"}
    texts = {p: next(SEEDS.glob(f"{prefix}*.txt")).read_text() for p, prefix in files.items()}
    for fig in all_figures():
        # OccLLaMA's per-type QA row is printed in OccVLA's Table 3
        source = "OccVLA" if fig.where.startswith("OccVLA") else fig.paper
        printed = {f"{fig.value:.1f}", f"{fig.value:.2f}"}
        assert any(re.search(rf"(?<![\d.]){re.escape(p)}(?!\d)", texts[source]) for p in printed), fig


# ----------------------------------------------------------------------------- samples


def test_bev_comparison_panels_and_labels():
    img = bev_comparison([("ground truth", _scene(100)), ("forecast", _scene(150))], scale=1)
    assert img.dtype == np.uint8 and img.shape[1] == 200 + 4 + 200 and img.shape[0] > 200
    # x forward is up: voxel row x maps to image row 199 - x; y left is left: column 199 - y
    assert (img[199 - 105, 199 - 92] == CLASS_COLORS[4]).all()  # the car in panel 1 ...
    assert (img[199 - 155, 204 + 199 - 92] == CLASS_COLORS[4]).all()  # ... and further ahead in panel 2
    assert (img[199 - 105, 204 + 199 - 92] == CLASS_COLORS[11]).all()  # road where the car was
    title = img[2:12, 2:60].max(-1)
    assert (title > 200).any() and (title == 0).any()  # light title text on black
    with pytest.raises(ValueError, match="semantics shape"):
        bev_comparison([("bad", np.zeros((10, 10, 16), np.uint8))])


def test_write_samples_round_trip_and_replaces_old_pictures(tmp_path: Path):
    red = np.zeros((4, 5, 3), np.uint8)
    red[..., 0] = 255
    write_samples(tmp_path, [("a", red), ("b", red)], [])
    write_samples(tmp_path, [("only", red)], [{"task": "qa", "prompt": "p", "prediction": "x", "reference": "y"}])
    images, texts = read_samples(tmp_path)
    assert [c for c, _ in images] == ["only"] and texts[0]["prediction"] == "x"
    assert sorted(p.name for p in (tmp_path / "samples").iterdir()) == ["index.json", "sample_0.png"]
    back = np.asarray(Image.open(tmp_path / "samples" / "sample_0.png"))
    assert (back == red).all()
    with pytest.raises(ValueError, match="uint8"):
        write_samples(tmp_path, [("f", red.astype(np.float32))], [])
    with pytest.raises(ValueError, match="reference"):
        write_samples(tmp_path, [], [{"task": "qa", "prompt": "p", "prediction": "x"}])


# ----------------------------------------------------------------------------- bad input


def test_missing_or_corrupt_run_dir_is_one_line(tmp_path: Path):
    with pytest.raises(OcctrainError, match="no such run directory"):
        write_dashboard(tmp_path / "nope")
    with pytest.raises(OcctrainError, match="no manifest.json"):
        write_dashboard(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(OcctrainError, match="unreadable manifest") as err:
        write_dashboard(tmp_path)
    assert "\n" not in str(err.value)


def test_corrupt_stage_files_are_shown_not_fatal(run_dir: Path):
    (run_dir / "tokenizer" / "metrics.json").write_text("[1, 2")
    (run_dir / "tokenizer" / "samples" / "sample_0.png").write_bytes(b"not a png")
    html = write_dashboard(run_dir).read_text()
    assert "metrics.json: unreadable metrics" in html and "not a PNG file" in html
    assert "<td>val/occworld_mIoU</td>" in html  # the manifest's copy of the metrics


def test_final_metrics_say_what_they_were_measured_on_and_a_subset_is_called_one(run_dir: Path):
    from occtrain.formats.metrics_file import Provenance, read_metrics, write_metrics

    path = run_dir / "tokenizer" / "metrics.json"
    html = write_dashboard(run_dir).read_text()  # written before provenance: said, not guessed
    assert "measured on: not recorded (metrics written before occtrain recorded it)" in html
    world = "occtrain world v5, seed 0 (12 train + 2 val scenes of 40 frames)"
    subset = Provenance("validation at the end of training", "val", {"validation": [4, 80]}, "k", "v5", world)
    write_metrics(path, read_metrics(path).metrics, subset)
    html = write_dashboard(run_dir).read_text()
    said = f"validation at the end of training: a subset of the val split (validation 4 of 80) of {world}"
    assert f'<p class="problem">{said}; code -</p>' in html
    whole = Provenance("validation at the end of training", "val", {"validation": [80, 80]}, "k", "v5", world)
    write_metrics(path, read_metrics(path).metrics, whole)
    assert f'<p class="note">validation at the end of training: the whole val split of {world}' in (
        write_dashboard(run_dir).read_text()
    )


def test_cli_command_writes_to_out(run_dir: Path, tmp_path: Path, capsys):
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["dashboard", str(run_dir), "--out", str(tmp_path / "page.html")])
    assert args.func(args) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "page.html")
    assert "<svg" in (tmp_path / "page.html").read_text()


# ----------------------------------------------------------------------------- browser


@pytest.mark.slow
@pytest.mark.skipif(
    not CHROMIUM.exists(), reason="Debian's chromium is not installed (/usr/bin/chromium); .ci/run installs it"
)
def test_chromium_renders_a_real_page(run_dir: Path, tmp_path: Path):
    page = write_dashboard(run_dir)
    shot = tmp_path / "dashboard.png"
    cmd = [
        str(CHROMIUM),
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--hide-scrollbars",
        f"--user-data-dir={tmp_path / 'profile'}",
        f"--screenshot={shot}",
        "--window-size=1280,2000",
        page.as_uri(),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert shot.is_file(), proc.stderr[-2000:]
    if os.environ.get("OCCTRAIN_KEEP_SCREENSHOT"):  # for a person to look at
        shutil.copy(shot, os.environ["OCCTRAIN_KEEP_SCREENSHOT"])
    img = np.asarray(Image.open(shot).convert("RGB"))
    assert img.shape[:2] == (2000, 1280)
    colours = np.unique(img.reshape(-1, 3), axis=0)
    assert len(colours) > 200  # text anti-aliasing, charts, the BEV picture
    # Not mostly blank: ink (text, lines, pictures) in most 50-pixel bands of the page.
    ink = img.min(-1) < 160
    assert ink.mean() > 0.01 and ink.reshape(40, 50, -1).any(axis=(1, 2)).mean() > 0.75
    header = img[:60, :600].reshape(-1, 3)
    assert (header.mean(0) < 90).all()  # the dark header bar was painted
    # Series colours of the charts (#1f77b4, #d62728) appear: the SVGs were drawn.
    for rgb in ((31, 119, 180), (214, 39, 40)):
        assert (np.abs(img.astype(int) - rgb).sum(-1) < 30).sum() > 50, rgb


# ----------------------------------------------------------------------------- the data


def test_the_data_section_shows_the_runs_dataset_beside_occ3d_and_counts_it_once(
    run_dir: Path, tmp_path: Path, monkeypatch
):
    import occtrain.data.stats as stats_module
    from conftest import write_hand_dataset
    from occtrain.dashboard.run_view import DATA_STATS_FILE

    root = write_hand_dataset(tmp_path / "ds", train=1, val=1, frames=4)
    (run_dir / "pipeline.yaml").write_text(f"name: quick\ndata:\n  root: {root}\nstages: []\n")
    html = write_dashboard(run_dir).read_text()
    section = html.split("<h2>Data: ", 1)[1].split("</section>", 1)[0]
    assert section.startswith(str(root))
    assert "occupied share inside mask_camera" in section and "52.7 %" in section and "30-70 %" in section
    assert section.count("data:image/png;base64,") == 1  # the class-share chart
    saved = json.loads((run_dir / DATA_STATS_FILE).read_text())
    assert saved["frames"] == 4 and saved["world_key"]

    def no_recount(*args, **kwargs):
        raise AssertionError("the statistics of an unchanged world were counted again")

    monkeypatch.setattr(stats_module, "dataset_stats", no_recount)
    assert write_dashboard(run_dir).read_text().count("<h2>Data: ") == 1


def test_a_dataset_not_found_is_said_on_the_page(run_dir: Path, tmp_path: Path):
    (run_dir / "pipeline.yaml").write_text(f"name: quick\ndata:\n  root: {tmp_path / 'gone'}\nstages: []\n")
    html = write_dashboard(run_dir).read_text()
    assert "gone: not found from" in html and 'class="problem"' in html


def test_a_stage_drive_is_tabled_with_its_animations(run_dir: Path, tmp_path: Path):
    gif = tmp_path / "tokenizer-000.gif"
    frames = [Image.new("RGB", (8, 8), c) for c in ((255, 0, 0), (0, 0, 255))]
    frames[0].save(gif, save_all=True, append_images=frames[1:], duration=500)
    drive = run_dir / "tokenizer" / "drive" / "seed1000-20s"
    drive.mkdir(parents=True)
    scores = {
        "planned_share": 75.0,
        "fell_back_share": 12.5,
        "open_loop_L2_stp3_avg": 0.87,
        "open_loop_collision_stp3_avg": 0.25,
        "driving_score": 61.25,
        "pdm_score": 70.0,
        "route_completion": 87.5,
        "collisions": 0.5,
    }
    (drive / "summary.json").write_text(
        json.dumps(
            {
                "routes": 2,
                "seconds": 20,
                "conventions": {"driving_score": "CARLA leaderboard 1.0"},
                "drivers": {"tokenizer": scores, "expert": {"driving_score": 100.0}},
                "videos": {"tokenizer-000": str(gif), "expert-000": str(gif)},
            }
        )
    )
    html = write_dashboard(run_dir).read_text()
    section = html[html.index("Closed-loop driving (2 routes of 20 s, seed1000-20s)") :]
    row = "<td>tokenizer</td><td>75</td><td>12</td><td>0.87</td><td>0.25</td><td>61.2</td><td>70.0</td><td>87.5</td>"
    assert row + "<td>0.50</td>" in section
    assert "CARLA leaderboard 1.0" in section
    gifs = re.findall(r'src="data:image/gif;base64,([^"]*)"', html)
    assert len(gifs) == 1 and base64.b64decode(gifs[0]) == gif.read_bytes()  # the stage's own episode only


def test_closed_loop_rounds_are_charted_apart_from_the_training_curves():
    from occtrain.dashboard.run_view import ROUND_COLLISIONS, ROUND_SCORES, charts_from_curves

    charts = charts_from_curves(
        {
            "dagger/rollout_driving_score": [(0, 48.0), (100, 61.0)],
            "dagger/rollout_policy_share": [(0, 50.0), (100, 75.0)],
            "dagger/rollout_collisions": [(0, 0.75), (100, 0.5)],
            "dagger/rollout_beta": [(0, 0.5), (100, 0.25)],  # a setting, not a score: not charted
            "train/loss": [(0, 1.0), (1, 0.5)],
        }
    )
    by_title = {c.title: sorted(s.label for s in c.series) for c in charts}
    assert by_title[ROUND_SCORES] == ["driving score", "policy share"]
    assert by_title[ROUND_COLLISIONS] == ["collisions"] and "train loss" in by_title
