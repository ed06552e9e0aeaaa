"""The documentation's pictures, drawn from a finished run.

    python tools/docs_pictures.py RUN --out docs/img/NAME [--data ROOT] [--only world,forecast,...]

From the run directory RUN (any recipe; a picture whose stage the run lacks is skipped and
said) it renders:

- ``world.png``: one val frame of the run's dataset, its bird's-eye view among the six cameras;
- ``reconstruction.png``: that frame and the tokenizer stage's reconstruction of it;
- ``forecast.png``: the pretrain stage's forecast 1, 2 and 3 s ahead beside the truth and
  Copy&Paste (the present copied forward, what a forecast must beat where nothing moves);
- ``drive.gif``: one closed-loop route of the run's planner (its last planner or dagger stage,
  or ``--drive-stage``) beside the world's expert on the same route (``occtrain drive
  --save-videos`` of one route; its results are kept in the stage's ``drive/`` as every
  drive's are);
- ``dashboard.png``: the top of the run's dashboard, in headless Chromium (skipped, and said,
  where ``/usr/bin/chromium`` is missing).

Beside them ``pictures.json`` holds each picture's file, alt text and caption; every caption
ends with the run's stamp (recipe, training seed, code, world: what ``occtrain report``
names a run by, never its path), and a picture of frames from ``--data`` that is not the
run's own world names the world it shows as such. The docs place a picture with a marker line
``<!-- picture: NAME/world -->``, which ``docs/hooks.py`` replaces with the image and its
caption at build time, so no caption is typed by hand and a marker naming a missing picture
fails the strict build. ``--only`` redraws some pictures and keeps the others' entries.

A mistake (a run directory without its manifest or recipe, an ``--out`` that cannot be
written, a broken ``pictures.json``) is one line, ``error: ...`` naming the file, with exit
status 2, before any picture is drawn.
"""

from __future__ import annotations

import argparse
import html
import io
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TypedDict

import numpy as np
from PIL import Image, ImageDraw

from occtrain.config.loading import read_yaml
from occtrain.data.identity import world_identity
from occtrain.data.layout import ANNOTATIONS_FILE, DatasetIndex
from occtrain.data.render import render_bev, strip
from occtrain.data.validate import first_problem
from occtrain.errors import ConfigError, DataError, OcctrainError, cause_line
from occtrain.formats.io import atomic_write_bytes, atomic_write_json, check_output, parse_json
from occtrain.formats.manifest import MANIFEST_FILE, PIPELINE_FILE
from occtrain.formats.occ3d import FRAME_DT, FREE

PICTURES = ("world", "reconstruction", "forecast", "drive", "dashboard")
INDEX_FILE = "pictures.json"
CHROMIUM = Path("/usr/bin/chromium")
#: The horizons a forecast picture shows (future step k is (k + 1) x 0.5 s ahead).
FORECAST_STEPS = (1, 3, 5)


@dataclass(frozen=True)
class Picture:
    """One rendered picture as the docs place it."""

    file: str
    alt: str
    caption: str


class PictureEntry(TypedDict):
    """A :class:`Picture` as ``pictures.json`` holds it."""

    file: str
    alt: str
    caption: str


class PicturesIndex(TypedDict):
    pictures: dict[str, PictureEntry]


class Skipped(Exception):
    """A picture the run cannot give (no such stage), said and left out."""


