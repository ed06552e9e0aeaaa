"""Bad input at every boundary, table-driven: each case breaks one thing in a copy of a tiny
valid world and runs the CLI in-process.

Every case ends in one line on stderr: ``error: ...`` naming the file or key (exit 2), or
for ``data check`` the summary line, with the problems themselves on stdout (exit 1). No
traceback anywhere, and no file that existed before the command is changed or removed
(nor, since every case fails, anything created).

A case is ``Case(id, setup, argv, code, says)``: ``setup(tmp)`` breaks the copy at ``tmp``;
``argv`` and ``says`` may use ``{tmp}``.
"""

from __future__ import annotations

import json
import shutil
import socket
import struct
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, NotRequired, Optional, TypedDict

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from builders import planning_files, qa_questions, read_only_disk, snapshot
from conftest import REPO, hand_frames, hand_labels, write_hand_dataset
from occtrain.cli import main
from occtrain.data.layout import DatasetIndex
from occtrain.data.poses import quaternion_from_yaw
from occtrain.data.validate import Len, problems
from occtrain.formats.occ3d import GRID_SHAPE

FRAMES = 8
SCENES = ("scene-0000", "scene-0001")  # train, val
#: Sample tokens of the tiny world, by scene (write_hand_dataset seeds scene s with s).
TOKENS = {scene: [f["token"] for f in hand_frames(scene, FRAMES, s)] for s, scene in enumerate(SCENES)}
T0, T1 = TOKENS[SCENES[0]], TOKENS[SCENES[1]]

DS = "{tmp}/ds"
ANN = "{tmp}/ds/annotations.json"
SIDECAR = "{tmp}/ds/occtrain/frames/scene-0000.json"
QA_VAL = "{tmp}/ds/nuscenes_qa/NuScenes_val_questions.json"


@dataclass(frozen=True)
class Case:
    id: str
    setup: Callable[[Path], None]
    argv: list[str]
    code: int
    #: What the output says; a case that breaks several things names each (all must appear).
    says: str | tuple[str, ...]
    #: What the machine does while the command runs (``patch(monkeypatch)``): a read-only disk.
    patch: Callable[[pytest.MonkeyPatch], None] | None = None


# ----------------------------------------------------------------------------- the tiny world


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    """A valid world: 2 scenes of 8 frames with every sidecar, frame shards of it, and a run
    directory whose pretrain stage has a (tiny, valid) export. Each case copies it."""
    from occtrain.config import load_config, to_yaml
    from occtrain.config.recipe import RecipeConfig
    from occtrain.data.shards import write_shards

    root = tmp_path_factory.mktemp("world")
    write_hand_dataset(root / "ds", train=1, val=1, frames=FRAMES)
    write_shards(root / "ds", root / "shards", samples_per_shard=4, kinds=["frames"])
    export = root / "run" / "pretrain" / "export"
    export.mkdir(parents=True)
    recipe = load_config(RecipeConfig, REPO / "recipes" / "quickstart.yaml", [f"data.root={root / 'ds'}"])
    (root / "run" / "pipeline.yaml").write_text(to_yaml(recipe))
    (root / "run" / "manifest.json").write_text(
        json.dumps({"name": "quickstart", "stages": {"pretrain": {"kind": "pretrain", "status": "done"}}})
    )
    save_file({"w": torch.zeros(4)}, str(export / "model.safetensors"))
    (export / "config.json").write_text(json.dumps({"stage_kind": "world_model"}))
    return root


# ----------------------------------------------------------------------------- breaking things


def edit_json(path: Path, change: Callable[[Any], Any]) -> None:
    """Rewrite a JSON file after ``change(data)`` mutated it in place (its return value is ignored)."""
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))  # Python's json writes NaN/Infinity as given, as a careless writer would


def edit_ann(change: Callable[[dict], Any]) -> Callable[[Path], None]:
    return lambda tmp: edit_json(tmp / "ds" / "annotations.json", change)


def edit_sample(scene: int, i: int, change: Callable[[dict], Any]) -> Callable[[Path], None]:
    """Change sample ``i`` of scene ``scene`` in annotations.json."""
    name = SCENES[scene]
    return edit_ann(lambda a: change(a["scene_infos"][name][TOKENS[name][i]]))


def edit_frame(i: int, change: Callable[[dict], Any], scene: int = 0) -> Callable[[Path], None]:
    """Change frame ``i`` of a scene's FrameAnnotation sidecar."""
    return lambda tmp: edit_json(tmp / "ds" / "occtrain" / "frames" / f"{SCENES[scene]}.json", lambda fs: change(fs[i]))


def edit_qa(change: Callable[[list], Any], split: str = "val") -> Callable[[Path], None]:
    return lambda tmp: edit_json(
        tmp / "ds" / "nuscenes_qa" / f"NuScenes_{split}_questions.json", lambda d: change(d["questions"])
    )


def write_text(rel: str, text: str) -> Callable[[Path], None]:
    return lambda tmp: (tmp / rel).write_text(text)


def labels_file(tmp: Path, scene: int = 0, i: int = 1) -> Path:
    return tmp / "ds" / "gts" / SCENES[scene] / TOKENS[SCENES[scene]][i] / "labels.npz"


LABELS = "{tmp}/ds/gts/scene-0000/" + T0[1] + "/labels.npz"


def link_out(rel: str) -> Callable[[Path], None]:
    """``rel`` moved out of the dataset root to ``tmp/outside/`` and a symbolic link left in its place."""

    def setup(tmp: Path) -> None:
        (tmp / "outside").mkdir(exist_ok=True)
        moved = tmp / "outside" / Path(rel).name
        (tmp / rel).rename(moved)
        (tmp / rel).symlink_to(moved)

    return setup


def save_labels(**change: Any) -> Callable[[Path], None]:
    """Overwrite frame 1's labels.npz with valid arrays, some replaced (None drops one)."""

    def setup(tmp: Path) -> None:
        arrays = {k: v for k, v in (hand_labels(1) | change).items() if v is not None}
        np.savez_compressed(labels_file(tmp), **arrays)

    return setup


def corrupt_deflate(path: Path) -> None:
    """Break the first member's deflate stream (reserved block type) but keep the zip intact:
    the archive opens, and the damage shows only when the array is inflated."""
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as z:
        offset = z.infolist()[0].header_offset
    name_len, extra_len = struct.unpack("<HH", data[offset + 26 : offset + 30])
    data[offset + 30 + name_len + extra_len] = 0xFF
    path.write_bytes(bytes(data))


def truncate(rel: str, keep: int) -> Callable[[Path], None]:
    def setup(tmp: Path) -> None:
        path = tmp / rel
        path.write_bytes(path.read_bytes()[:keep])

    return setup


def both(*setups: Callable[[Path], None]) -> Callable[[Path], None]:
    def setup(tmp: Path) -> None:
        for s in setups:
            s(tmp)

    return setup


def nothing(tmp: Path) -> None:
    pass


# -- occtrain score inputs


def forecast(semantics: np.ndarray) -> Callable[[Path], None]:
    """A forecast of the val scene's first sample."""

    def setup(tmp: Path) -> None:
        path = tmp / "fc" / SCENES[1] / T1[0] / "forecast.npz"
        path.parent.mkdir(parents=True)
        np.savez_compressed(path, semantics=semantics)

    return setup


def bad_forecast_deflate(tmp: Path) -> None:
    forecast(np.zeros((6, *GRID_SHAPE), np.uint8))(tmp)
    corrupt_deflate(tmp / "fc" / SCENES[1] / T1[0] / "forecast.npz")


def planning(change: Callable[[dict, dict], Any]) -> Callable[[Path], None]:
    """test_scoring_cli's planning files (tok-a, tok-b), changed by ``change(preds, gts)``."""

    def setup(tmp: Path) -> None:
        p, g = planning_files(tmp)
        preds, gts = json.loads(p.read_text()), json.loads(g.read_text())
        change(preds, gts)
        p.write_text(json.dumps(preds))
        g.write_text(json.dumps(gts))

    return setup


def occupancy_prediction(tmp: Path) -> None:
    path = tmp / "occ" / SCENES[1] / T1[0] / "labels.npz"
    path.parent.mkdir(parents=True)
    np.savez_compressed(path, semantics=np.zeros(GRID_SHAPE, np.float32))


def captions(preds: Any, refs: Any) -> Callable[[Path], None]:
    def setup(tmp: Path) -> None:
        (tmp / "cap.json").write_text(json.dumps(preds))
        (tmp / "ref.json").write_text(json.dumps(refs))

    return setup


def qa_answers(answers: Any, change: Callable[[list], Any] | None = None) -> Callable[[Path], None]:
    """test_scoring_cli's 4 questions, changed by ``change(questions)``, and ``answers``."""

    def setup(tmp: Path) -> None:
        q = qa_questions(tmp / "q.json")
        if change:
            edit_json(q, lambda d: change(d["questions"]))
        (tmp / "a.json").write_text(json.dumps(answers))

    return setup


def export_file(name: str, content: bytes | None = None, keep: int | None = None) -> Callable[[Path], None]:
    def setup(tmp: Path) -> None:
        path = tmp / "run" / "pretrain" / "export" / name
        path.write_bytes(path.read_bytes()[:keep] if content is None else content)

    return setup


def shard_index(change: Callable[[dict], Any]) -> Callable[[Path], None]:
    return lambda tmp: edit_json(tmp / "shards" / "index.json", change)


def other_shards(tmp: Path) -> None:
    (tmp / "out").mkdir()
    (tmp / "out" / "index.json").write_text(json.dumps({"source": {"dataset": "elsewhere"}, "kinds": {}}))


def stray_tar(tmp: Path) -> None:
    (tmp / "out" / "frames").mkdir(parents=True)
    (tmp / "out" / "frames" / "train-000000.tar").write_bytes(b"half a shard")


def drop_key(d: dict, key: str) -> None:
    del d[key]


def duplicate_token(a: dict) -> None:
    """Scene 1 also claims scene 0's last sample."""
    a["scene_infos"][SCENES[1]][T0[-1]] = dict(a["scene_infos"][SCENES[0]][T0[-1]], prev="", next="")


def swap_timestamps(a: dict) -> None:
    infos = a["scene_infos"][SCENES[0]]
    infos[T0[2]]["timestamp"], infos[T0[3]]["timestamp"] = infos[T0[3]]["timestamp"], infos[T0[2]]["timestamp"]


def unlinked_token_timestamps(a: dict) -> None:
    """Neither links nor numeric timestamps order scene 0."""
    for info in a["scene_infos"][SCENES[0]].values():
        info.pop("prev"), info.pop("next")
        info["timestamp"] = "tok-" + info["gt_path"][-30:-12]


def camera(intrinsic: Any) -> dict:
    pose = {"translation": [1.0, 0.0, 1.5], "rotation": [1.0, 0.0, 0.0, 0.0]}
    return {
        "CAM_FRONT_tok": {
            "img_path": "imgs/CAM_FRONT/x.jpg",
            "intrinsic": intrinsic,
            "extrinsic": pose,
            "ego_pose": pose,
        }
    }


def pickled_checkpoint(tmp: Path) -> None:
    """The tokenizer stage cut off under the recipe's own config, its last.ckpt a sound
    archive whose pickle names a class (not what occtrain writes)."""
    import collections

    from occtrain.run.planning import load_recipe

    recipe()(tmp)
    planned = load_recipe(tmp / "r.yaml")[1]
    manifest({"status": "interrupted", "config_hash": planned[0].config_hash, "config": planned[0].config})(tmp)
    (tmp / "run2" / "tokenizer" / "checkpoints").mkdir(parents=True)
    torch.save(
        {"global_step": 2, "counts": collections.OrderedDict(a=1), "evil": Evil()},
        tmp / "run2" / "tokenizer" / "checkpoints" / "last.ckpt",
    )


class Evil:
    """Stands for any class a pickle could name (and run code through)."""


def with_cameras(missing: str = "", corrupt: str = "") -> Callable[[Path], None]:
    """Every sample gets six camera records and 8 x 16 PNGs (the released form: records
    keyed by channel); ``missing`` leaves one file out, ``corrupt`` damages one."""

    def setup(tmp: Path) -> None:
        from PIL import Image

        from occtrain.data.cameras import CAMERA_NAMES

        def change(a: dict) -> None:
            for infos in a["scene_infos"].values():
                for token, info in infos.items():
                    pose = {"translation": [1.0, 0.0, 1.5], "rotation": [1.0, 0.0, 0.0, 0.0]}
                    info["camera_sensor"] = {}
                    for cam in CAMERA_NAMES:
                        rel = f"imgs/{cam}/{token}.png"
                        info["camera_sensor"][cam] = {
                            "img_path": rel,
                            "intrinsic": [[8.0, 0, 8], [0, 8.0, 4], [0, 0, 1]],
                            "extrinsic": pose,
                            "ego_pose": pose,
                        }
                        (tmp / "ds" / rel).parent.mkdir(parents=True, exist_ok=True)
                        Image.new("RGB", (16, 8), (40, 80, 120)).save(tmp / "ds" / rel)

        edit_json(tmp / "ds" / "annotations.json", change)
        if missing:
            (tmp / "ds" / missing).unlink()
        if corrupt:
            data = bytearray((tmp / "ds" / corrupt).read_bytes())
            data[40] ^= 0xFF  # inside the IHDR/IDAT chunks: the CRC no longer matches
            (tmp / "ds" / corrupt).write_bytes(bytes(data))

    return setup


def shards_then(change: Callable[[Path], None], **layout: Any) -> Callable[[Path], None]:
    """Shards of the copy's own dataset in ``tmp/s2`` (frames, 4 per shard, unless ``layout``
    says otherwise), then ``change`` to the dataset."""

    def setup(tmp: Path) -> None:
        from occtrain.data.shards import write_shards

        write_shards(tmp / "ds", tmp / "s2", **{"samples_per_shard": 4, "kinds": ["frames"], **layout})
        change(tmp)

    return setup


def world_without_qa(tmp: Path) -> None:
    shutil.copytree(tmp / "ds", tmp / "noqa")
    shutil.rmtree(tmp / "noqa" / "nuscenes_qa")


def stage_status(status: str) -> Callable[[Path], None]:
    return lambda tmp: edit_json(tmp / "run" / "manifest.json", lambda m: m["stages"]["pretrain"].update(status=status))


