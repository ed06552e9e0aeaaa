"""OmniDrive-nuScenes' released language annotations, read as published.

The release keeps one JSON file per nuScenes sample token and split, in four folders:

    <root>/desc/<split>/<token>.json      {"description": "..."}: the scene description
    <root>/conv/<split>/<token>.json      [{"question": ..., "answer": ...}, ...]: conversation
    <root>/vqa/<split>/<token>.json       [{"question": ..., "answer": ...}, ...]: scene VQA
    <root>/keywords/<split>/<token>.json  "...": the short driving action

(OmniDrive's own loader reads exactly these paths and keys.) Occ3D-nuScenes uses the same
sample tokens, so a frame of an Occ3D-layout dataset finds its text by token.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any

from occtrain.errors import DataError
from occtrain.formats.io import parse_json

FOLDERS = ("desc", "conv", "vqa", "keywords")


class OmniDriveText:
    """The annotations of one OmniDrive-nuScenes root, by sample token (see the module docstring)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not self.root.is_dir() or not any((self.root / f).is_dir() for f in FOLDERS):
            raise DataError(
                f"{self.root}: not an OmniDrive-nuScenes root (it holds none of {', '.join(f + '/' for f in FOLDERS)})"
            )

    def _read(self, folder: str, token: str) -> Any:
        for path in sorted((self.root / folder).glob(f"*/{token}.json")):
            try:
                return parse_json(path.read_text())
            except (OSError, ValueError) as err:
                raise DataError(
                    f"{path}: unreadable OmniDrive annotation ({err}); restore the file from the release"
                ) from None
        return None

    def description(self, token: str) -> str | None:
        """The scene description of ``token``, or None."""
        data = self._read("desc", token)
        if data is None:
            return None
        if not isinstance(data, dict) or not isinstance(data.get("description"), str):
            raise DataError(f'{self.root}/desc/*/{token}.json: expected {{"description": "..."}}')
        return data["description"]

    def pairs(self, token: str) -> list[dict[str, str]]:
        """The conversation and VQA pairs of ``token`` ({"question", "answer"}), conversation first."""
        out = []
        for folder in ("conv", "vqa"):
            data = self._read(folder, token) or []
            if not isinstance(data, list) or not all(
                isinstance(p, dict) and {"question", "answer"} <= set(p) for p in data
            ):
                raise DataError(
                    f'{self.root}/{folder}/*/{token}.json: expected a list of {{"question", "answer"}} pairs'
                )
            out += [{"question": str(p["question"]), "answer": str(p["answer"])} for p in data]
        return out

    def driving_action(self, token: str) -> str | None:
        data = self._read("keywords", token)
        return data if isinstance(data, str) else None


@lru_cache(maxsize=4)
def omnidrive(root: str) -> OmniDriveText:
    """The (cached) reader of an OmniDrive-nuScenes root."""
    return OmniDriveText(root)
