"""``occtrain data import`` and ``occtrain data export``: the public releases in, and the
dataset back out as them (the bodies live in ``data.releases``)."""

from __future__ import annotations

from pathlib import Path

from occtrain.errors import ConfigError
from occtrain.formats.io import check_output


def import_nuscenes(nuscenes: str, version: str, occ3d: str, out: str, copy: bool = False) -> dict:
    """``occtrain data import nuscenes``: frames from the tables, Occ3D's labels linked (or copied)."""
    from occtrain.data.releases.nuscenes_import import import_nuscenes as run
    from occtrain.data.releases.nuscenes_tables import VERSIONS

    if version not in VERSIONS:
        raise ConfigError(
            f"--version {version}: occtrain imports {' or '.join(VERSIONS)} (Occ3D-nuScenes labels those two)"
        )
    check_output(out, "--out", kind="dir")
    return run(nuscenes, version, occ3d, out, copy=copy)


def import_text(release: str, src: str, into: str) -> str:
    """``occtrain data import omnidrive|drivelm|nuscenes-qa``: its summary line."""
    from occtrain.data.releases import text_import

    run = {
        "omnidrive": text_import.import_omnidrive,
        "drivelm": text_import.import_drivelm,
        "nuscenes-qa": text_import.import_nuscenes_qa,
    }[release]
    return run(Path(src), Path(into)).line()


def export_nuscenes(root: str, out: str, version: str) -> dict:
    """``occtrain data export nuscenes``: the dataset as the nuScenes tables and the text releases."""
    from occtrain.data.releases.nuscenes_export import export_nuscenes as run
    from occtrain.data.releases.nuscenes_tables import VERSIONS

    if version not in VERSIONS:
        raise ConfigError(f"--version {version}: write one of {' or '.join(VERSIONS)}")
    check_output(out, "--out", kind="dir")
    return run(root, out, version)