FIRST_IMG = f"imgs/CAM_FRONT/{T0[0]}.png"
STALE = ["data", "shards", DS, "--out", "{tmp}/s2", "--kinds", "frames", "--samples-per-shard", "4"]


# -- shorthands for argv
SHARDS_FRAMES = ["data", "shards", DS, "--out", "{tmp}/out", "--kinds", "frames", "--samples-per-shard", "4"]
SHARDS_CLIPS = ["data", "shards", DS, "--out", "{tmp}/out", "--kinds", "clips", "--history", "2", "--future", "3"]
CHECK = ["data", "check", DS]
CHECK_SHARDS = ["data", "check", "{tmp}/shards"]
FORECAST = ["score", "forecast", "--pred", "{tmp}/fc", "--gt", DS]
PLANNING = ["score", "planning", "--pred", "{tmp}/p.json", "--gt", "{tmp}/g.json"]
QA = ["score", "qa", "--pred", "{tmp}/a.json", "--questions", "{tmp}/q.json"]
CAPTIONS = ["score", "captions", "--pred", "{tmp}/cap.json", "--ref", "{tmp}/ref.json"]
EVAL = ["eval", "{tmp}/run/pretrain"]
DRIVE = ["drive", "{tmp}/run/pretrain"]
#: Stage locks a case holds while its command runs (another process's eval or restart).
_HELD: list[Any] = []


def holding(stage: str, shared: bool) -> Callable[[Path], None]:
    """Hold the run's lock of ``stage`` as another process would: shared (scoring it) or
    exclusive (a --restart replacing it). A lock is per open file, so this process's own
    command meets it as another's."""

    def setup(tmp: Path) -> None:
        import fcntl

        path = tmp / "run" / stage / "export" / "config.json"
        fh = open(path)  # noqa: SIM115 (held open past the setup: closed when the case's test ends)
        fcntl.flock(fh.fileno(), fcntl.LOCK_SH if shared else fcntl.LOCK_EX)
        _HELD.append(fh)

    return setup


EXPORT = "{tmp}/run/pretrain/export/"
S0 = f"scene_infos.scene-0000.{T0[0]}"

# ----------------------------------------------------------------------------- recipes and runs

RECIPE = """name: tiny
runs_root: {tmp}/runs
data: {{root: {tmp}/ds, batch_size: 2, samples_per_shard: 4, history: 1, future: 1}}
trainer: {{max_steps: 2, val_check_interval: 2, limit_val_batches: 1}}
stages:
  - name: tokenizer
    kind: tokenizer
    model:
      arch: occworld_vqvae
      occworld_vqvae: {{num_codes: 8, code_dim: 4, base_channels: 4, channel_mult: [1, 1, 1], strides: [4, 5],
                        num_res_blocks: 1, latent_attention: false, z_channels: 4}}
    trainer: {{max_steps: 3}}
  - name: pretrain
    kind: pretrain
    consumes: [tokenizer]
    model: {{family: occllama}}
"""


def with_dagger(text: str) -> str:
    """The tiny recipe, its pretrain reading 2 frames of history, then a planner and a dagger stage."""
    text = text.replace(
        "    model: {family: occllama}\n", "    model: {family: occllama, tasks: {context_frames: 2}}\n"
    )
    return text + (
        "  - {name: planner, kind: planner, consumes: [pretrain]}\n"
        "  - name: closed_loop\n"
        "    kind: dagger\n"
        "    consumes: [pretrain, planner]\n"
        "    model: {rounds: 1, steps_per_round: 2, routes_per_round: 1, seconds: 3}\n"
        "    trainer: {max_steps: 2}\n"
    )


RUN = ["run", "{tmp}/r.yaml", "--run-dir", "{tmp}/run2"]
RECIPE_FILE = "{tmp}/r.yaml"


def recipe(change: Callable[[str], str] = lambda text: text) -> Callable[[Path], None]:
    """Write the tiny recipe (optionally edited) to ``tmp/r.yaml``."""

    def setup(tmp: Path) -> None:
        (tmp / "r.yaml").write_text(change(RECIPE.format(tmp=tmp)))

    return setup


_HELD: list = []


def VISION_ONLY(text: str) -> str:  # noqa: N802 - reads as a constant in the table
    """The tiny recipe with one camera stage instead of its two."""
    return text[: text.index("  - name: tokenizer")] + "  - {name: vision, kind: vision}\n"


def locked_run_dir(tmp: Path) -> None:
    """The run directory held by another ``occtrain run`` (a lock on its own open file)."""
    import fcntl

    recipe()(tmp)
    (tmp / "run2").mkdir()
    fh = open(tmp / "run2" / ".lock", "a+")
    fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    fh.write("pid 4242 on elsewhere\n")
    fh.flush()
    _HELD.append(fh)  # released when the test process ends


def manifest(entry: dict) -> Callable[[Path], None]:
    """A run directory whose manifest holds the tokenizer stage as ``entry``."""

    def setup(tmp: Path) -> None:
        recipe()(tmp)
        (tmp / "run2").mkdir()
        text = json.dumps({"name": "tiny", "stages": {"tokenizer": {"kind": "tokenizer", **entry}}})
        (tmp / "run2" / "manifest.json").write_text(text)
        (tmp / "run2" / "pipeline.yaml").write_text("name: tiny\n")

    return setup


DONE_OTHER_CONFIG = {"status": "done", "config_hash": "0123456789abcdef", "config": {"optim": {"lr": 0.5}}}
CUT_OTHER_CONFIG = {"status": "interrupted", "config_hash": "0123456789abcdef", "config": {"optim": {"lr": 0.5}}}


def cut_off_under_other_config(tmp: Path) -> None:
    manifest(CUT_OTHER_CONFIG)(tmp)
    (tmp / "run2" / "tokenizer" / "checkpoints").mkdir(parents=True)
    (tmp / "run2" / "tokenizer" / "checkpoints" / "last.ckpt").write_bytes(b"PK")


# -- setups: names and deletions


def victim_beside(tmp: Path) -> None:
    """A directory a hostile stage name would reach from a run at ``tmp/a/run2``."""
    (tmp / "victim").mkdir()
    (tmp / "victim" / "precious.txt").write_text("mine")


def stage_named(name: str) -> Callable[[Path], None]:
    """The tiny recipe with its first stage called ``name`` (``{tmp}`` filled in)."""

    def setup(tmp: Path) -> None:
        named = name.format(tmp=tmp)
        victim_beside(tmp)
        recipe(
            lambda t: t.replace("  - name: tokenizer\n", f"  - name: '{named}'\n").replace(
                "consumes: [tokenizer]", f"consumes: ['{named}']"
            )
        )(tmp)

    return setup


ESCAPING_RUN = ["run", "{tmp}/r.yaml", "--run-dir", "{tmp}/a/run2"]


def manifest_naming(stage: str) -> Callable[[Path], None]:
    """A run directory whose manifest (edited by hand) records a stage called ``stage``."""

    def setup(tmp: Path) -> None:
        recipe()(tmp)
        (tmp / "run2").mkdir()
        (tmp / "run2" / "manifest.json").write_text(
            json.dumps({"name": "tiny", "stages": {stage: {"kind": "tokenizer", "status": "done"}}})
        )

    return setup


# -- setups: restart and validate


def finished_run(tmp: Path) -> None:
    """The tiny recipe's run at ``tmp/run2``, both stages done with exports and checkpoints."""
    recipe()(tmp)
    stages = {}
    for name, kind in (("tokenizer", "tokenizer"), ("pretrain", "pretrain")):
        for rel in ("export/model.safetensors", "export/config.json", "checkpoints/last.ckpt", "metrics.json"):
            (tmp / "run2" / name / rel).parent.mkdir(parents=True, exist_ok=True)
            (tmp / "run2" / name / rel).write_text(f"{name} {rel}")
        stages[name] = {"kind": kind, "status": "done"}
    (tmp / "run2" / "manifest.json").write_text(json.dumps({"name": "tiny", "stages": stages}))
    (tmp / "run2" / "pipeline.yaml").write_text("name: tiny\n")
    victim_beside(tmp)


# -- setups: eval and outputs


def full_disk(mp: pytest.MonkeyPatch) -> None:
    """A disk with room for a file's name but none for its bytes."""
    import errno
    import os

    def refuse(fd: int, data: bytes) -> int:
        raise OSError(errno.ENOSPC, "No space left on device")

    mp.setattr(os, "write", refuse)


def tokenizer_done(tmp: Path) -> None:
    edit_json(
        tmp / "run" / "manifest.json", lambda m: m["stages"].update(tokenizer={"kind": "tokenizer", "status": "done"})
    )


# -- setups: plan-memory

PLAN = ["plan-memory", RECIPE_FILE]
SCALE_LLAMA = str(REPO / "recipes" / "scale" / "occllama_llama8b.yaml")
LLM_DIR = "{tmp}/llm"


def llm_dir(**change: Any) -> Callable[[Path], None]:
    """The tiny recipe, and ``tmp/llm``: Llama-3.1-8B's config.json (no weights) with ``change``."""

    def setup(tmp: Path) -> None:
        recipe()(tmp)
        config = json.loads((REPO / "configs" / "llm" / "llama-3.1-8b" / "config.json").read_text())
        (tmp / "llm").mkdir()
        (tmp / "llm" / "config.json").write_text(json.dumps({**config, **change}))

    return setup


# -- setups: plugins


def with_plugin(module: str, file: str = "r.yaml") -> Callable[[Path], None]:
    """The tiny recipe (or the run's pipeline.yaml) loading plugin ``module``, one of the
    test-only plugins in tests/plugins/ (importable as ``plugins.*``, outside the tree the
    case checks). A plugin that fails leaves nothing behind: Python drops a module whose
    import raised, and the registry refuses a clash before it changes anything."""

    def setup(tmp: Path) -> None:
        if file == "r.yaml":
            recipe()(tmp)
        with open(tmp / file, "a") as fh:
            fh.write(f"plugins: [{module}]\n")

    return setup


PLUGIN_RAISES = "failed while being imported: RuntimeError: the broken plugin's settings are missing"

# -- setups: exports, load and trackers


# -- setups: data
def released_cameras(drop: str = "") -> Callable[[Path], None]:
    """Cameras in the released files' form (``img_path`` relative to ``imgs/``), ``drop``
    (a folder or an image under ``imgs/``) deleted."""

    def setup(tmp: Path) -> None:
        with_cameras()(tmp)

        def strip(a: dict) -> None:
            for infos in a["scene_infos"].values():
                for info in infos.values():
                    for record in info["camera_sensor"].values():
                        record["img_path"] = record["img_path"].removeprefix("imgs/")

        edit_json(tmp / "ds" / "annotations.json", strip)
        gone = tmp / "ds" / "imgs" / drop
        if drop:
            shutil.rmtree(gone) if gone.is_dir() else gone.unlink()

    return setup


def without_folder(folder: str) -> Callable[[Path], None]:
    """Cameras in the README's form (``img_path`` from the root), ``folder`` deleted."""
    return both(with_cameras(), lambda tmp: shutil.rmtree(tmp / "ds" / folder))


def plain_copy(tmp: Path) -> None:
    """``cp -r ds ds2``: the same bytes, every file with a new mtime."""
    shutil.copytree(tmp / "ds", tmp / "ds2", copy_function=shutil.copy)


NO_BACK = "{tmp}/ds/imgs/CAM_BACK: camera folder not found, while {tmp}/ds/annotations.json names images in it"
REBUILD_COPY = (
    "or replace them with `occtrain data shards {tmp}/ds2 --out {tmp}/s2 --samples-per-shard 4 "
    "--history 1 --future 1 --rebuild`"
)


# -- setups: issue 58, round four
def npz_claiming(path: Path, shape: tuple[int, ...]) -> None:
    """A labels.npz whose 'semantics' header declares ``shape`` over a few bytes of data (the
    masks as they were): a few hundred bytes on disk, however large the shape it claims."""
    import io

    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "|u1", "fortran_order": False, "shape": shape})
    masks = {k: v for k, v in hand_labels(1).items() if k != "semantics"}
    np.savez_compressed(path, **masks)
    with zipfile.ZipFile(path, "a", zipfile.ZIP_DEFLATED) as z:
        z.writestr("semantics.npy", header.getvalue() + bytes(64))


#: No process has this pid (Linux's pids are below 2**22), so a rebuild named by it was killed.
DEAD_PID = 2**22
HOST = socket.gethostname()
KILLED_REBUILD = f".shards.rebuild-{DEAD_PID}.{HOST}-x1y2z3"


def killed_rebuild(rel: str) -> Callable[[Path], None]:
    """The half-written shards a `data shards --rebuild` killed with -9 leaves beside its --out."""

    def setup(tmp: Path) -> None:
        (tmp / rel / "frames").mkdir(parents=True)
        (tmp / rel / "frames" / "train-000000.tar").write_bytes(b"half a shard")

    return setup


def earlier_prediction(rel: str) -> Callable[[Path], None]:
    """A file an earlier ``eval --save-predictions tmp/preds`` wrote."""

    def setup(tmp: Path) -> None:
        (tmp / "preds" / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp / "preds" / rel).write_text("an earlier eval's")

    return setup


#: A value nested 100,000 deep, and an integer of 5,016 digits (Python reads at most 4,300).
DEEP_JSON = '{"scene_infos": ' + "[" * 100_000 + "]" * 100_000 + "}"
LONG_INT_JSON = '{"scene_infos": {}, "count": ' + "7" * 5016 + "}"