@dataclass(frozen=True)
class RunFacts:
    """What the pictures need of a run: its stages by kind, the dataset its frames are drawn
    from and its stamps."""

    path: Path
    name: str
    kinds: dict[str, str]  # stage -> kind, in the recipe's order
    data: Path
    #: The run: recipe, training seed, code and the world it trained on (when that lies here).
    stamp: str
    #: The stamp of a picture drawn from ``data``: the run's, and the world drawn when
    #: ``--data`` names one other than the run's own.
    drawn: str

    @classmethod
    def read(cls, run: Path, data: Path | None) -> RunFacts:
        manifest_file, pipeline_file = run / MANIFEST_FILE, run / PIPELINE_FILE
        if not manifest_file.is_file():
            raise DataError(f"{run}: not a run directory (no {MANIFEST_FILE}); pass the directory of a run")
        try:
            manifest = parse_json(manifest_file.read_bytes())
            done = {s: e for s, e in manifest.get("stages", {}).items() if e.get("status") == "done"}
            seeds = sorted({str(e.get("config", {}).get("trainer", {}).get("seed", "?")) for e in done.values()})
            codes = sorted({e.get("code_version") or "?" for e in done.values()})
        except (OSError, ValueError, AttributeError, TypeError) as err:
            # AttributeError, TypeError: valid JSON of another shape (a list, a stage that is not an object).
            raise DataError(f"{manifest_file}: not a run manifest ({cause_line(err)}); rerun `occtrain run`") from None
        if not done:
            raise DataError(f"{run}: no stage is done; finish the run first")
        if not pipeline_file.is_file():
            raise DataError(f"{run}: no {PIPELINE_FILE} (the recipe a run keeps); pass the directory of a run")
        section = read_yaml(pipeline_file).get("data")
        if not isinstance(section, dict) or not isinstance(section.get("root"), str):
            raise DataError(f"{pipeline_file}: no data.root; it is not the recipe of an occtrain run")
        own_root = Path(section["root"])
        own = world_identity(own_root) if (own_root / ANNOTATIONS_FILE).is_file() else None
        if data is not None and not (data / ANNOTATIONS_FILE).is_file():
            raise DataError(f"{data}: not a dataset (no {ANNOTATIONS_FILE}); --data takes the root of one")
        if data is None and own is None:
            raise DataError(f"{own_root}: not the run's dataset (no {ANNOTATIONS_FILE}); pass it with --data")
        data = own_root if data is None else data
        drawn = world_identity(data)
        name = str(manifest.get("name", run.name))
        stamp = f"recipe {name}, training seed {', '.join(seeds)}, code {', '.join(codes)}"
        stamp += f", world {own.name} [{own.key}]" if own is not None else ""
        if own is not None and own.key == drawn.key:
            drawn_stamp = stamp
        else:
            # --data names another world, or one the run's own cannot be compared with: the
            # picture says which it shows, and never passes it off as the run's.
            which = ", not the run's own" if own is not None else " (the run's own world is not here to compare)"
            drawn_stamp = f"{stamp}; drawn on world {drawn.name} [{drawn.key}] given with --data{which}"
        return cls(run, name, {s: str(e.get("kind")) for s, e in done.items()}, data, stamp, drawn_stamp)

    def stage(self, *kinds: str) -> str:
        """The last done stage of one of ``kinds`` (the recipe's order), or Skipped."""
        found = [s for s, k in self.kinds.items() if k in kinds]
        if not found:
            raise Skipped(f"the run has no done {' or '.join(kinds)} stage")
        return found[-1]


def first_val_frame(index: DatasetIndex, frame: int) -> tuple[str, str, int]:
    """(scene, token, position) of frame ``frame`` of the first val scene (clamped to it)."""
    scene = next(iter(index.splits.get("val") or index.scenes))
    tokens = index.scenes[scene]
    i = min(frame, len(tokens) - 1)
    return scene, tokens[i], i


def _png(image: Image.Image) -> bytes:
    """PNG bytes, as a 256-colour palette: the world's colours are flat, the file a third the size."""
    buffer = io.BytesIO()
    image.convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT).save(buffer, format="PNG", optimize=True)
    return buffer.getvalue()


def _labelled(image: Image.Image, label: str) -> Image.Image:
    """``image`` under a black bar naming it."""
    out = Image.new("RGB", (image.width, image.height + 16), (0, 0, 0))
    out.paste(image, (0, 16))
    ImageDraw.Draw(out).text((4, 2), label, fill=(255, 255, 255))
    return out


# ----------------------------------------------------------------------------- pictures


def world_picture(run: RunFacts, frame: int, out: Path) -> Picture:
    from occtrain.commands.data_show import show

    index = DatasetIndex.open(run.data)
    scene, _, i = first_val_frame(index, frame)
    with tempfile.TemporaryDirectory() as tmp:
        shown = show(run.data, Path(tmp) / "world.png", scene=scene, index=i, scale=2)
        atomic_write_bytes(out / "world.png", _png(Image.open(shown)))
    return Picture(
        "world.png",
        "A bird's-eye view of a street scene in class colours, the ego car at the centre with its future path, "
        "the six camera images around it",
        f"The world: frame {i} of val scene {scene}, its occupancy from above (the ego's next 3 s in green, "
        "columns no camera sees darkened) among the six cameras (`occtrain data show`). " + run.drawn,
    )


