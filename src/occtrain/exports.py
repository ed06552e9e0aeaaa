"""The handoff between stages: an export directory of safetensors weights + JSON config.

``model.safetensors`` + ``config.json`` (+ extra files or directories) are written as one
atomic directory swap, so a reader sees the old export or the new one, never half of
either. Nothing here imports Lightning: models, families and the engine load exports too.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from occtrain.errors import OcctrainError

EXPORT_WEIGHTS = "model.safetensors"
EXPORT_CONFIG = "config.json"


def write_export(export_dir: Path, state_dict: dict[str, torch.Tensor], config: dict, extra: dict[str, Path] | None = None) -> Path:
    """Write ``model.safetensors`` + ``config.json`` (+ extra files/dirs) as one atomic directory swap."""
    export_dir = Path(export_dir)
    export_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=export_dir.parent, prefix=".export."))
    try:
        tensors = {k: v.detach().cpu().contiguous() for k, v in state_dict.items()}
        save_file(tensors, str(tmp / EXPORT_WEIGHTS))
        (tmp / EXPORT_CONFIG).write_text(json.dumps(config, indent=2) + "\n")
        for name, src in (extra or {}).items():
            (shutil.copytree if Path(src).is_dir() else shutil.copy2)(src, tmp / name)
        for f in tmp.rglob("*"):
            if f.is_file():
                with open(f, "rb") as fh:
                    os.fsync(fh.fileno())
        old = export_dir.with_name(f".{export_dir.name}.old")
        if export_dir.exists():
            shutil.rmtree(old, ignore_errors=True)
            export_dir.rename(old)
        tmp.rename(export_dir)
        shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return export_dir


def read_export(export_dir: Path) -> tuple[dict[str, torch.Tensor], dict]:
    """Load an export's weights and config (safetensors + JSON: nothing is unpickled)."""
    export_dir = Path(export_dir)
    weights, config = export_dir / EXPORT_WEIGHTS, export_dir / EXPORT_CONFIG
    if not weights.is_file() or not config.is_file():
        raise OcctrainError(f"{export_dir}: no exported model ({EXPORT_WEIGHTS} + {EXPORT_CONFIG}); run the stage that produces it first")
    try:
        cfg = json.loads(config.read_text())
    except (ValueError, OSError) as err:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise OcctrainError(f"{config}: unreadable export config ({_first_line(err)}); re-run the stage that wrote it") from None
    if not isinstance(cfg, dict):
        raise OcctrainError(f"{config}: is not a JSON object (found a {type(cfg).__name__}); re-run the stage that wrote it")
    try:
        state = load_file(str(weights))
    except Exception as err:  # safetensors raises its own error types on a corrupt or truncated file
        raise OcctrainError(f"{weights}: unreadable weights ({type(err).__name__}: {_first_line(err)}); re-run the stage that wrote it") from None
    return state, cfg


def read_config(export_dir: Path) -> dict:
    """An export's ``config.json``, weights unread."""
    config = Path(export_dir) / EXPORT_CONFIG
    try:
        data = json.loads(config.read_text())
    except (OSError, ValueError) as err:
        raise OcctrainError(f"{config}: unreadable export config ({_first_line(err)}); re-run the stage that wrote it") from None
    if not isinstance(data, dict):
        raise OcctrainError(f"{config}: is not a JSON object (found a {type(data).__name__}); re-run the stage that wrote it")
    return data


def export_kind(export_dir: Path) -> str:
    """The stage kind an export was written by (its config's ``stage_kind``), weights unread."""
    return str(read_config(export_dir).get("stage_kind", ""))


def _first_line(err: BaseException) -> str:
    return str(err).splitlines()[0] if str(err) else type(err).__name__


def require_config(config: dict, keys: tuple[str, ...], export_dir: Path) -> None:
    """Refuse an export config that lacks an entry its loader reads (a KeyError otherwise)."""
    lacking = [k for k in keys if k not in config]
    if lacking:
        raise OcctrainError(f"{Path(export_dir) / EXPORT_CONFIG}: no '{lacking[0]}' entry; re-run the stage that wrote it")


def load_state_strict(
    module: torch.nn.Module, state: dict[str, torch.Tensor], ignore: tuple[str, ...], source: str,
    hint: str = "re-run the stage that wrote them",
) -> None:
    """Load ``state`` into ``module``; every key outside the ``ignore`` prefixes must match
    both ways and in shape, else a one-line error names the first tensor that does not."""
    own = module.state_dict()
    for key, tensor in state.items():
        if key in own and tuple(own[key].shape) != tuple(tensor.shape):
            raise OcctrainError(
                f"{source}: tensor '{key}' has shape {tuple(tensor.shape)} in the weights, the model built from its config "
                f"wants {tuple(own[key].shape)}; {hint}"
            )
    missing, unexpected = module.load_state_dict(state, strict=False)
    check_loaded_keys(missing, unexpected, ignore, source, hint)


def check_loaded_keys(missing: list[str], unexpected: list[str], ignore: tuple[str, ...], source: str, hint: str) -> None:
    """The strict half of ``load_state_dict(strict=False)``: keys under ``ignore`` may be
    missing (frozen parts that come from another export); nothing else may be."""
    missing = [k for k in missing if not k.startswith(ignore)]
    if missing or unexpected:
        key, what = (missing[0], "missing") if missing else (unexpected[0], "unexpected")
        raise OcctrainError(f"{source}: weights do not match the model ({what} tensor '{key}'); {hint}")