CASES: list[Case] = [
    # ------------------------------------------------------------------ annotations.json
    Case("ann-not-json", write_text("ds/annotations.json", "{not json"), SHARDS_FRAMES, 2, f"{ANN}: not valid JSON"),
    Case(
        "ann-not-an-object", write_text("ds/annotations.json", "[]"), SHARDS_FRAMES, 2, f"{ANN}: no 'scene_infos' key"
    ),
    Case(
        "ann-translation-string",
        edit_sample(0, 0, lambda s: s["ego_pose"].update(translation="1,2,0")),
        SHARDS_FRAMES,
        2,
        f'{ANN}: {S0}.ego_pose.translation is the string "1,2,0", expected a list of 3 numbers',
    ),
    Case(
        "ann-rotation-three-numbers",
        edit_sample(0, 0, lambda s: s["ego_pose"].update(rotation=[1.0, 0.0, 0.0])),
        SHARDS_FRAMES,
        2,
        f"{ANN}: {S0}.ego_pose.rotation holds 3 items, expected a list of 4 numbers",
    ),
    Case(
        "ann-translation-nan",
        edit_sample(0, 0, lambda s: s["ego_pose"]["translation"].__setitem__(0, float("nan"))),
        SHARDS_FRAMES,
        2,
        f"{ANN}: {S0}.ego_pose.translation[0] is NaN, expected a number",
    ),
    Case(
        "ann-rotation-zero-quaternion",
        edit_sample(0, 2, lambda s: s["ego_pose"].update(rotation=[0.0, 0.0, 0.0, 0.0])),
        ["data", "stats", DS],
        2,
        f"{ANN}: scene_infos.scene-0000.{T0[2]}.ego_pose.rotation [0.0, 0.0, 0.0, 0.0] is not a unit quaternion "
        "(its norm is 0)",
    ),
    Case(
        "ann-translation-far-beyond-any-map",
        edit_sample(0, 2, lambda s: s["ego_pose"]["translation"].__setitem__(0, 1e308)),
        ["data", "shards", DS, "--out", "{tmp}/out", "--kinds", "frames"],
        2,
        f"{ANN}: scene_infos.scene-0000.{T0[2]}.ego_pose.translation [1e+308, 0.0, 0.0] is not within 1e+06 m",
    ),
    Case(
        "ann-pose-jumps-500-m",
        edit_sample(0, 3, lambda s: s["ego_pose"]["translation"].__setitem__(1, 500.0)),
        SHARDS_FRAMES,
        2,
        f"{ANN}: scene_infos.scene-0000.{T0[3]}.ego_pose is 500.0 m from the sample before it ({T0[2]}) after 0.5 s, "
        "faster than 70 m/s",
    ),
    Case(
        "labels-link-out-of-the-root",
        link_out("ds/gts/scene-0000/" + T0[1] + "/labels.npz"),
        ["data", "stats", DS, "--split", "train"],
        2,
        (LABELS + ": a link out of the dataset root {tmp}/ds (to {tmp}/outside/labels.npz)", "link the whole root"),
    ),
    Case(
        "sidecar-link-out-of-the-root",
        link_out("ds/occtrain/frames/scene-0000.json"),
        SHARDS_CLIPS,
        2,
        SIDECAR + ": a link out of the dataset root {tmp}/ds",
    ),
    Case(
        "ann-rotation-bool",
        edit_sample(0, 0, lambda s: s["ego_pose"]["rotation"].__setitem__(0, True)),
        ["data", "show", DS, "--out", "{tmp}/b.png"],
        2,
        f"{ANN}: {S0}.ego_pose.rotation[0] is true, expected a number",
    ),
    Case(
        "ann-no-ego-pose",
        edit_sample(0, 0, lambda s: drop_key(s, "ego_pose")),
        SHARDS_FRAMES,
        2,
        f"{ANN}: {S0}.ego_pose is missing, expected an object",
    ),
    Case(
        "ann-timestamp-float",
        edit_sample(0, 0, lambda s: s.update(timestamp=1.5e14)),
        SHARDS_FRAMES,
        2,
        f"{ANN}: {S0}.timestamp is the number 1.5e+14, expected an integer or a string",
    ),
    Case(
        "ann-prev-is-a-number",
        edit_sample(0, 0, lambda s: s.update(prev=0)),
        SHARDS_FRAMES,
        2,
        f"{ANN}: {S0}.prev is the integer 0, expected a string",
    ),
    Case(
        "ann-gt-path-list",
        edit_sample(0, 0, lambda s: s.update(gt_path=["gts"])),
        SHARDS_FRAMES,
        2,
        f"{ANN}: {S0}.gt_path is a list of 1 item, expected a string",
    ),
    Case(
        "ann-camera-intrinsic-2x3",
        edit_sample(0, 0, lambda s: s.update(camera_sensor=camera([[1.0, 0.0, 0.5]] * 2))),
        SHARDS_FRAMES,
        2,
        f"{ANN}: {S0}.camera_sensor.CAM_FRONT_tok.intrinsic holds 2 items, expected a list of 3 lists of 3 numbers",
    ),
    Case(
        "ann-scene-is-a-list",
        edit_ann(lambda a: a["scene_infos"].update({SCENES[0]: []})),
        SHARDS_FRAMES,
        2,
        f"{ANN}: scene_infos.scene-0000 is a list of 0 items, expected an object",
    ),
    Case(
        "ann-split-is-a-string",
        edit_ann(lambda a: a.update(train_split="scene-0000")),
        SHARDS_FRAMES,
        2,
        f'{ANN}: train_split is the string "scene-0000", expected a list of strings',
    ),
    Case(
        "ann-split-names-unknown-scene",
        edit_ann(lambda a: a.update(val_split=["scene-9999"])),
        SHARDS_FRAMES,
        2,
        f"{ANN}: val_split names scene 'scene-9999' that has no scene_infos entry",
    ),
    Case(
        "ann-no-order",
        edit_ann(unlinked_token_timestamps),
        SHARDS_FRAMES,
        2,
        f"{ANN}: scene_infos.scene-0000.{T0[0]}.timestamp is not a number of microseconds",
    ),
    Case(
        "ann-as-score-ground-truth",
        edit_sample(1, 0, lambda s: s["ego_pose"].update(translation=None)),
        ["score", "occupancy", "--pred", "{tmp}/ds/gts", "--gt", DS],
        2,
        f"{ANN}: scene_infos.scene-0001.{T1[0]}.ego_pose.translation is null, expected a list of 3 numbers",
    ),
    Case(
        "check-ann-lists-every-problem",
        edit_ann(
            lambda a: [
                a["scene_infos"][SCENES[0]][T0[0]].update(prev=1),
                a["scene_infos"][SCENES[1]][T1[4]].update(timestamp=None),
            ]
        ),
        CHECK,
        1,
        (
            f"{ANN}: scene_infos.scene-0000.{T0[0]}.prev is the integer 1, expected a string",
            f"{ANN}: scene_infos.scene-0001.{T1[4]}.timestamp is null, expected an integer or a string",
        ),
    ),
    Case(
        "check-timestamps-decrease",
        edit_ann(swap_timestamps),
        CHECK,
        1,
        f"{ANN}: scene 'scene-0000' timestamps do not increase",
    ),
    Case(
        "check-duplicate-token",
        edit_ann(duplicate_token),
        CHECK,
        1,
        f"{ANN}: sample token {T0[-1]} is in both scene_infos.scene-0000 and scene_infos.scene-0001",
    ),
    Case(
        "check-not-a-unit-quaternion",
        edit_sample(0, 3, lambda s: s["ego_pose"].update(rotation=[0.0, 0.0, 0.0, 0.0])),
        CHECK,
        1,
        f"{ANN}: scene_infos.scene-0000.{T0[3]}.ego_pose.rotation [0.0, 0.0, 0.0, 0.0] is not a unit quaternion",
    ),
    # ------------------------------------------------------------------ labels.npz
    Case(
        "labels-garbage",
        lambda tmp: labels_file(tmp).write_bytes(b"garbage"),
        SHARDS_FRAMES,
        2,
        f"{LABELS}: corrupt or truncated .npz (not a zip archive)",
    ),
    Case(
        "labels-truncated",
        lambda tmp: labels_file(tmp).write_bytes(labels_file(tmp).read_bytes()[:300]),
        SHARDS_FRAMES,
        2,
        f"{LABELS}: corrupt or truncated .npz",
    ),
    Case(
        "labels-corrupt-deflate",
        lambda tmp: corrupt_deflate(labels_file(tmp)),
        SHARDS_FRAMES,
        2,
        f"{LABELS}: corrupt or truncated .npz (zlib.error: Error -3 while decompressing data",
    ),
    Case(
        "labels-corrupt-deflate-check",
        lambda tmp: corrupt_deflate(labels_file(tmp)),
        CHECK,
        1,
        f"{LABELS}: corrupt or truncated .npz (zlib.error",
    ),
    Case(
        "labels-pickled",
        save_labels(semantics=np.array([{"evil": 1}], dtype=object)),
        SHARDS_FRAMES,
        2,
        f"{LABELS}: holds an object (pickled) array; refusing to load it",
    ),
    Case(
        "labels-wrong-shape",
        save_labels(semantics=np.zeros((200, 200, 8), np.uint8)),
        SHARDS_FRAMES,
        2,
        f"{LABELS}: 'semantics' has shape (200, 200, 8)",
    ),
    Case(
        "labels-float",
        save_labels(semantics=np.zeros(GRID_SHAPE, np.float32)),
        SHARDS_FRAMES,
        2,
        f"{LABELS}: 'semantics' has dtype float32, expected uint8",
    ),
    Case(
        "labels-class-18",
        save_labels(semantics=np.full(GRID_SHAPE, 18, np.uint8)),
        SHARDS_FRAMES,
        2,
        f"{LABELS}: 'semantics' holds class 18",
    ),
    Case(
        "labels-no-camera-mask",
        save_labels(mask_camera=None),
        SHARDS_FRAMES,
        2,
        f"{LABELS}: missing array 'mask_camera'",
    ),
    Case(
        "labels-mask-of-twos",
        save_labels(mask_lidar=np.full(GRID_SHAPE, 2, np.uint8)),
        SHARDS_FRAMES,
        2,
        f"{LABELS}: 'mask_lidar' holds values other than 0/1",
    ),
    Case("labels-missing", lambda tmp: labels_file(tmp).unlink(), SHARDS_FRAMES, 2, f"{LABELS}: file not found"),
    Case(
        "check-labels-all-visible",
        save_labels(mask_camera=np.ones(GRID_SHAPE, np.uint8)),
        CHECK,
        1,
        f"{LABELS}: mask_camera is all ones",
    ),
    # ------------------------------------------------------------------ frame sidecars
    Case(
        "frames-no-ego-future",
        edit_frame(2, lambda f: drop_key(f, "ego_future")),
        SHARDS_CLIPS,
        2,
        f"{SIDECAR}: [2].ego_future is missing, expected a list of 6 lists of 2 numbers",
    ),
    Case(
        "frames-translation-string",
        edit_frame(3, lambda f: f["ego_pose"].update(translation="7.5, 0")),
        SHARDS_CLIPS,
        2,
        f'{SIDECAR}: [3].ego_pose.translation is the string "7.5, 0", expected a list of 3 numbers',
    ),
    Case(
        "frames-not-json",
        write_text("ds/occtrain/frames/scene-0000.json", "[{"),
        SHARDS_CLIPS,
        2,
        f"{SIDECAR}: not valid JSON",
    ),
    Case(
        "frames-not-a-list",
        write_text("ds/occtrain/frames/scene-0000.json", "{}"),
        SHARDS_CLIPS,
        2,
        f"{SIDECAR}: the top level is an object, expected a list of objects",
    ),
    Case(
        "frames-unknown-command",
        edit_frame(0, lambda f: f.update(command="fly")),
        SHARDS_CLIPS,
        2,
        f'{SIDECAR}: [0].command is the string "fly", expected one of "turn right", "turn left", "go straight"',
    ),
    Case(
        "frames-mask-of-two",
        edit_frame(0, lambda f: f["ego_future_mask"].__setitem__(1, 2)),
        SHARDS_CLIPS,
        2,
        f"{SIDECAR}: [0].ego_future_mask[1] is the integer 2, expected one of 0, 1",
    ),
    Case(
        "frames-short-future",
        edit_frame(1, lambda f: f["ego_future"].pop()),
        SHARDS_CLIPS,
        2,
        f"{SIDECAR}: [1].ego_future holds 5 items, expected a list of 6 lists of 2 numbers",
    ),
    Case(
        "frames-box-category",
        edit_frame(
            4,
            lambda f: f["boxes"].append(
                {
                    "track_id": 1,
                    "category": "spaceship",
                    "center": [1.0, 2.0, 0.5],
                    "size": [4.0, 2.0, 1.5],
                    "yaw": 0.0,
                    "velocity": [0.0, 0.0],
                    "attribute": "",
                }
            ),
        ),
        SHARDS_CLIPS,
        2,
        f'{SIDECAR}: [4].boxes[0].category is the string "spaceship", expected one of "others"',
    ),
    Case(
        "frames-speed-infinite",
        edit_frame(5, lambda f: f.update(ego_speed=float("inf"))),
        ["data", "show", DS, "--scene", "scene-0000", "--out", "{tmp}/b.png"],
        2,
        f"{SIDECAR}: [5].ego_speed is Infinity, expected a number",
    ),
    Case(
        "frames-token-mismatch",
        edit_frame(0, lambda f: f.update(token="not-a-sample")),
        SHARDS_CLIPS,
        2,
        f"{SIDECAR}: frame tokens do not match the samples of scene_infos.scene-0000",
    ),
    Case(
        "frames-one-scene-lacks-its-sidecar",
        lambda tmp: (tmp / "ds/occtrain/frames/scene-0001.json").unlink(),
        SHARDS_CLIPS,
        2,
        "{tmp}/ds/occtrain/frames/scene-0001.json: missing while 1 other scenes have their frame sidecar",
    ),
    Case(
        "check-frames-lists-every-problem",
        both(edit_frame(2, lambda f: drop_key(f, "ego_future")), edit_frame(6, lambda f: f.update(index="6"))),
        CHECK,
        1,
        (
            f"{SIDECAR}: [2].ego_future is missing, expected a list of 6 lists of 2 numbers",
            f'{SIDECAR}: [6].index is the string "6", expected an integer',
        ),
    ),
    Case(
        "check-frames-disagree-with-poses",
        edit_frame(1, lambda f: f["ego_future"].__setitem__(0, [9.0, 9.0])),
        CHECK,
        1,
        f"{SIDECAR}: [1].ego_future[0] [9.0, 9.0] disagrees with the ego poses",
    ),
    Case(
        "check-frames-box-count",
        edit_frame(1, lambda f: f["agent_futures"].append([[0.0, 0.0]] * 6)),
        CHECK,
        1,
        f"{SIDECAR}: [1].agent_futures has 1 entries for 0 boxes",
    ),
    # ------------------------------------------------------------------ NuScenes-QA sidecars
    Case(
        "qa-not-json",
        write_text("ds/nuscenes_qa/NuScenes_val_questions.json", '{"questions": ['),
        SHARDS_CLIPS,
        2,
        f"{QA_VAL}: not valid JSON",
    ),
    Case(
        "qa-top-level-list",
        write_text("ds/nuscenes_qa/NuScenes_val_questions.json", "[]"),
        SHARDS_CLIPS,
        2,
        f"{QA_VAL}: the top level is a list of 0 items, expected an object; NuScenes-QA format is",
    ),
    Case(
        "qa-entry-not-an-object",
        edit_qa(lambda qs: qs.__setitem__(0, "Are there any cars?")),
        SHARDS_CLIPS,
        2,
        f'{QA_VAL}: questions[0] is the string "Are there any cars?", expected an object',
    ),
    Case(
        "qa-sample-token-list",
        edit_qa(lambda qs: qs[1].update(sample_token=[T1[1]])),
        SHARDS_CLIPS,
        2,
        f"{QA_VAL}: questions[1].sample_token is a list of 1 item, expected a string",
    ),
    Case(
        "qa-unknown-template",
        edit_qa(lambda qs: qs[2].update(template_type="why")),
        SHARDS_CLIPS,
        2,
        f'{QA_VAL}: questions[2].template_type is the string "why", expected one of "exist", "count"',
    ),
    Case(
        "qa-num-hop-2",
        edit_qa(lambda qs: qs[3].update(num_hop=2)),
        SHARDS_CLIPS,
        2,
        f"{QA_VAL}: questions[3].num_hop is the integer 2, expected one of 0, 1",
    ),
    Case(
        "qa-no-answer",
        edit_qa(lambda qs: drop_key(qs[0], "answer"), split="train"),
        SHARDS_CLIPS,
        2,
        "{tmp}/ds/nuscenes_qa/NuScenes_train_questions.json: questions[0].answer is missing, expected a string",
    ),
    Case(
        "check-qa-outside-split",
        edit_qa(lambda qs: qs[0].update(sample_token=T0[0])),
        CHECK,
        1,
        f"{QA_VAL}: questions[0].sample_token '{T0[0]}' is not a sample of the val split",
    ),
    Case(
        "check-qa-lists-every-problem",
        edit_qa(lambda qs: [qs[0].update(num_hop=True), qs[5].update(answer=5)]),
        CHECK,
        1,
        (
            f"{QA_VAL}: questions[0].num_hop is true, expected one of 0, 1",
            f"{QA_VAL}: questions[5].answer is the integer 5, expected a string",
        ),
    ),
    # ------------------------------------------------------------------ shards
    Case(
        "shards-out-holds-other-shards",
        other_shards,
        SHARDS_FRAMES,
        2,
        "{tmp}/out: already holds shards of a different dataset or layout",
    ),
    Case(
        "shards-out-index-not-json",
        both(other_shards, write_text("out/index.json", "{")),
        SHARDS_FRAMES,
        2,
        "{tmp}/out/index.json: not valid JSON",
    ),
    Case("shards-out-holds-a-stray-tar", stray_tar, SHARDS_FRAMES, 2, "{tmp}/out: holds shards without an index.json"),
    Case(
        "shards-zero-per-shard",
        nothing,
        ["data", "shards", DS, "--out", "{tmp}/out", "--samples-per-shard", "0"],
        2,
        "samples_per_shard is 0; it must be a whole number of at least 1",
    ),
    Case(
        "check-shards-index-escapes",
        shard_index(lambda i: i["kinds"]["frames"]["train"][0].update(file="../../ds/annotations.json")),
        CHECK_SHARDS,
        1,
        "{tmp}/shards/index.json: kinds.frames.train[0].file '../../ds/annotations.json' is not a file name",
    ),
    Case(
        "check-shards-index-count-string",
        shard_index(lambda i: i["kinds"]["frames"]["val"][1].update(samples="4")),
        CHECK_SHARDS,
        1,
        '{tmp}/shards/index.json: kinds.frames.val[1].samples is the string "4", expected an integer',
    ),
    Case(
        "check-shards-index-is-a-list",
        write_text("shards/index.json", "[]"),
        CHECK_SHARDS,
        1,
        "{tmp}/shards/index.json: the top level is a list of 0 items, expected an object",
    ),
    Case(
        "check-shards-truncated",
        truncate("shards/frames/train-000001.tar", 3000),
        CHECK_SHARDS,
        1,
        "{tmp}/shards/frames/train-000001.tar",
    ),
    Case(
        "check-shards-missing",
        lambda tmp: (tmp / "shards/frames/val-000000.tar").unlink(),
        CHECK_SHARDS,
        1,
        "{tmp}/shards/frames/val-000000.tar: listed in index.json but missing",
    ),
    Case(
        "check-shards-wrong-count",
        shard_index(lambda i: i["kinds"]["frames"]["val"][1].update(samples=9)),
        CHECK_SHARDS,
        1,
        "{tmp}/shards/frames/val-000001.tar: holds 4 samples, index.json says 9",
    ),
    # ------------------------------------------------------------------ occtrain score
    Case(
        "forecast-float-labels",
        forecast(np.full((6, *GRID_SHAPE), 4.0, np.float32)),
        FORECAST,
        2,
        f"{{tmp}}/fc/scene-0001/{T1[0]}/forecast.npz: 'semantics' has dtype float32; save class indices 0..17 as uint8",
    ),
    Case(
        "forecast-nan-labels",
        forecast(np.full((6, *GRID_SHAPE), np.nan, np.float16)),
        FORECAST,
        2,
        f"{{tmp}}/fc/scene-0001/{T1[0]}/forecast.npz: 'semantics' has dtype float16",
    ),
    Case(
        "forecast-negative-labels",
        forecast(np.full((6, *GRID_SHAPE), -1, np.int8)),
        FORECAST,
        2,
        f"{{tmp}}/fc/scene-0001/{T1[0]}/forecast.npz: 'semantics' holds class -1; Occ3D classes are 0..17",
    ),
    Case(
        "forecast-bool-labels",
        forecast(np.zeros((6, *GRID_SHAPE), bool)),
        FORECAST,
        2,
        f"{{tmp}}/fc/scene-0001/{T1[0]}/forecast.npz: 'semantics' has dtype bool",
    ),
    Case(
        "forecast-corrupt-deflate",
        bad_forecast_deflate,
        FORECAST,
        2,
        f"{{tmp}}/fc/scene-0001/{T1[0]}/forecast.npz: corrupt or truncated .npz",
    ),
    Case(
        "forecast-pickled",
        forecast(np.array([{"evil": 1}], dtype=object)),
        FORECAST,
        2,
        f"{{tmp}}/fc/scene-0001/{T1[0]}/forecast.npz: holds an object (pickled) array",
    ),
    Case(
        "occupancy-float-prediction",
        occupancy_prediction,
        ["score", "occupancy", "--pred", "{tmp}/occ", "--gt", DS, "--split", "val", "--allow-missing"],
        2,
        f"{{tmp}}/occ/scene-0001/{T1[0]}/labels.npz: 'semantics' has dtype float32, expected uint8",
    ),
    Case(
        "planning-mask-of-strings",
        planning(lambda p, g: g["tok-b"].update(mask=["1", "1", "1", "1", "1", "0"])),
        PLANNING,
        2,
        '{tmp}/g.json: tok-b.mask[0] is the string "1", expected one of 0, 1, true, false',
    ),
    Case(
        "planning-mask-of-twos",
        planning(lambda p, g: g["tok-a"].update(mask=[1, 1, 2, 1, 1, 1])),
        PLANNING,
        2,
        "{tmp}/g.json: tok-a.mask[2] is the integer 2, expected one of 0, 1, true, false",
    ),
    Case(
        "planning-nan-prediction",
        planning(lambda p, g: p["tok-b"][3].__setitem__(0, float("nan"))),
        PLANNING,
        2,
        "{tmp}/p.json: tok-b[3][0] is NaN, expected a number",
    ),
    Case(
        "planning-infinite-truth",
        planning(lambda p, g: g["tok-a"]["traj"][0].__setitem__(1, float("-inf"))),
        PLANNING,
        2,
        "{tmp}/g.json: tok-a.traj[0][1] is -Infinity, expected a number",
    ),
    Case(
        "planning-numbers-as-strings",
        planning(lambda p, g: p.update({"tok-a": [["2.5", "0"]] * 6})),
        PLANNING,
        2,
        '{tmp}/p.json: tok-a[0][0] is the string "2.5", expected a number',
    ),
    Case(
        "planning-agents-not-boxes",
        planning(lambda p, g: g["tok-a"]["agents"].__setitem__(2, "none")),
        PLANNING,
        2,
        '{tmp}/g.json: tok-a.agents[2] is the string "none", expected a list of lists of 5 numbers',
    ),
    Case(
        "planning-out-is-a-directory",
        planning(lambda p, g: None),
        [*PLANNING, "--out", "{tmp}/ds"],
        2,
        "{tmp}/ds: is a directory; --out takes a file name",
    ),
    Case(
        "captions-number",
        captions({"a": 3}, {"a": ["x"]}),
        CAPTIONS,
        2,
        "{tmp}/cap.json: a is the integer 3, expected a string",
    ),
    Case(
        "captions-reference-numbers",
        captions({"a": "x"}, {"a": ["x", 2]}),
        CAPTIONS,
        2,
        "{tmp}/ref.json: a is a list of 2 items, expected a string or a list of strings",
    ),
    Case(
        "qa-answer-bool", qa_answers(["yes", True, "1", "car"]), QA, 2, "{tmp}/a.json: [1] is true, expected a string"
    ),
    Case(
        "qa-questions-without-answer",
        qa_answers(["yes", "2", "1", "car"], lambda qs: drop_key(qs[1], "answer")),
        QA,
        2,
        "{tmp}/q.json: questions[1].answer is missing, expected a string",
    ),
    Case(
        "qa-questions-hop-string",
        qa_answers(["yes", "2", "1", "car"], lambda qs: qs[2].update(num_hop="1")),
        QA,
        2,
        '{tmp}/q.json: questions[2].num_hop is the string "1", expected one of 0, 1',
    ),
    # ------------------------------------------------------------------ exports
    Case(
        "export-config-not-json",
        export_file("config.json", b'{"stage_kind": '),
        EVAL,
        2,
        EXPORT + "config.json: unreadable export config",
    ),
    Case(
        "export-config-a-list",
        export_file("config.json", b"[]"),
        EVAL,
        2,
        EXPORT + "config.json: is not a JSON object (found a list); re-run the stage that wrote it",
    ),
    Case(
        "export-weights-truncated",
        export_file("model.safetensors", keep=40),
        EVAL,
        2,
        EXPORT + "model.safetensors: unreadable weights",
    ),
    Case(
        "export-weights-garbage",
        export_file("model.safetensors", b"\x00" * 3),
        EVAL,
        2,
        EXPORT + "model.safetensors: unreadable weights",
    ),
    # ------------------------------------------------------------------ data synth / show
    Case(
        "synth-into-another-dataset",
        nothing,
        ["data", "synth", "--out", DS, "--scenes", "1", "--val-scenes", "1", "--frames", "8"],
        2,
        "{tmp}/ds: already holds a different dataset",
    ),
    Case(
        "synth-into-a-foreign-directory",
        nothing,
        ["data", "synth", "--out", "{tmp}/ds/gts", "--scenes", "1", "--frames", "8"],
        2,
        "{tmp}/ds/gts: exists and is not an occtrain dataset",
    ),
    Case(
        "synth-no-frames",
        nothing,
        ["data", "synth", "--out", "{tmp}/new", "--frames", "0"],
        2,
        "synth needs at least one train scene and one frame per scene",
    ),
    Case(
        "synth-no-workers",
        nothing,
        ["data", "synth", "--out", "{tmp}/new", "--workers", "0"],
        2,
        "--workers 0: give at least 1 process",
    ),
    Case(
        "synth-camera-size-not-hxw",
        nothing,
        ["data", "synth", "--out", "{tmp}/new", "--cameras", "144by256"],
        2,
        "--cameras 144by256: give the image size as HxW pixels",
    ),
    Case(
        "synth-camera-size-half-zero",
        nothing,
        ["data", "synth", "--out", "{tmp}/new", "--cameras", "144x0"],
        2,
        "synth.camera_height=144, synth.camera_width=0: both positive, or both 0",
    ),
    Case(
        "show-unknown-scene",
        nothing,
        ["data", "show", DS, "--scene", "scene-9999", "--out", "{tmp}/b.png"],
        2,
        "{tmp}/ds: no scene 'scene-9999'",
    ),
    Case(
        "show-out-under-a-file",
        nothing,
        ["data", "show", DS, "--out", "{tmp}/ds/annotations.json/b.png"],
        2,
        "{tmp}/ds/annotations.json/b.png: cannot write the picture",
    ),
    Case(
        "show-zero-scale",
        nothing,
        ["data", "show", DS, "--scale", "0", "--out", "{tmp}/b.png"],
        2,
        "--scale 0: must be at least 1",
    ),
    # ------------------------------------------------------------------ recipes, overrides, run directories
    Case(
        "recipe-without-name", recipe(lambda t: t.replace("name: tiny\n", "")), RUN, 2, RECIPE_FILE + " has no 'name:'"
    ),
    Case(
        "stage-without-kind",
        recipe(lambda t: t.replace("    kind: tokenizer\n", "")),
        RUN,
        2,
        "stages[0] in " + RECIPE_FILE + " has no 'kind:'",
    ),
    Case(
        "stage-without-name",
        recipe(lambda t: t.replace("  - name: tokenizer\n    kind", "  - kind")),
        RUN,
        2,
        "stages[0] in " + RECIPE_FILE + " has no 'name:'",
    ),
    Case(
        "recipe-unknown-key",
        recipe(lambda t: t + "trainr: {}\n"),
        RUN,
        2,
        "unknown key 'trainr' in " + RECIPE_FILE + "; did you mean 'trainer'?",
    ),
    Case("recipe-not-yaml", recipe(lambda t: t + "stages: [\n"), RUN, 2, RECIPE_FILE + " line"),
    Case("recipe-missing", nothing, ["run", "{tmp}/none.yaml"], 2, "config file not found: {tmp}/none.yaml"),
    Case(
        "recipe-stages-not-a-list",
        recipe(lambda t: t[: t.index("stages:")] + "stages: 3\n"),
        RUN,
        2,
        "invalid value for 'stages' in " + RECIPE_FILE,
    ),
    Case(
        "stage-kind-unknown",
        recipe(lambda t: t.replace("kind: pretrain", "kind: pretrian")),
        RUN,
        2,
        "unknown stage kind 'pretrian'",
    ),
    Case(
        "stage-consumes-later",
        recipe(lambda t: t.replace("    kind: tokenizer\n", "    kind: tokenizer\n    consumes: [pretrain]\n", 1)),
        RUN,
        2,
        "consumes 'pretrain', which is not an earlier stage (it runs later)",
    ),
    Case(
        "stage-names-twice",
        recipe(lambda t: t.replace("name: pretrain", "name: tokenizer")),
        RUN,
        2,
        "stage name 'tokenizer' is used twice",
    ),
    Case(
        "stage-model-typo",
        recipe(lambda t: t.replace("num_codes: 8", "num_code: 8")),
        RUN,
        2,
        "unknown key 'stages[0].model.occworld_vqvae.num_code' in " + RECIPE_FILE + "; did you mean 'num_codes'?",
    ),
    Case(
        "stage-data-root",
        recipe(lambda t: t.replace("    trainer: {max_steps: 3}", "    trainer: {max_steps: 3}\n    data: {root: x}")),
        RUN,
        2,
        "stages[0].data.root in " + RECIPE_FILE + ": a stage sets only batch_size, num_workers, shuffle_buffer",
    ),
    Case(
        "recipe-alias-bomb-in-plugins",
        recipe(
            lambda t: (
                t
                + "x: &a [m, m, m, m, m, m, m, m, m, m]\n"
                + "y: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
                + "z: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b, *b]\n"
                + "plugins: [*c, *c, *c, *c, *c, *c, *c, *c, *c, *c]\n"
            )
        ),
        ["validate", "{tmp}/r.yaml"],
        2,
        "{tmp}/r.yaml: its YAML aliases expand to over 10000 values (an alias bomb?)",
    ),
    Case(
        "override-alias-refers-to-itself",
        recipe(),
        ["validate", "{tmp}/r.yaml", "plugins=&x [*x]"],
        2,
        "override 'plugins=&x [*x]': a YAML alias refers to the value that holds it",
    ),
    Case(
        "plugin-missing",
        recipe(lambda t: t + "plugins: [no_such_plugin_module]\n"),
        RUN,
        2,
        "plugin 'no_such_plugin_module'",
    ),
    Case(
        "override-typo",
        recipe(),
        [*RUN, "trainer.max_step=3"],
        2,
        "unknown key 'trainer.max_step' in override 'trainer.max_step=3'; did you mean 'max_steps'?",
    ),
    Case(
        "override-no-equals",
        recipe(),
        [*RUN, "trainer.max_steps"],
        2,
        "override 'trainer.max_steps' must look like key=value",
    ),
    Case("override-wrong-type", recipe(), [*RUN, "trainer.max_steps=many"], 2, "invalid value for 'trainer.max_steps'"),
    Case(
        "override-unknown-stage-name",
        recipe(),
        [*RUN, "stages.tokeniser.optim.lr=1"],
        2,
        "has no stage 'tokeniser' (stages: tokenizer, pretrain); address one as stages.<name>.<key>=",
    ),
    Case("override-stage-index-out-of-range", recipe(), [*RUN, "stages.7.optim.lr=1"], 2, "has no stage '7'"),
    Case(
        "override-stage-key-typo",
        recipe(),
        [*RUN, "stages.tokenizer.optim.lrr=1"],
        2,
        "unknown key 'stages[0].optim.lrr'",
    ),
    Case(
        "max-steps-zero",
        recipe(lambda t: t.replace("    trainer: {max_steps: 3}\n", "")),
        [*RUN, "trainer.max_steps=0"],
        2,
        "trainer.max_steps is 0 in " + RECIPE_FILE + ": a stage trains for a positive number of optimizer steps",
    ),
    Case(
        "max-steps-minus-one",
        recipe(),
        [*RUN, "stages.tokenizer.trainer.max_steps=-1"],
        2,
        "stages.tokenizer.trainer.max_steps is -1",
    ),
    Case(
        "only-unknown-stage",
        recipe(),
        [*RUN, "--only", "planner"],
        2,
        "--only names stage 'planner', but " + RECIPE_FILE + " has stages tokenizer, pretrain",
    ),
    Case("restart-unknown-stage", recipe(), [*RUN, "--restart", "planner"], 2, "--restart names stage 'planner'"),
    Case(
        "run-dir-locked",
        locked_run_dir,
        RUN,
        2,
        "{tmp}/run2 is in use by pid 4242 on elsewhere; wait for it to finish, stop it, or choose another --run-dir",
    ),
    Case(
        "done-stage-config-changed",
        manifest(DONE_OTHER_CONFIG),
        RUN,
        2,
        "stage 'tokenizer' is done but its config changed",
    ),
    Case(
        "cut-off-under-other-config",
        cut_off_under_other_config,
        RUN,
        2,
        "stage 'tokenizer' was cut off under a different config",
    ),
    Case(
        "manifest-unreadable",
        both(manifest({}), write_text("run2/manifest.json", "{")),
        RUN,
        2,
        "{tmp}/run2/manifest.json: unreadable manifest",
    ),
    Case(
        "vision-without-cameras",
        recipe(VISION_ONLY),
        RUN,
        2,
        "stage 'vision' reads camera images, and {tmp}/ds has none (no camera_sensor records or no imgs/)",
    ),
    Case(
        "vision-synth-without-cameras",
        recipe(VISION_ONLY),
        [*RUN, "data.root={tmp}/none", "data.synth.camera_height=0"],
        2,
        "stage 'vision' reads camera images; data.synth.camera_height=0 synthesizes none",
    ),
    Case("eval-not-a-stage-dir", nothing, ["eval", "{tmp}/nowhere"], 2, "{tmp}/nowhere"),
    # ------------------------------------------------------------------ round two: wrong data, silently
    Case(
        "shards-stale-after-labels-edit",
        shards_then(save_labels(semantics=np.full(GRID_SHAPE, 3, np.uint8))),
        STALE,
        2,
        "{tmp}/s2: its shards were made before {tmp}/ds changed",
    ),
    Case(
        "shards-stale-after-sidecar-edit",
        shards_then(edit_frame(0, lambda f: f.update(caption="a different caption"))),
        STALE,
        2,
        "{tmp}/s2: its shards were made before {tmp}/ds changed",
    ),
    Case(
        "shards-one-camera-image-missing",
        with_cameras(missing=FIRST_IMG),
        SHARDS_FRAMES,
        2,
        "{tmp}/ds/" + FIRST_IMG + ": cannot read it",
    ),
    Case(
        "shards-corrupt-png",
        with_cameras(corrupt=f"imgs/CAM_BACK/{T0[3]}.png"),
        SHARDS_FRAMES,
        2,
        "{tmp}/ds/imgs/CAM_BACK/" + T0[3] + ".png: not a readable image",
    ),
    Case(
        "eval-interrupted-stage",
        stage_status("interrupted"),
        EVAL,
        2,
        "{tmp}/run/pretrain: stage 'pretrain' is interrupted, not done",
    ),
    Case(
        "eval-never-run-stage",
        lambda tmp: (tmp / "run" / "manifest.json").unlink(),
        EVAL,
        2,
        "stage 'pretrain' is never run, not done",
    ),
    Case(
        "data-root-empty",
        both(recipe(), lambda tmp: (tmp / "empty").mkdir()),
        [*RUN, "data.root={tmp}/empty"],
        2,
        "data.root {tmp}/empty is empty",
    ),
    Case(
        "data-root-gts-without-annotations",
        both(recipe(), lambda tmp: [(tmp / "ds" / f).unlink() for f in ("annotations.json", "occtrain/dataset.json")]),
        RUN,
        2,
        "data.root {tmp}/ds holds no annotations.json",
    ),
    Case(
        "data-root-foreign-record-without-annotations",
        both(recipe(), lambda tmp: (tmp / "ds" / "annotations.json").unlink()),
        RUN,
        2,
        "{tmp}/ds/occtrain/dataset.json: records a dataset occtrain did not synthesize, and {tmp}/ds has no "
        "annotations.json",
    ),
    # ------------------------------------------------------------------ round two: paths outside their roots
    Case(
        "ann-gt-path-escapes",
        edit_sample(0, 1, lambda s: s.update(gt_path="../../../../../etc/passwd")),
        SHARDS_FRAMES,
        2,
        f"{ANN}: scene_infos.scene-0000.{T0[1]}.gt_path '../../../../../etc/passwd' points outside the dataset root",
    ),
    Case(
        "ann-gt-path-absolute",
        edit_sample(0, 1, lambda s: s.update(gt_path="/etc/passwd")),
        SHARDS_FRAMES,
        2,
        "gt_path '/etc/passwd' points outside",
    ),
    Case(
        "check-gt-path-valid-file-outside",
        lambda tmp: edit_json(
            tmp / "ds" / "annotations.json",
            lambda a: a["scene_infos"][SCENES[0]][T0[2]].update(gt_path=str(labels_file(tmp, 0, 2).resolve())),
        ),
        CHECK,
        1,
        f"scene_infos.scene-0000.{T0[2]}.gt_path '",
    ),
    Case(
        "show-gt-path-outside",
        edit_sample(1, 0, lambda s: s.update(gt_path="/etc/hostname")),
        ["data", "show", DS, "--out", "{tmp}/b.png"],
        2,
        "gt_path '/etc/hostname' points outside the dataset root",
    ),
    Case(
        "ann-img-path-escapes",
        edit_sample(
            0,
            0,
            lambda s: s.update(
                camera_sensor={"CAM_FRONT": {**camera([[1.0, 0, 0]] * 3)["CAM_FRONT_tok"], "img_path": "../x.png"}}
            ),
        ),
        SHARDS_FRAMES,
        2,
        "camera_sensor.CAM_FRONT.img_path '../x.png' points outside the dataset root",
    ),
    Case(
        "recipe-name-escapes",
        recipe(lambda t: t.replace("name: tiny", "name: ../../escape")),
        ["run", "{tmp}/r.yaml"],
        2,
        "name '../../escape' in " + RECIPE_FILE + ": a run is a folder name inside runs_root",
    ),
    # ------------------------------------------------------------------ round two: exit 0 with nothing done
    Case("eval-split-test", nothing, [*EVAL, "--split", "test"], 2, "--split test: a dataset's splits are train, val"),
    Case(
        "eval-tasks-qa-without-qa",
        world_without_qa,
        ["eval", "{tmp}/run/pretrain", "--tasks", "qa", "--data", "{tmp}/noqa"],
        2,
        "--tasks qa: the task needs nuscenes_qa/NuScenes_<split>_questions.json, which this dataset lacks ({tmp}/noqa)",
    ),
    Case(
        "eval-samples-zero",
        nothing,
        [*EVAL, "--samples", "0"],
        2,
        "--samples 0: score a positive number of items per task, or -1",
    ),
    Case("eval-samples-minus-five", nothing, [*EVAL, "--samples", "-5"], 2, "--samples -5"),
    Case(
        "show-zero-frames",
        nothing,
        ["data", "show", DS, "--frames", "0", "--out", "{tmp}/b.png"],
        2,
        "--frames 0: draw at least 1 frame",
    ),
    Case(
        "show-out-exists",
        write_text("b.png", "mine"),
        ["data", "show", DS, "--out", "{tmp}/b.png"],
        2,
        "{tmp}/b.png: exists; pass --overwrite",
    ),
    Case(
        "shards-no-clip-fits",
        nothing,
        ["data", "shards", DS, "--out", "{tmp}/out", "--kinds", "clips"],
        2,
        "{tmp}/ds: its longest train scene has 8 frames and a clip spans history 4 + 1 + future 6 = 11",
    ),
    Case(
        "qa-answer-integer",
        qa_answers(["yes", "2", 1, "car"]),
        QA,
        2,
        "{tmp}/a.json: [2] is the integer 1, expected a string",
    ),
    # ------------------------------------------------------------------ round two: late or raw failures
    Case(
        "pretrain-family-unknown",
        recipe(lambda t: t.replace("family: occllama", "family: occlama")),
        RUN,
        2,
        "model.family: unknown model family 'occlama'",
    ),
    Case(
        "instruct-family-other",
        recipe(lambda t: t + "  - {name: instruct, kind: instruct, consumes: [pretrain], model: {family: occllm}}\n"),
        RUN,
        2,
        "stages[2].model.family in "
        + RECIPE_FILE
        + " is 'occllm', but the stage tunes the consumed 'occllama' world model",
    ),
    Case(
        "batch-size-zero",
        recipe(),
        [*RUN, "data.batch_size=0"],
        2,
        "data.batch_size is 0 in " + RECIPE_FILE + ": it must be at least 1",
    ),
    Case(
        "stage-batch-size-zero",
        recipe(),
        [*RUN, "stages.pretrain.data.batch_size=0"],
        2,
        "stages.pretrain.data.batch_size is 0",
    ),
    Case(
        "lr-negative",
        recipe(),
        [*RUN, "stages.tokenizer.optim.lr=-1"],
        2,
        "stages.tokenizer.optim.lr is -1.0 in " + RECIPE_FILE + ": it must be at least 0",
    ),
    Case(
        "lr-nan",
        recipe(),
        [*RUN, "stages.tokenizer.optim.lr=nan"],
        2,
        "stages.tokenizer.optim.lr is nan in " + RECIPE_FILE + ": it must be a finite number",
    ),
    Case(
        "val-check-interval-zero",
        recipe(),
        [*RUN, "trainer.val_check_interval=0"],
        2,
        "trainer.val_check_interval is 0 in " + RECIPE_FILE,
    ),
    Case(
        "schedule-unknown",
        recipe(),
        [*RUN, "stages.pretrain.optim.schedule=linear"],
        2,
        "stages.pretrain.optim.schedule is linear",
    ),
    Case(
        "checkpoint-pickled",
        pickled_checkpoint,
        RUN,
        2,
        "{tmp}/run2/tokenizer/checkpoints/last.ckpt: holds pickled object e2e.test_bad_inputs.Evil",
    ),
    # ------------------------------------------------------------------ trainers this machine cannot run
    Case(
        "gpu-config-without-gpu",
        recipe(),
        [*RUN, f"trainer={REPO / 'configs/trainer/gpu.yaml'}"],
        2,
        "trainer.accelerator is gpu, but torch "
        + torch.__version__
        + " sees no GPU here; train on the CPU with configs/trainer/cpu.yaml",
    ),
    Case(
        "cpu-devices-beyond-cores",
        recipe(),
        [*RUN, "trainer.devices=100000"],
        2,
        "trainer.devices is 100000 CPU processes, but this machine has",
    ),
    # Lightning's own FSDP strategies need a GPU (occtrain's `fsdp` is FSDP2 and runs on CPU processes).
    Case(
        "fsdp-offload-on-cpu",
        recipe(),
        [*RUN, "stages.pretrain.trainer.strategy=fsdp_cpu_offload"],
        2,
        "stages.pretrain.trainer: accelerator=cpu devices=1 strategy=fsdp_cpu_offload precision=32-true cannot run "
        "here (The strategy `fsdp` requires a GPU",
    ),
    Case(
        "fsdp-for-a-stage-that-does-not-shard",
        recipe(),
        [*RUN, "trainer.strategy=fsdp"],
        2,
        "trainer.strategy is fsdp, but a tokenizer stage does not shard (the pretrain and instruct stages do); "
        "train 'tokenizer' with stages.tokenizer.trainer.strategy=ddp",
    ),
    Case(
        "precision-unknown",
        recipe(),
        [*RUN, "trainer.precision=bf17"],
        2,
        "trainer: accelerator=cpu devices=1 strategy=auto precision=bf17 cannot run here (Precision 'bf17' is invalid",
    ),
    Case(
        "validate-batch-size-zero",
        recipe(),
        ["validate", "{tmp}/r.yaml", "data.batch_size=0"],
        2,
        "data.batch_size is 0",
    ),
    Case(
        "dry-run-family-unknown",
        recipe(lambda t: t.replace("family: occllama", "family: occlama")),
        [*RUN, "--dry-run"],
        2,
        "unknown model family 'occlama'",
    ),
    Case(
        "validate-stale-shards",
        both(
            recipe(),
            shards_then(
                save_labels(semantics=np.full(GRID_SHAPE, 3, np.uint8)), kinds=["frames", "clips"], history=1, future=1
            ),
        ),
        ["validate", "{tmp}/r.yaml", "data.shards={tmp}/s2"],
        2,
        "{tmp}/s2: its shards were made before {tmp}/ds changed",
    ),
    # ------------------------------------------------------------------ names and deletions
    Case(
        "stage-name-escapes",
        stage_named("../../victim"),
        ESCAPING_RUN,
        2,
        "stages[0].name '../../victim' in " + RECIPE_FILE + ": a stage is a folder name inside the run",
    ),
    Case(
        "validate-stage-name-escapes",
        stage_named("../../victim"),
        ["validate", "{tmp}/r.yaml", "--run-dir", "{tmp}/a/run2"],
        2,
        "stages[0].name '../../victim'",
    ),
    Case(
        "restart-an-escaping-stage",
        stage_named("../../victim"),
        [*ESCAPING_RUN, "--restart", "../../victim"],
        2,
        "stages[0].name '../../victim'",
    ),
    Case("stage-name-absolute", stage_named("{tmp}/victim"), ESCAPING_RUN, 2, "stages[0].name '{tmp}/victim'"),
    Case("stage-name-empty", stage_named(""), ESCAPING_RUN, 2, "stages[0].name '' in"),
    Case("stage-name-hidden", stage_named(".."), ESCAPING_RUN, 2, "stages[0].name '..' in"),
    Case(
        "manifest-stage-name-escapes",
        manifest_naming("../../victim"),
        RUN,
        2,
        "{tmp}/run2/manifest.json: stage '../../victim' is not a folder name inside the run",
    ),
    # ------------------------------------------------------------------ restart and validate
    Case(
        "restart-with-an-architecture-run-refuses",
        finished_run,
        [*RUN, "--restart", "tokenizer", "stages.pretrain.model.llm.num_heads=3"],
        2,
        "stages.pretrain.model.llm.num_heads is 3, which does not divide hidden_size 128",
    ),
    Case(
        "validate-refuses-the-architecture-run-refuses",
        finished_run,
        [
            "validate",
            "{tmp}/r.yaml",
            "--run-dir",
            "{tmp}/run2",
            "--restart",
            "pretrain",
            "stages.pretrain.model.llm.num_heads=3",
        ],
        2,
        "stages.pretrain.model.llm.num_heads is 3, which does not divide",
    ),
    Case(
        "restart-with-a-negative-hidden-size",
        finished_run,
        [*RUN, "--restart", "pretrain", "stages.pretrain.model.llm.hidden_size=-128"],
        2,
        "stages.pretrain.model.llm.hidden_size is -128; it sizes the model's tensors",
    ),
    Case(
        "restart-with-adapters-and-lora",
        finished_run,
        [
            *RUN,
            "--restart",
            "pretrain",
            "stages.pretrain.model.use_lora=true",
            "stages.pretrain.model.use_adapters=true",
        ],
        2,
        "stages.pretrain.model: use_lora and use_adapters are both on",
    ),
    Case(
        "validate-refuses-a-tokenizer-its-build-refuses",
        recipe(),
        ["validate", "{tmp}/r.yaml", "stages.tokenizer.model.occworld_vqvae.strides=[3,5]"],
        2,
        "stages.tokenizer.model.occworld_vqvae",
    ),
    Case(
        "validate-refuses-a-student-its-build-refuses",
        recipe(
            lambda t: (
                t
                + "  - {name: instruct, kind: instruct, consumes: [pretrain]}\n"
                + "  - {name: distill, kind: distill, consumes: [instruct]}\n"
            )
        ),
        ["validate", "{tmp}/r.yaml", "stages.distill.model.student.num_heads=5"],
        2,
        "stages.distill.model.student.num_heads is 5, which does not divide hidden_size 96",
    ),
    Case(
        "validate-refuses-dagger-episodes-shorter-than-the-history",
        recipe(with_dagger),
        ["validate", "{tmp}/r.yaml", "stages.closed_loop.model.seconds=1"],
        2,
        "stages.closed_loop.model.seconds 1: the expert drives the first 1 s (the 2 frames of history the stage's "
        "prompts read), so the stage would never drive; give stages.closed_loop.model.seconds 1.5 or more",
    ),
    Case(
        "validate-refuses-a-negative-route-seed",
        recipe(with_dagger),
        ["validate", "{tmp}/r.yaml", "stages.closed_loop.model.route_seed=-1"],
        2,
        "stages.closed_loop.model.route_seed is -1: a seed is an integer from 0 to 4294967295",
    ),
    Case(
        "validate-refuses-more-rollout-workers-than-cores",
        recipe(with_dagger),
        ["validate", "{tmp}/r.yaml", "stages.closed_loop.model.workers=1000"],
        2,
        "stages.closed_loop.model.workers: 1000 is more than the ",
    ),
    Case(
        "validate-refuses-a-negative-generation-length",
        recipe(with_dagger),
        ["validate", "{tmp}/r.yaml", "stages.closed_loop.model.max_new_text_tokens=-5"],
        2,
        "stages.closed_loop.model.max_new_text_tokens is -5 in {tmp}/r.yaml: it must be at least 0",
    ),
    Case(
        "validate-refuses-a-world-model-generating-nothing",
        recipe(),
        ["validate", "{tmp}/r.yaml", "stages.pretrain.model.max_new_text_tokens=0"],
        2,
        "stages.pretrain.model.max_new_text_tokens: 0; a validation generates at least 1 token of text per answer",
    ),
    Case(
        "validate-refuses-scenes-longer-than-the-world-holds",
        recipe(),
        ["validate", "{tmp}/r.yaml", "data.root={tmp}/new", "data.synth.frames_per_scene=100000"],
        2,
        "data.synth.frames_per_scene=100000",
    ),
    Case(
        "synth-refuses-scenes-longer-than-the-world-holds",
        nothing,
        ["data", "synth", "--out", "{tmp}/w", "--scenes", "1", "--val-scenes", "1", "--frames", "100000"],
        2,
        "frames_per_scene=100000",
    ),
    Case(
        "stage-consumes-itself",
        recipe(lambda t: t.replace("consumes: [tokenizer]", "consumes: [pretrain]")),
        RUN,
        2,
        "stages[1] ('pretrain') in " + RECIPE_FILE + " consumes itself",
    ),
    Case(
        "precision-16-mixed-on-cpu",
        recipe(),
        [*RUN, "trainer.precision=16-mixed"],
        2,
        "trainer.precision is 16-mixed, but float16 mixed precision needs a GPU; on the CPU use bf16-mixed",
    ),
    # ------------------------------------------------------------------ eval and outputs
    Case(
        "eval-save-predictions-onto-a-file",
        write_text("p.json", "mine"),
        [*EVAL, "--save-predictions", "{tmp}/p.json"],
        2,
        "{tmp}/p.json: is a file; --save-predictions takes a directory",
    ),
    Case(
        "eval-save-predictions-read-only",
        nothing,
        [*EVAL, "--save-predictions", "{tmp}/preds"],
        2,
        "cannot write {tmp}/preds: the file system is read-only; choose another --save-predictions",
        patch=read_only_disk,
    ),
    Case(
        "eval-save-predictions-of-a-tokenizer",
        tokenizer_done,
        ["eval", "{tmp}/run/tokenizer", "--save-predictions", "{tmp}/preds"],
        2,
        "--save-predictions {tmp}/preds: a tokenizer stage's eval has metrics only, no predictions to save",
    ),
    Case(
        "eval-blank-cameras-of-a-stage-without-cameras",
        tokenizer_done,
        ["eval", "{tmp}/run/tokenizer", "--blank-cameras"],
        2,
        "--blank-cameras: stage 'tokenizer' reads no camera images (nor does a stage it consumes); leave the flag out",
    ),
    Case(
        "eval-read-only-run",
        nothing,
        EVAL,
        2,
        (
            "cannot write {tmp}/run/pretrain/eval/val/metrics.json: the file system is read-only; eval writes its "
            "metrics into {tmp}/run/pretrain",
            "copy the run to a writable place",
        ),
        patch=read_only_disk,
    ),
    Case(
        "eval-blank-cameras-read-only-run",
        nothing,
        [*EVAL, "--blank-cameras"],
        2,
        (
            "cannot write {tmp}/run/pretrain/eval/val+blank_cameras/metrics.json: the file system is read-only; eval "
            "writes its metrics into {tmp}/run/pretrain",
        ),
        patch=read_only_disk,
    ),
    Case(
        "score-out-read-only",
        planning(lambda p, g: None),
        [*PLANNING, "--out", "{tmp}/o/r.json"],
        2,
        "cannot write {tmp}/o/r.json: the file system is read-only; choose another --out",
        patch=read_only_disk,
    ),
    Case(
        "dashboard-out-read-only",
        nothing,
        ["dashboard", "{tmp}/run", "--out", "{tmp}/d.html"],
        2,
        "cannot write {tmp}/d.html: the file system is read-only; choose another --out",
        patch=read_only_disk,
    ),
    Case(
        "dashboard-out-is-a-directory",
        nothing,
        ["dashboard", "{tmp}/run", "--out", "{tmp}/ds"],
        2,
        "{tmp}/ds: is a directory; --out takes a file name",
    ),
    # ------------------------------------------------------------------ plan-memory
    Case(
        "plan-memory-hidden-size-negative",
        recipe(),
        [*PLAN, "stages.pretrain.model.llm.hidden_size=-128"],
        2,
        "stages.pretrain.model.llm.hidden_size is -128; it sizes the model's tensors, so it must be a positive integer",
    ),
    Case(
        "plan-memory-heads-do-not-divide-hidden",
        recipe(),
        [*PLAN, "stages.pretrain.model.llm.num_heads=3"],
        2,
        "stages.pretrain.model.llm.num_heads is 3, which does not divide hidden_size 128; set num_heads to a divisor "
        "of 128 (e.g. 4)",
    ),
    Case(
        "plan-memory-layers-zero",
        recipe(),
        [*PLAN, "stages.pretrain.model.llm.num_layers=0"],
        2,
        "stages.pretrain.model.llm.num_layers is 0;",
    ),
    Case(
        "plan-memory-config-json-hidden-negative",
        llm_dir(hidden_size=-128),
        [*PLAN, f"stages.pretrain.model.llm.path={LLM_DIR}"],
        2,
        f"{LLM_DIR}/config.json: hidden_size is -128; it sizes the model's tensors, so it must be a positive integer",
    ),
    Case(
        "plan-memory-config-json-kv-heads-do-not-divide",
        llm_dir(num_key_value_heads=5),
        [*PLAN, f"stages.pretrain.model.llm.path={LLM_DIR}"],
        2,
        f"{LLM_DIR}/config.json: num_key_value_heads is 5, which does not divide num_attention_heads 32",
    ),
    Case(
        "plan-memory-config-json-vocab-string",
        llm_dir(vocab_size="128256"),
        [*PLAN, f"stages.pretrain.model.llm.path={LLM_DIR}"],
        2,
        f"{LLM_DIR}/config.json: vocab_size is '128256';",
    ),
    Case(
        "plan-memory-size-override-beside-path",
        nothing,
        ["plan-memory", SCALE_LLAMA, "stages.pretrain.model.llm.hidden_size=-128"],
        2,
        "stages.pretrain.model.llm.hidden_size: ignored, since stages.pretrain.model.llm.path is set "
        "(configs/llm/llama-3.1-8b) and its config.json decides the model",
    ),
    Case("plan-memory-gpus-zero", recipe(), [*PLAN, "--gpus", "0"], 2, "--gpus 0: plan at least 1 GPU"),
    Case(
        "plan-memory-seq-len-huge",
        recipe(),
        [*PLAN, "--seq-len", str(10**12)],
        2,
        f"--seq-len {10**12}: tokens per training sequence must be in 1..4194304 (2**22)",
    ),
    Case(
        "plan-memory-gpu-memory-negative",
        recipe(),
        [*PLAN, "--gpu-memory", "-5"],
        2,
        "--gpu-memory -5: a GPU's memory in GiB must be above 0 and at most 10000",
    ),
    Case(
        "plan-memory-gpu-memory-absurd",
        recipe(),
        [*PLAN, "--gpu-memory", "1e6"],
        2,
        "--gpu-memory 1e+06: a GPU's memory in GiB must be above 0 and at most 10000",
    ),
    # ------------------------------------------------------------------ plugins
    Case(
        "plugin-raises-on-import",
        with_plugin("plugins.broken_plugin"),
        RUN,
        2,
        "plugin 'plugins.broken_plugin' in " + RECIPE_FILE + " " + PLUGIN_RAISES,
    ),
    Case(
        "validate-plugin-raises-on-import",
        with_plugin("plugins.broken_plugin"),
        ["validate", RECIPE_FILE],
        2,
        "plugin 'plugins.broken_plugin' in " + RECIPE_FILE + " " + PLUGIN_RAISES,
    ),
    Case(
        "eval-pipeline-plugin-raises-on-import",
        with_plugin("plugins.broken_plugin", "run/pipeline.yaml"),
        EVAL,
        2,
        "plugin 'plugins.broken_plugin' in {tmp}/run/pipeline.yaml " + PLUGIN_RAISES,
    ),
    Case(
        "plugin-family-name-shipped",
        with_plugin("plugins.clashing_family"),
        RUN,
        2,
        (
            "plugin 'plugins.clashing_family' in "
            + RECIPE_FILE
            + ": family 'occllama' of plugin plugins.clashing_family is already registered by "
            "occtrain.families.occllama (shipped with occtrain); register it with override=True to replace it"
        ),
    ),
    Case(
        "plugin-kind-name-built-in",
        with_plugin("plugins.clashing_kind"),
        RUN,
        2,
        "stage kind 'pretrain' of plugin plugins.clashing_kind is already registered by "
        "occtrain.stages.pretrain_instruct (shipped with occtrain)",
    ),
    # ------------------------------------------------------------------ exports, load and trackers
    Case(
        "export-config-unknown-key",
        export_file("config.json", b'{"stage_kind": "world_model", "familly": "occllama"}'),
        EVAL,
        2,
        EXPORT + "config.json: unknown key 'familly' (rename or remove it); did you mean 'family'?",
    ),
    Case(
        "export-config-unknown-key-unlike-any",
        export_file("config.json", b'{"stage_kind": "world_model", "notes": "mine"}'),
        EVAL,
        2,
        EXPORT
        + "config.json: unknown key 'notes' (rename or remove it); valid keys: family, max_new_text_tokens, stage, "
        "stage_kind, tasks, vocab, world",
    ),
    # ------------------------------------------------------------------ eval and restart, drive
    Case(
        "eval-while-a-restart-replaces-the-stage",
        holding("pretrain", shared=False),
        EVAL,
        2,
        "{tmp}/run/pretrain: the stage is being retrained (`occtrain run --restart`) in another process",
    ),
    Case(
        "restart-while-an-eval-scores-the-stage",
        both(recipe(), holding("pretrain", shared=True)),
        ["run", "{tmp}/r.yaml", "--run-dir", "{tmp}/run", "--restart", "pretrain"],
        2,
        "{tmp}/run/pretrain is being scored by `occtrain eval` or `occtrain drive` in another process; wait for it",
    ),
    Case(
        "restart-of-an-earlier-stage-while-an-eval-scores-a-later-one",
        both(recipe(), holding("pretrain", shared=True)),
        ["validate", "{tmp}/r.yaml", "--run-dir", "{tmp}/run", "--restart", "tokenizer"],
        2,
        "{tmp}/run/pretrain is being scored by `occtrain eval` or `occtrain drive` in another process; wait for it "
        "to finish (or stop it), then --restart tokenizer",
    ),
    Case(
        "validate-restart-while-an-eval-scores-the-stage",
        both(recipe(), holding("pretrain", shared=True)),
        ["validate", "{tmp}/r.yaml", "--run-dir", "{tmp}/run", "--restart", "pretrain"],
        2,
        "{tmp}/run/pretrain is being scored by `occtrain eval` or `occtrain drive` in another process",
    ),
    Case(
        "report-split-climbs-out-of-eval",
        nothing,
        ["report", "{tmp}/run", "--split", ".."],
        2,
        "--split ..: a split (train, val), or the folder `occtrain eval --data` wrote under a stage's eval/",
    ),
    Case(
        "report-split-not-a-split",
        nothing,
        ["report", "{tmp}/run", "--split", "world-abc/../../x/val"],
        2,
        "--split world-abc/../../x/val: a split (train, val)",
    ),
    Case(
        "report-out-is-a-directory",
        nothing,
        ["report", "{tmp}/run", "--out", "{tmp}/ds"],
        2,
        "{tmp}/ds: is a directory; --out takes a file name",
    ),
    Case(
        "drive-seed-negative",
        nothing,
        [*DRIVE, "--seed", "-1"],
        2,
        "--seed -1: a route seed is a whole number from 0 to 4294967295",
    ),
    Case(
        "drive-scenes-beyond-the-bound",
        nothing,
        [*DRIVE, "--scenes", "1000000"],
        2,
        "--scenes 1000000: drive 1 to 10000 routes at a time",
    ),
    Case(
        "drive-workers-beyond-the-cores",
        nothing,
        [*DRIVE, "--workers", "100000"],
        2,
        "--workers 100000: give 1 to ",
    ),
    Case(
        "drive-too-short-for-the-stage-to-plan",
        export_file("config.json", b'{"stage_kind": "world_model", "tasks": {"context_frames": 4}}'),
        [*DRIVE, "--seconds", "2"],
        2,
        "--seconds 2: the expert drives the first 2 s (the 4 frames of history the stage's prompts read), so the "
        "stage would never drive; give --seconds 2.5 or more",
    ),
    Case(
        "drive-read-only-run",
        nothing,
        [*DRIVE, "--seconds", "3"],
        2,
        "the file system is read-only; drive writes its results into {tmp}/run/pretrain; make it writable, or copy",
        patch=read_only_disk,
    ),
    # ------------------------------------------------------------------ data
    Case("stats-frames-zero", nothing, ["data", "stats", DS, "--frames", "0"], 2, "--frames 0: count at least 1 frame"),
    Case(
        "stats-json-is-a-directory",
        nothing,
        ["data", "stats", DS, "--json", "{tmp}/ds"],
        2,
        "{tmp}/ds: is a directory; --json takes a file name",
    ),
    Case(
        "stats-chart-read-only",
        nothing,
        ["data", "stats", DS, "--chart", "{tmp}/c.png"],
        2,
        "cannot write {tmp}/c.png: the file system is read-only; choose another --chart",
        patch=read_only_disk,
    ),
    Case("stats-not-a-dataset", nothing, ["data", "stats", "{tmp}/nowhere"], 2, "{tmp}/nowhere"),
    Case(
        "validate-a-clip-stage-where-no-clip-fits",
        recipe(),
        ["validate", "{tmp}/r.yaml", "data.history=4", "data.future=6"],
        2,
        "stage 'pretrain' reads clips",
    ),
    Case(
        "shards-plain-copy-validate",
        both(recipe(), shards_then(plain_copy, kinds=["frames", "clips"], history=1, future=1)),
        ["validate", "{tmp}/r.yaml", "data.root={tmp}/ds2", "data.shards={tmp}/s2"],
        2,
        (
            "{tmp}/s2: its shards were made from {tmp}/ds, and {tmp}/ds2 is not that dataset as it was then",
            "delete {tmp}/s2",
            REBUILD_COPY,
        ),
    ),
    Case(
        "shards-plain-copy-run",
        both(recipe(), shards_then(plain_copy, kinds=["frames", "clips"], history=1, future=1)),
        [*RUN, "data.root={tmp}/ds2", "data.shards={tmp}/s2"],
        2,
        ("{tmp}/s2: its shards were made from {tmp}/ds", REBUILD_COPY),
    ),
    Case(
        "shards-plain-copy-data-shards",
        shards_then(plain_copy),
        ["data", "shards", "{tmp}/ds2", "--out", "{tmp}/s2", "--kinds", "frames", "--samples-per-shard", "4"],
        2,
        (
            "{tmp}/s2: its shards were made from {tmp}/ds",
            "`occtrain data shards {tmp}/ds2 --out {tmp}/s2 --samples-per-shard 4 --kinds frames --rebuild`",
        ),
    ),
    Case(
        "shards-other-layout-names-the-rebuild",
        shards_then(nothing),
        [*STALE[:-1], "5"],
        2,
        (
            "{tmp}/s2: already holds shards of a different dataset or layout (samples_per_shard 4 there, 5 here)",
            "`occtrain data shards {tmp}/ds --out {tmp}/s2 --samples-per-shard 5 --kinds frames --rebuild`",
        ),
    ),
    Case(
        "shards-rebuild-out-is-a-dataset",
        nothing,
        ["data", "shards", DS, "--out", DS, "--rebuild"],
        2,
        "{tmp}/ds: holds annotations.json, which is not a shard file; --rebuild replaces the whole directory",
    ),
    Case(
        "shards-out-is-a-file",
        write_text("f", "mine"),
        ["data", "shards", DS, "--out", "{tmp}/f"],
        2,
        "{tmp}/f: is a file; --out takes a directory",
    ),
    Case(
        "shards-out-under-a-file",
        write_text("f", "mine"),
        ["data", "shards", DS, "--out", "{tmp}/f/out"],
        2,
        "cannot write {tmp}/f/out: {tmp}/f is a file",
    ),
    Case("shards-camera-folder-deleted", released_cameras(drop="CAM_BACK"), SHARDS_FRAMES, 2, NO_BACK),
    Case("shards-camera-folder-deleted-readme-form", without_folder("imgs/CAM_BACK"), SHARDS_FRAMES, 2, NO_BACK),
    Case(
        "validate-camera-folder-deleted",
        both(recipe(), released_cameras(drop="CAM_BACK")),
        ["validate", "{tmp}/r.yaml"],
        2,
        NO_BACK,
    ),
    Case(
        "run-vision-camera-folder-deleted",
        both(recipe(VISION_ONLY), released_cameras(drop="CAM_BACK")),
        RUN,
        2,
        NO_BACK,
    ),
    Case(
        "shards-camera-image-missing-released-form",
        released_cameras(drop=FIRST_IMG.removeprefix("imgs/")),
        SHARDS_FRAMES,
        2,
        "{tmp}/ds/" + FIRST_IMG + ": cannot read it",
    ),
    # ------------------------------------------------------------------ issue 58: round four
    Case(
        "synth-seed-negative",
        nothing,
        ["data", "synth", "--out", "{tmp}/new", "--seed", "-1"],
        2,
        "--seed is -1: a seed is an integer from 0 to 4294967295 (2**32 - 1), as numpy's random generators take",
    ),
    Case(
        "validate-synth-seed-negative",
        recipe(),
        ["validate", RECIPE_FILE, "data.root={tmp}/new", "data.synth.seed=-1"],
        2,
        "data.synth.seed is -1 in " + RECIPE_FILE + ": a seed is an integer from 0 to 4294967295 (2**32 - 1)",
    ),
    Case(
        "validate-trainer-seed-negative",
        recipe(),
        ["validate", RECIPE_FILE, "trainer.seed=-1"],
        2,
        "trainer.seed is -1 in " + RECIPE_FILE + ": a seed is an integer from 0 to 4294967295 (2**32 - 1)",
    ),
    Case(
        "run-stage-trainer-seed-too-large",
        recipe(),
        [*RUN, "stages.tokenizer.trainer.seed=4294967296"],
        2,
        "stages.tokenizer.trainer.seed is 4294967296 in " + RECIPE_FILE + ": a seed is an integer from 0 to",
    ),
    Case(
        "validate-data-seed-negative",
        recipe(),
        ["validate", RECIPE_FILE, "data.seed=-1"],
        2,
        "data.seed is -1 in " + RECIPE_FILE + ": a seed is an integer from 0 to 4294967295 (2**32 - 1)",
    ),
    Case(
        "stats-ann-nested-too-deep",
        write_text("ds/annotations.json", DEEP_JSON),
        ["data", "stats", DS],
        2,
        f"{ANN}: not valid JSON (nested deeper than Python's JSON reader goes",
    ),
    Case(
        "validate-ann-integer-of-5016-digits",
        both(recipe(), write_text("ds/annotations.json", LONG_INT_JSON)),
        ["validate", RECIPE_FILE],
        2,
        f"{ANN}: not valid JSON (an integer of 5016 digits, more than Python reads (4300))",
    ),
    Case(
        "check-ann-nested-too-deep",
        write_text("ds/annotations.json", DEEP_JSON),
        CHECK,
        1,
        f"{ANN}: not valid JSON (nested deeper than Python's JSON reader goes",
    ),
    Case(
        "check-shards-index-nested-too-deep",
        write_text("shards/index.json", DEEP_JSON),
        CHECK_SHARDS,
        1,
        "{tmp}/shards/index.json: not valid JSON (nested deeper",
    ),
    Case(
        "planning-integer-of-5016-digits",
        both(planning(lambda p, g: None), write_text("p.json", LONG_INT_JSON)),
        PLANNING,
        2,
        "{tmp}/p.json: planning predictions is not valid JSON (an integer of 5016 digits",
    ),
    Case(
        "validate-val-batch-size-zero",
        recipe(),
        ["validate", RECIPE_FILE, "stages.pretrain.model.val_batch_size=0"],
        2,
        "stages.pretrain.model.val_batch_size is 0 in " + RECIPE_FILE + ": it must be at least 1",
    ),
    Case(
        "run-distill-val-batch-size-negative",
        recipe(
            lambda t: (
                t
                + "  - {name: instruct, kind: instruct, consumes: [pretrain]}\n"
                + "  - {name: distill, kind: distill, consumes: [instruct]}\n"
            )
        ),
        [*RUN, "stages.distill.model.val_batch_size=-4"],
        2,
        "stages.distill.model.val_batch_size is -4 in " + RECIPE_FILE + ": it must be at least 1",
    ),
    Case(
        "validate-vision-prior-batches-negative",
        both(recipe(VISION_ONLY), with_cameras()),
        ["validate", RECIPE_FILE, "stages.vision.model.prior_batches=-1"],
        2,
        "stages.vision.model.prior_batches is -1 in " + RECIPE_FILE + ": it must be at least 0",
    ),
    Case(
        "validate-precision-16-true-on-cpu",
        recipe(),
        ["validate", RECIPE_FILE, "trainer.precision=16-true"],
        2,
        "trainer.precision is 16-true, but on the CPU occtrain's stages train at 32-true or bf16-mixed only",
    ),
    Case(
        "run-stage-precision-16-true-on-cpu",
        recipe(),
        [*RUN, "stages.pretrain.trainer.precision=16-true"],
        2,
        "stages.pretrain.trainer.precision is 16-true, but on the CPU occtrain's stages train at 32-true or "
        "bf16-mixed only",
    ),
    Case(
        "validate-precision-bf16-true-on-cpu",
        recipe(),
        ["validate", RECIPE_FILE, "trainer.precision=bf16-true"],
        2,
        "trainer.precision is bf16-true, but on the CPU occtrain's stages train at 32-true or bf16-mixed only",
    ),
    Case(
        "labels-header-claims-a-huge-grid",
        lambda tmp: npz_claiming(labels_file(tmp), (2000, 2000, 160)),
        SHARDS_FRAMES,
        2,
        f"{LABELS}: 'semantics' has shape (2000, 2000, 160), expected (200, 200, 16)",
    ),
    Case(
        "check-dataset-names-a-killed-rebuild",
        killed_rebuild("ds/" + KILLED_REBUILD),
        CHECK,
        1,
        (
            f"{{tmp}}/ds/{KILLED_REBUILD}: left by an `occtrain data shards --rebuild` of {{tmp}}/ds/shards that was "
            f"stopped (pid {DEAD_PID} on {HOST} is gone)",
            f"remove it with `rm -r {{tmp}}/ds/{KILLED_REBUILD}`",
        ),
    ),
    Case(
        "check-shards-names-a-killed-rebuild",
        killed_rebuild(KILLED_REBUILD),
        CHECK_SHARDS,
        1,
        f"{{tmp}}/{KILLED_REBUILD}: left by an `occtrain data shards --rebuild` of {{tmp}}/shards that was stopped",
    ),
    Case(
        "shards-one-cut-short",
        truncate("shards/frames/train-000001.tar", 512),
        ["data", "shards", DS, "--out", "{tmp}/shards", "--kinds", "frames", "--samples-per-shard", "4"],
        2,
        (
            "{tmp}/shards/frames/train-000001.tar: 512 bytes where index.json recorded ",
            "--rebuild`",
        ),
    ),
    Case(
        "shards-one-missing",
        lambda tmp: (tmp / "shards" / "frames" / "val-000000.tar").unlink(),
        ["data", "shards", DS, "--out", "{tmp}/shards", "--kinds", "frames", "--samples-per-shard", "4"],
        2,
        ("{tmp}/shards/frames/val-000000.tar: a shard index.json lists is missing", "--rebuild`"),
    ),
    Case(
        "eval-save-predictions-over-earlier-ones",
        earlier_prediction("qa_pred.json"),
        [*EVAL, "--save-predictions", "{tmp}/preds"],
        2,
        "{tmp}/preds/qa_pred.json: exists, and --save-predictions would overwrite it; choose an empty or new "
        "directory, or move the earlier predictions away",
    ),
    Case(
        "eval-save-predictions-over-earlier-forecasts",
        earlier_prediction(f"forecast/{SCENES[1]}/{T1[0]}/forecast.npz"),
        [*EVAL, "--save-predictions", "{tmp}/preds"],
        2,
        f"{{tmp}}/preds/forecast/{SCENES[1]}/{T1[0]}/forecast.npz: exists, and --save-predictions would overwrite it",
    ),
    Case(
        "eval-save-predictions-into-a-folder-of-other-files",
        earlier_prediction("notes.txt"),
        [*EVAL, "--save-predictions", "{tmp}/preds"],
        2,
        "--save-predictions {tmp}/preds: holds notes.txt; the predictions go in whole into an empty or new "
        "directory: choose one",
    ),
    Case(
        "eval-on-a-full-disk",
        nothing,
        EVAL,
        2,
        "cannot write {tmp}/run/pretrain/eval/val/metrics.json: the disk is full; eval writes its metrics into",
        patch=full_disk,
    ),
    Case(
        "plugin-is-a-path",
        with_plugin("'../../etc/passwd'"),
        RUN,
        2,
        "plugin '../../etc/passwd' in "
        + RECIPE_FILE
        + ": a plugin is a Python module name (e.g. my_package.occtrain_plugin), importable on sys.path",
    ),
    Case(
        "validate-plugin-is-a-distribution-name",
        with_plugin("occtrain-my-plugin"),
        ["validate", RECIPE_FILE],
        2,
        "plugin 'occtrain-my-plugin' in " + RECIPE_FILE + ": a plugin is a Python module name",
    ),
]