def reconstruction_picture(run: RunFacts, frame: int, out: Path) -> Picture:
    import torch

    from occtrain.core.registry import tokenizer_archs
    from occtrain.core.tokenizer_exports import load_tokenizer
    from occtrain.data.frames import frames_batch

    stage = run.stage("tokenizer")
    model = load_tokenizer(run.path / stage / "export")
    index = DatasetIndex.open(run.data)
    scene, token, i = first_val_frame(index, frame)
    reads_cameras = tokenizer_archs()[model.arch].reads_cameras
    batch = frames_batch(index, [(scene, token)], cameras=reads_cameras)
    truth = batch["semantics"][0].numpy()
    with torch.no_grad():
        if reads_cameras:
            pred = model(batch, index, None).prediction()[0]
        else:
            pred = model.decode_labels(model.encode(batch["semantics"].long()))[0]
    pred = pred.to(torch.uint8).numpy()
    source = "from the six cameras alone" if reads_cameras else "from its scene tokens"
    mask = batch["mask_camera"][0].numpy()
    panels = [render_bev(truth, mask, scale=2, title="truth"), render_bev(pred, mask, scale=2, title="reconstruction")]
    classes = sorted({int(c) for c in np.unique(np.concatenate([truth.ravel(), pred.ravel()]))} - {FREE})
    atomic_write_bytes(out / "reconstruction.png", _png(strip(panels, classes)))
    return Picture(
        "reconstruction.png",
        "Two bird's-eye views side by side: the true occupancy of a frame and the scene tokenizer's reconstruction",
        f"What the `{stage}` stage ({model.arch}) keeps of a scene: frame {i} of val scene {scene}, truth (left) and "
        f"its reconstruction {source} (right). " + run.drawn,
    )


def forecast_picture(run: RunFacts, frame: int, out: Path) -> Picture:
    import occtrain

    stage = run.stage("pretrain")
    model = occtrain.load(run.path / stage)
    if "forecast" not in model.operations:
        raise Skipped(f"the {model.family} world model of `{stage}` does not forecast")
    index = DatasetIndex.open(run.data)
    scene, token, i = first_val_frame(index, frame)
    try:
        clip = model.clip(run.data, token=token)
    except OcctrainError as err:
        raise Skipped(f"frame {i} of {scene} cannot be forecast ({err}); pick another --frame") from None
    forecast = model.forecast(clip)
    tokens = index.scenes[scene]
    present = index.labels(scene, token)
    steps = [k for k in FORECAST_STEPS if k < len(forecast)]
    if not steps:
        raise Skipped(f"`{stage}` forecasts {len(forecast)} frames, none 1 s ahead")
    rows = []
    for k in steps:
        ahead = f"{(k + 1) * FRAME_DT:g} s"
        truth = index.labels(scene, tokens[i + k + 1])["semantics"]
        rows.append(
            strip(
                [
                    render_bev(truth, scale=1, title=f"truth {ahead}"),
                    render_bev(forecast[k], scale=1, title=f"forecast {ahead}"),
                    render_bev(present["semantics"], scale=1, title=f"Copy&Paste {ahead}"),
                ]
            )
        )
    seen = {int(c) for r in (forecast, present["semantics"]) for c in np.unique(r)}
    grid = Image.new("RGB", (rows[0].width, sum(r.height + 4 for r in rows)), (255, 255, 255))
    for n, row in enumerate(rows):
        grid.paste(row, (0, n * (row.height + 4)))
    atomic_write_bytes(out / "forecast.png", _png(strip([grid], sorted(seen - {FREE}))))
    horizons = ", ".join(f"{(k + 1) * FRAME_DT:g}" for k in steps)
    return Picture(
        "forecast.png",
        "A grid of bird's-eye views: rows one to three seconds ahead; columns the truth, the world model's forecast "
        "and the present copied forward",
        f"The `{stage}` stage's {model.family} world model forecasting val scene {scene} from frame {i}: the truth "
        f"(left), its forecast (middle) and Copy&Paste, the present copied forward (right), {horizons} s ahead. "
        + run.drawn,
    )


