"""The handoff between stages: an export directory of safetensors weights + JSON config.

``model.safetensors`` + ``config.json`` (+ extra files or directories) are written as one
atomic directory swap, so a reader sees the old export or the new one, never half of
either. Nothing here imports Lightning: models, families and the engine load exports too.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save

from occtrain.errors import OcctrainError, did_you_mean
from occtrain.formats.io import parse_json, remove_inside, write_error

EXPORT_WEIGHTS = "model.safetensors"
EXPORT_CONFIG = "config.json"


#: The top-level keys of each export config occtrain writes, by its ``stage_kind`` and, for a
#: planner, the ``planner`` that wrote it (the meta-action head writes none). A reader refuses
#: any other key: a typo in a hand-edited config would otherwise be ignored and the model
#: rebuilt from a default. Exports of other kinds (a plugin's stage or planner) are their
#: writer's to check.
EXPORT_KEYS: dict[tuple[str, str], frozenset[str]] = {
    ("tokenizer", ""): frozenset(
        {
            "stage_kind",
            "arch",
            "config",
            "params",
            "label_convention",
            "num_codes",
            "codebook_sizes",
            "latent_hw",  # a discrete tokenizer's layout
            "discrete",
            "tokens",
            "token_dim",  # a continuous one's
        }
    ),
    ("world_model", ""): frozenset({"stage_kind", "stage", "family", "vocab", "world", "tasks", "max_new_text_tokens"}),
    ("vision", ""): frozenset({"stage_kind", "stage", "vision", "tower", "image_mean", "image_std", "num_classes"}),
    ("planner", ""): frozenset(
        {
            "stage_kind",
            "features",
            "visual_dim",
            "visual_width",
            "hidden",
            "layers",
            "inputs",
            "train_meta",
            "prior",
            "loss",
            "steps",
        }
    ),
}


def write_export(
    export_dir: Path, state_dict: dict[str, torch.Tensor], config: dict, extra: dict[str, Path] | None = None
) -> Path:
    """Write ``model.safetensors`` + ``config.json`` (+ extra files/dirs) as one atomic directory swap.

    A full disk, a read-only file system or a permission error is a one-line
    :class:`~occtrain.formats.io.WriteError` naming ``export_dir``, whose previous export is kept.
    """
    export_dir = Path(export_dir)
    unknown = _unknown_key(config)
    if unknown is not None:  # occtrain's own writer and EXPORT_KEYS disagree: its readers would refuse the export
        raise ValueError(f"export config key '{unknown}' is missing from occtrain.formats.exports.EXPORT_KEYS")
    try:
        export_dir.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=export_dir.parent, prefix=".export."))
    except OSError as err:
        raise write_error(export_dir, err) from None
    try:
        _fill(tmp, state_dict, config, extra or {})
        _swap_in(tmp, export_dir)
    except BaseException as err:
        with contextlib.suppress(OSError):  # the write's own error is the one to report
            remove_inside(tmp, export_dir.parent)
        if isinstance(err, OSError):
            raise write_error(export_dir, err) from None
        raise
    return export_dir


def _fill(tmp: Path, state_dict: dict[str, torch.Tensor], config: dict, extra: dict[str, Path]) -> None:
    """The export's files in ``tmp``, each on disk (fsynced) before the swap makes them visible."""
    tensors = {k: v.detach().cpu().contiguous() for k, v in state_dict.items()}
    # Serialised here and written by Python: safetensors' own save_file reports a full disk as a
    # SafetensorError whose message is the only trace of the errno.
    (tmp / EXPORT_WEIGHTS).write_bytes(save(tensors))
    (tmp / EXPORT_CONFIG).write_text(json.dumps(config, indent=2) + "\n")
    for name, src in extra.items():
        _copy(Path(src), tmp / name)
    for f in tmp.rglob("*"):
        if f.is_file():
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())


def _copy(src: Path, dst: Path) -> None:
    """``src`` (a file or a tree) copied to ``dst``, file by file: shutil.copytree gathers its
    failures into one shutil.Error of strings, losing the errno a full disk is known by."""
    if not src.is_dir():
        shutil.copy2(src, dst)
        return
    dst.mkdir()
    for child in src.iterdir():
        _copy(child, dst / child.name)


def _swap_in(tmp: Path, export_dir: Path) -> None:
    """``tmp`` becomes ``export_dir``; the export it replaces is put back if the swap fails."""
    old = export_dir.with_name(f".{export_dir.name}.old")
    replaced = export_dir.exists()
    if replaced:
        remove_inside(old, export_dir.parent)
        export_dir.rename(old)
    try:
        tmp.rename(export_dir)
    except OSError:
        if replaced:
            old.rename(export_dir)
        raise
    remove_inside(old, export_dir.parent)