def run_cli(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as exit_:  # argparse
        return int(exit_.code or 0)


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_is_one_line_and_changes_nothing(
    case: Case, world: Path, tmp_path: Path, capsys, monkeypatch
) -> None:
    shutil.copytree(world, tmp_path, dirs_exist_ok=True)
    case.setup(tmp_path)
    before = snapshot(tmp_path)
    capsys.readouterr()  # what the setup printed (writing shards to break) is not the command's
    if case.patch is not None:
        case.patch(monkeypatch)
    code = run_cli([a.format(tmp=tmp_path) for a in case.argv])
    out, err = capsys.readouterr()
    says = [s.format(tmp=tmp_path) for s in ((case.says,) if isinstance(case.says, str) else case.says)]
    assert "Traceback" not in out + err
    assert code == case.code, out + err
    assert err.endswith("\n") and err.count("\n") == 1, f"stderr must be one line:\n{err}"
    if code == 2:
        assert err.startswith("error: ") and all(s in err for s in says), err
        assert out == ""
    else:  # data check: the problems on stdout, each naming its file; a summary on stderr
        found = [line for line in out.splitlines() if not line.startswith("note: ")]
        assert f"{len(found)} problem(s) in" in err, (out, err)
        assert all(s in out for s in says), out
        assert all(str(tmp_path) in line for line in out.splitlines()), out
    assert snapshot(tmp_path) == before
    while _HELD:
        _HELD.pop().close()


def test_an_eval_of_a_stage_retrained_meanwhile_writes_nothing(world: Path, tmp_path: Path, capsys, monkeypatch):
    """The manifest says the stage was trained again while the eval ran (another process
    got past the lock, or wrote the manifest by hand): the old model's scores are not written."""
    from occtrain.stages.pretrain_instruct import WorldModelStage
    from occtrain.stages.stage import EvalResult

    shutil.copytree(world, tmp_path, dirs_exist_ok=True)

    def retrained_meanwhile(request: Any) -> EvalResult:
        manifest = tmp_path / "run" / "manifest.json"
        edit_json(manifest, lambda m: m["stages"]["pretrain"].update(attempts=2, config_hash="other"))
        return EvalResult({"qa_overall": 50.0})

    monkeypatch.setattr(
        WorldModelStage, "evaluate_export", classmethod(lambda cls, request: retrained_meanwhile(request))
    )
    code = run_cli(["eval", str(tmp_path / "run" / "pretrain")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    assert err == (
        f"error: {tmp_path}/run/pretrain: the stage was retrained while occtrain eval read it, so its results of the "
        "model it loaded are not written; run occtrain eval again\n"
    )
    assert not (tmp_path / "run" / "pretrain" / "eval" / "val" / "metrics.json").exists()


def test_the_table_is_big_and_its_ids_unique() -> None:
    assert len(CASES) >= 60
    assert len({c.id for c in CASES}) == len(CASES)


# ----------------------------------------------------------------------------- a real Occ3D release


def make_release(root: Path, released_form: bool = False) -> Path:
    """What an Occ3D-nuScenes download holds: annotations.json as the release writes it
    (timestamps as strings of digits, camera_sensor records, prev/next links, samples not
    in time order) and gts/<scene>/<token>/labels.npz; no occtrain sidecars, no NuScenes-QA.
    Camera records in the README's form (keyed by camera token, ``intrinsic``) or, with
    ``released_form``, as the released files hold them (keyed by channel, ``intrinsics``,
    ``img_path`` relative to imgs/, a timestamp in the camera's ego pose).

    Scene B has no prev/next links at all: its order comes from the timestamps, compared
    as numbers ("999500000" < "1000000000" although not as strings)."""
    scenes = {"scene-0061": ["a0", "a1", "a2", "a3"], "scene-0103": ["b0", "b1", "b2"]}
    start = {"scene-0061": 1_532_402_927_647_951, "scene-0103": 999_500_000}
    infos: dict[str, dict] = {}
    for scene, order in scenes.items():
        infos[scene] = {}
        for i in reversed(range(len(order))):
            token = order[i]
            pose = {"translation": [600.0 + 2.5 * i, 1600.0, 0.0], "rotation": quaternion_from_yaw(0.1 * i)}
            infos[scene][token] = {
                "timestamp": str(start[scene] + 500_000 * i),
                "camera_sensor": {
                    f"CAM_{c}" if released_form else f"{token}-cam{c}": {
                        "img_path": f"CAM_{c}/{token}.jpg" if released_form else f"imgs/CAM_{c}/{token}.jpg",
                        "intrinsics" if released_form else "intrinsic": [
                            [1266.4, 0.0, 816.3],
                            [0.0, 1266.4, 491.5],
                            [0.0, 0.0, 1.0],
                        ],
                        "extrinsic": {"translation": [1.7, 0.0, 1.5], "rotation": [0.5, -0.5, 0.5, -0.5]},
                        "ego_pose": {**pose, "timestamp": start[scene] + 500_000 * i} if released_form else pose,
                    }
                    for c in ("FRONT", "BACK")
                },
                "ego_pose": pose,
                "gt_path": f"gts/{scene}/{token}/labels.npz",
            }
            if scene == "scene-0061":
                infos[scene][token] |= {
                    "prev": order[i - 1] if i else "",
                    "next": order[i + 1] if i + 1 < len(order) else "",
                }
            path = root / "gts" / scene / token / "labels.npz"
            path.parent.mkdir(parents=True)
            np.savez_compressed(path, **hand_labels(i))
    (root / "annotations.json").write_text(
        json.dumps({"train_split": ["scene-0061"], "val_split": ["scene-0103"], "scene_infos": infos})
    )
    return root


@pytest.mark.parametrize("released_form", [False, True], ids=["readme-form", "released-form"])
def test_a_real_release_reads_unchanged_and_checks_ok(tmp_path: Path, capsys, released_form: bool) -> None:
    root = make_release(tmp_path / "occ3d", released_form)
    before = snapshot(root)
    ds = DatasetIndex.open(root)
    assert ds.scenes == {"scene-0061": ["a0", "a1", "a2", "a3"], "scene-0103": ["b0", "b1", "b2"]}
    assert ds.timestamp("scene-0103", "b0") == 999_500_000 and ds.timestamp("scene-0103", "b1") == 1_000_000_000
    x, y, yaw = ds.ego_pose("scene-0061", "a2")
    assert (x, y) == (605.0, 1600.0) and yaw == pytest.approx(0.2)
    assert ds.labels("scene-0103", "b2")["semantics"].shape == GRID_SHAPE
    assert ds.questions("val") is None and ds.questions_by_sample("train") == {}

    assert run_cli(["data", "check", str(root)]) == 0
    out, err = capsys.readouterr()
    assert err == "" and out.splitlines()[-1] == f"dataset {root}: ok"
    notes = out.splitlines()[:-1]
    assert len(notes) == 3 and all(n.startswith(f"note: {root}: no ") for n in notes)
    assert (
        "detection, counting, prediction, chain_of_thought, meta_action, caption training" in notes[0]
        and "occtrain/frames/<scene>.json" in notes[0]
    )
    assert "no qa training" in notes[1] and "NuScenes_<split>_questions.json" in notes[1]
    assert notes[2] == f"note: {root}: no imgs/ camera images; stages that read cameras (vision) need them"

    out_dir = tmp_path / "shards"
    assert run_cli(["data", "shards", str(root), "--out", str(out_dir), "--history", "1", "--future", "1"]) == 0
    capsys.readouterr()
    assert json.loads((out_dir / "index.json").read_text())["kinds"]["clips"]["train"][0]["samples"] == 2
    assert snapshot(root) == before  # read, never written


def _strict_json(text: str) -> Any:
    def refuse(name: str) -> None:
        raise AssertionError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


def test_score_output_is_standard_json(world: Path, tmp_path: Path, capsys) -> None:
    """Classes absent on both sides are undefined (NaN inside): null on stdout and in --out."""
    out = tmp_path / "occ.json"
    # the ground truth scored against itself: its labels tree is a prediction directory too
    code = run_cli(
        [
            "score",
            "occupancy",
            "--pred",
            str(world / "ds" / "gts"),
            "--gt",
            str(world / "ds"),
            "--split",
            "val",
            "--out",
            str(out),
        ]
    )
    printed = capsys.readouterr().out
    assert code == 0
    for result in (_strict_json(printed), _strict_json(out.read_text())):
        assert result["per_class"]["bus"] is None and result["mIoU"] == pytest.approx(100.0)


# ----------------------------------------------------------------------------- the checker itself


class Inner(TypedDict):
    xy: Annotated[list[float], Len(2)]
    tag: NotRequired[Literal["a", "b"]]


@pytest.mark.parametrize(
    "value, tp, found",
    [
        (3, int, []),
        (True, int, ["x is true, expected an integer"]),
        (3, float, []),
        (float("nan"), float, ["x is NaN, expected a number"]),
        (False, float, ["x is false, expected a number"]),
        # typing.Optional spelled out on purpose: the validator reads both spellings of a union.
        (None, Optional[int], []),  # noqa: UP045
        ("3", Optional[int], ['x is the string "3", expected an integer']),  # noqa: UP045
        ({"xy": [1, 2.5], "extra": "kept"}, Inner, []),
        (
            {"xy": [1], "tag": "c"},
            Inner,
            ["x.xy holds 1 item, expected a list of 2 numbers", 'x.tag is the string "c", expected one of "a", "b"'],
        ),
        ({}, Inner, ["x.xy is missing, expected a list of 2 numbers"]),
        ({"k": [{"xy": "no"}]}, dict[str, list[Inner]], ['x.k[0].xy is the string "no", expected a list of 2 numbers']),
        (1.0, Literal[1], ["x is the number 1, expected 1"]),
    ],
)
def test_problems_words_each_mismatch_by_its_key(value: Any, tp: Any, found: list[str]) -> None:
    assert problems(value, tp, "x") == found