def drive_picture(run: RunFacts, seconds: float, seed: int, out: Path, stage: str | None = None) -> Picture:
    from occtrain.commands.drive import drive

    stage = stage or run.stage("planner", "dagger")
    with tempfile.TemporaryDirectory() as tmp:
        drive(run.path / stage, routes=1, seed=seed, seconds=seconds, workers=1, save_videos=tmp)
        episodes = [Image.open(Path(tmp) / f"{who}-000.gif") for who in (stage, "expert")]
        frames = [_gif_frames(e) for e in episodes]
    labels = (f"the run's planner ({stage})", "the world's expert")
    pictures = []
    for n in range(max(len(f) for f in frames)):
        # An episode that ended early (a blocked route) holds its last frame.
        pictures.append(strip([_labelled(f[min(n, len(f) - 1)], lab) for f, lab in zip(frames, labels)]))
    palette = _palette(pictures)
    indexed = [p.quantize(palette=palette, dither=Image.Dither.NONE) for p in pictures]
    buffer = io.BytesIO()
    indexed[0].save(buffer, format="GIF", save_all=True, append_images=indexed[1:], duration=500, loop=0, optimize=True)
    atomic_write_bytes(out / "drive.gif", buffer.getvalue())
    return Picture(
        "drive.gif",
        "Two animated bird's-eye views of the same route: the trained planner driving on the left, the world's "
        "expert on the right, other traffic as boxes",
        f"Closed loop: the `{stage}` stage driving route 0 of seed {seed} for {seconds:g} s (left) beside the world's "
        "expert on the same route (right); its plan in cyan, the route ahead in yellow, infractions in red "
        f"(`occtrain drive --save-videos`). " + run.stamp,
    )


def _palette(pictures: list[Image.Image]) -> Image.Image:
    """One palette for every frame of an animation: the commonest colours, and always those of
    the plan, route, ego, lights and infractions, which cover few pixels but are the point.
    Flat colours mapped to themselves keep the frames sharp and the GIF small (full size, about
    220 KiB for two 10 s episodes, where an adaptive palette per resized frame took 520)."""
    from occtrain.data.synth.camera_render import LIGHT_COLOURS
    from occtrain.data.synth.closed_loop_view import ALERT_COLOUR, EGO_COLOUR, PLAN_COLOUR, ROUTE_COLOUR

    must = [(0, 0, 0), (255, 255, 255), PLAN_COLOUR, ROUTE_COLOUR, EGO_COLOUR, ALERT_COLOUR, *LIGHT_COLOURS.values()]
    pixels = np.concatenate([np.asarray(p).reshape(-1, 3) for p in pictures])
    colours, counts = np.unique(pixels, axis=0, return_counts=True)
    common = [tuple(int(v) for v in c) for c in colours[np.argsort(-counts)]]
    chosen = list(dict.fromkeys([*must, *common]))[:256]
    palette = Image.new("P", (1, 1))
    palette.putpalette([v for c in chosen for v in c] + [0] * (768 - 3 * len(chosen)))
    return palette


def _gif_frames(gif: Image.Image) -> list[Image.Image]:
    frames = []
    for n in range(getattr(gif, "n_frames", 1)):
        gif.seek(n)
        frames.append(gif.convert("RGB"))
    return frames