def read_export(export_dir: Path) -> tuple[dict[str, torch.Tensor], dict]:
    """Load an export's weights and config (safetensors + JSON: nothing is unpickled)."""
    export_dir = Path(export_dir)
    weights, config = export_dir / EXPORT_WEIGHTS, export_dir / EXPORT_CONFIG
    if not weights.is_file() or not config.is_file():
        raise OcctrainError(
            f"{export_dir}: no exported model ({EXPORT_WEIGHTS} + {EXPORT_CONFIG}); run the stage that produces it "
            "first"
        )
    cfg = read_config(export_dir)
    try:
        state = load_file(str(weights))
    except Exception as err:  # safetensors raises its own error types on a corrupt or truncated file
        raise OcctrainError(
            f"{weights}: unreadable weights ({type(err).__name__}: {_first_line(err)}); re-run the stage that wrote it"
        ) from None
    return state, cfg


def read_config(export_dir: Path) -> dict:
    """An export's ``config.json``, weights unread; a key its kind does not have is refused."""
    config = Path(export_dir) / EXPORT_CONFIG
    try:
        data = parse_json(config.read_text())
    except (OSError, ValueError) as err:
        raise OcctrainError(
            f"{config}: unreadable export config ({_first_line(err)}); re-run the stage that wrote it"
        ) from None
    if not isinstance(data, dict):
        raise OcctrainError(
            f"{config}: is not a JSON object (found a {type(data).__name__}); re-run the stage that wrote it"
        )
    unknown = _unknown_key(data)
    if unknown is not None:
        raise OcctrainError(f"{config}: unknown key '{unknown}' (rename or remove it){_suggestion(unknown, data)}")
    return data


def _kind_of(config: dict) -> tuple[str, str]:
    return str(config.get("stage_kind", "")), str(config.get("planner", ""))


def _unknown_key(config: dict) -> str | None:
    """The first key of ``config`` that an export of its kind does not have (None for a kind occtrain does not know)."""
    known = EXPORT_KEYS.get(_kind_of(config))
    return next((k for k in config if k not in known), None) if known is not None else None


def _suggestion(key: str, config: dict) -> str:
    return did_you_mean(key, sorted(EXPORT_KEYS[_kind_of(config)]))


def check_section(schema: type, values: Any, key: str, export_dir: Path) -> None:
    """Refuse, in one line as at the top level, a key of ``values`` (the ``key`` section of
    an export's config.json) that the ``schema`` dataclass it was written from lacks: built
    with ``schema(**values)`` it would be a TypeError, merged onto defaults it would be
    silently ignored."""
    config = Path(export_dir) / EXPORT_CONFIG
    if not isinstance(values, dict):
        raise OcctrainError(f"{config}: '{key}' is not a JSON object; re-run the stage that wrote it")
    names = [f.name for f in dataclasses.fields(schema)]
    unknown = next((k for k in values if k not in names), None)
    if unknown is not None:
        raise OcctrainError(
            f"{config}: unknown key '{key}.{unknown}' (rename or remove it){did_you_mean(str(unknown), names)}"
        )


def export_kind(export_dir: Path) -> str:
    """The stage kind an export was written by (its config's ``stage_kind``), weights unread."""
    return str(read_config(export_dir).get("stage_kind", ""))


def _first_line(err: BaseException) -> str:
    return str(err).splitlines()[0] if str(err) else type(err).__name__


def require_config(config: dict, keys: tuple[str, ...], export_dir: Path) -> None:
    """Refuse an export config that lacks an entry its loader reads (a KeyError otherwise)."""
    lacking = [k for k in keys if k not in config]
    if lacking:
        raise OcctrainError(
            f"{Path(export_dir) / EXPORT_CONFIG}: no '{lacking[0]}' entry; re-run the stage that wrote it"
        )


def load_state_strict(
    module: torch.nn.Module,
    state: dict[str, torch.Tensor],
    ignore: tuple[str, ...],
    source: str,
    hint: str = "re-run the stage that wrote them",
) -> None:
    """Load ``state`` into ``module``; every key outside the ``ignore`` prefixes must match
    both ways and in shape, else a one-line error names the first tensor that does not."""
    own = module.state_dict()
    for key, tensor in state.items():
        if key in own and tuple(own[key].shape) != tuple(tensor.shape):
            raise OcctrainError(
                f"{source}: tensor '{key}' has shape {tuple(tensor.shape)} in the weights, the model built from its "
                "config "
                f"wants {tuple(own[key].shape)}; {hint}"
            )
    missing, unexpected = module.load_state_dict(state, strict=False)
    check_loaded_keys(missing, unexpected, ignore, source, hint)


def check_loaded_keys(
    missing: list[str], unexpected: list[str], ignore: tuple[str, ...], source: str, hint: str
) -> None:
    """The strict half of ``load_state_dict(strict=False)``: keys under ``ignore`` may be
    missing (frozen parts that come from another export); nothing else may be."""
    missing = [k for k in missing if not k.startswith(ignore)]
    if missing or unexpected:
        key, what = (missing[0], "missing") if missing else (unexpected[0], "unexpected")
        raise OcctrainError(f"{source}: weights do not match the model ({what} tensor '{key}'); {hint}")
