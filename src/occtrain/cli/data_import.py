"""``occtrain data import nuscenes | omnidrive | drivelm | nuscenes-qa`` and ``occtrain data
export nuscenes``: the arguments (the bodies in ``commands.data_import``)."""

from __future__ import annotations

import argparse

VERSION_HELP = "the tables' folder under the root: v1.0-mini or v1.0-trainval (default)"


def _cmd_import_nuscenes(args: argparse.Namespace) -> int:
    from occtrain.commands.data_import import import_nuscenes

    import_nuscenes(args.nuscenes, args.version, args.occ3d, args.out, copy=args.copy)
    return 0


def _cmd_import_text(args: argparse.Namespace) -> int:
    from occtrain.commands.data_import import import_text

    print(import_text(args.release, args.src, args.into))
    return 0


def _cmd_export_nuscenes(args: argparse.Namespace) -> int:
    from occtrain.commands.data_import import export_nuscenes

    export_nuscenes(args.dataset, args.out, args.version)
    return 0


def register(data: argparse._SubParsersAction) -> None:
    """Add ``import`` and ``export`` to the ``data`` group."""
    releases = data.add_parser(
        "import", help="build occtrain's sidecars from the public releases (nuScenes, OmniDrive, DriveLM, NuScenes-QA)"
    ).add_subparsers(dest="release", required=True)
    p = releases.add_parser(
        "nuscenes", help="an Occ3D-layout dataset with frame sidecars from the nuScenes tables and Occ3D-nuScenes"
    )
    p.add_argument("--nuscenes", required=True, help="nuScenes root: the folder holding v1.0-*/ (and can_bus/)")
    p.add_argument("--version", default="v1.0-trainval", help=VERSION_HELP)
    p.add_argument("--occ3d", required=True, help="Occ3D-nuScenes root: annotations.json and gts/ (and imgs/)")
    p.add_argument("--out", required=True, help="dataset directory to create (an interrupted import resumes)")
    p.add_argument("--copy", action="store_true", help="copy Occ3D's gts/ scenes instead of linking them")
    p.set_defaults(func=_cmd_import_nuscenes)
    for release, what, src in (
        ("omnidrive", "OmniDrive-nuScenes' descriptions, conversations, VQA and actions", "its root (desc/, ...)"),
        ("drivelm", "DriveLM-nuScenes' graph QA", "its JSON file (v1_1_train_nus.json, ...)"),
        ("nuscenes-qa", "NuScenes-QA's questions", "NuScenes_<split>_questions.json, or the folder holding them"),
    ):
        p = releases.add_parser(release, help=f"{what}, joined to a dataset's frames by sample token")
        p.add_argument("src", help=src)
        p.add_argument("--into", required=True, help="the dataset (an import, or any occtrain dataset)")
        p.set_defaults(func=_cmd_import_text, release=release)

    exports = data.add_parser("export", help="write a dataset as the public releases").add_subparsers(
        dest="release", required=True
    )
    p = exports.add_parser(
        "nuscenes", help="nuScenes v1.0 tables (+ CAN bus), the Occ3D layout, OmniDrive, DriveLM and NuScenes-QA files"
    )
    p.add_argument("dataset", help="dataset root with occtrain's sidecars")
    p.add_argument("--out", required=True, help="directory to create")
    p.add_argument("--version", default="v1.0-trainval", help=VERSION_HELP)
    p.set_defaults(func=_cmd_export_nuscenes)