def dashboard_picture(run: RunFacts, out: Path) -> Picture:
    from occtrain.dashboard import write_dashboard

    if not CHROMIUM.exists():
        raise Skipped(f"{CHROMIUM} is missing (Debian's chromium package draws the page)")
    with tempfile.TemporaryDirectory() as tmp:
        file, shot = Path(tmp) / "dashboard.html", Path(tmp) / "dashboard.png"
        # The page names the run by where it lies; the docs name it as its recipe's runs/NAME.
        page = write_dashboard(run.path, out=file).read_text()
        file.write_text(page.replace(html.escape(str(run.path)), f"runs/{html.escape(run.name)}"))
        cmd = [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars"]
        cmd += [f"--user-data-dir={Path(tmp) / 'profile'}", f"--screenshot={shot}", "--window-size=1200,900"]
        proc = subprocess.run([*cmd, file.as_uri()], capture_output=True, text=True, timeout=120)
        if not shot.is_file():
            raise Skipped(f"chromium drew no screenshot ({proc.stderr.strip()[-300:]})")
        atomic_write_bytes(out / "dashboard.png", _png(Image.open(shot)))
    return Picture(
        "dashboard.png",
        "The top of the run dashboard: a dark header, the table of stages with their status and headline metrics",
        "The run's dashboard (`occtrain dashboard`), its top: every stage with its status, time and headline "
        "numbers, then charts and samples below. " + run.stamp,
    )


# ----------------------------------------------------------------------------- command


def read_index(index_file: Path) -> dict[str, dict]:
    """The entries of an existing ``pictures.json``, whose pictures ``--only`` keeps."""
    try:
        raw = parse_json(index_file.read_bytes())
        problem = first_problem(raw, PicturesIndex)
    except (OSError, ValueError) as err:
        problem = str(err)
    if problem:
        raise DataError(f"{index_file}: not a pictures index ({problem}); move it aside to draw every picture anew")
    return raw["pictures"]


def render(
    run: RunFacts,
    out: Path,
    only: list[str],
    frame: int = 8,
    seconds: float = 10.0,
    seed: int = 1000,
    drive_stage: str | None = None,
) -> dict[str, Picture]:
    """Render ``only`` of the pictures into ``out``; ``pictures.json`` keeps the others'
    entries. Returns what was drawn."""
    makers: dict[str, Callable[[], Picture]] = {
        "world": lambda: world_picture(run, frame, out),
        "reconstruction": lambda: reconstruction_picture(run, frame, out),
        "forecast": lambda: forecast_picture(run, frame, out),
        "drive": lambda: drive_picture(run, seconds, seed, out, drive_stage),
        "dashboard": lambda: dashboard_picture(run, out),
    }
    out.mkdir(parents=True, exist_ok=True)
    index_file = out / INDEX_FILE
    kept = read_index(index_file) if index_file.is_file() else {}
    drawn = {}
    for name in only:
        try:
            drawn[name] = makers[name]()
        except Skipped as why:
            print(f"{name}: skipped: {why}", file=sys.stderr)
            continue
        print(f"{name}: {out / drawn[name].file} ({(out / drawn[name].file).stat().st_size / 1024:.0f} KiB)")
    pictures = {k: v for k, v in kept.items() if k not in drawn} | {k: asdict(v) for k, v in drawn.items()}
    atomic_write_json(index_file, {"pictures": dict(sorted(pictures.items()))})
    return drawn


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a finished run directory")
    parser.add_argument("--out", type=Path, required=True, help="their folder, e.g. docs/img/quickstart")
    parser.add_argument("--data", type=Path, help="the run's dataset (default: its recipe's data.root)")
    parser.add_argument("--only", default=",".join(PICTURES), help=f"some of {', '.join(PICTURES)} (default: all)")
    parser.add_argument("--frame", type=int, default=8, help="which frame of the first val scene (default 8)")
    parser.add_argument("--seconds", type=float, default=10.0, help="how long the drive animation runs (default 10)")
    parser.add_argument("--seed", type=int, default=1000, help="the route seed of the drive (default 1000)")
    parser.add_argument("--drive-stage", help="the stage that drives (default: the run's last planner or dagger stage)")
    args = parser.parse_args(argv)
    only = [p.strip() for p in args.only.split(",") if p.strip()]
    unknown = [p for p in only if p not in PICTURES]
    if unknown:
        parser.error(f"--only {','.join(unknown)}: the pictures are {', '.join(PICTURES)}")
    try:
        run = RunFacts.read(args.run, args.data)
        if args.drive_stage and "drive" in only and args.drive_stage not in run.kinds:
            raise ConfigError(
                f"--drive-stage {args.drive_stage}: the run has no done stage of that name; "
                f"it has {', '.join(run.kinds)}"
            )
        check_output(args.out, "--out", kind="dir")
        render(run, args.out, only, args.frame, args.seconds, args.seed, args.drive_stage)
    except OcctrainError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
