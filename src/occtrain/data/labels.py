"""Occ3D's label files (``gts/<scene>/<token>/labels.npz``): read without unpickling, their
keys, shapes and dtypes checked from the ``.npy`` headers before the arrays inflate, and
their values checked against the classes."""

from __future__ import annotations

import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from occtrain.errors import DataError
from occtrain.formats.occ3d import GRID_SHAPE, NUM_CLASSES

#: The arrays of an Occ3D label file, the masks optional where a reader says so.
LABEL_KEYS = ("semantics", "mask_lidar", "mask_camera")


def label_form_problem(key: str, shape: tuple[int, ...], dtype: np.dtype) -> str | None:
    """What is wrong with the shape or dtype of an Occ3D label array ``key`` (None: nothing,
    or not a label array); read from a ``.npy`` header, it refuses before the data inflates."""
    if key not in LABEL_KEYS:
        return None
    if shape != GRID_SHAPE:
        return f"'{key}' has shape {shape}, expected {GRID_SHAPE}"
    if key == "semantics" and dtype != np.uint8:
        return f"'semantics' has dtype {dtype}, expected uint8"
    if key != "semantics" and dtype not in (np.uint8, np.bool_):
        return f"'{key}' has dtype {dtype}, expected uint8 or bool"
    return None


def validate_labels(arrays: dict[str, np.ndarray], source: str, require_masks: bool = True) -> None:
    """Raise DataError naming ``source`` if an Occ3D label set has a wrong key, shape, dtype or value."""
    keys = LABEL_KEYS if require_masks else LABEL_KEYS[:1]
    for key in keys:
        if key not in arrays:
            raise DataError(f"{source}: missing array '{key}' (expected {', '.join(keys)})")
        arr = arrays[key]
        problem = label_form_problem(key, arr.shape, arr.dtype)
        if problem:
            raise DataError(f"{source}: {problem}")
        if key == "semantics":
            top = int(arr.max())
            if top >= NUM_CLASSES:
                raise DataError(f"{source}: 'semantics' holds class {top}; Occ3D classes are 0..{NUM_CLASSES - 1}")
        elif arr.dtype == np.uint8 and int(arr.max()) > 1:
            raise DataError(f"{source}: '{key}' holds values other than 0/1")


#: Says what is wrong with an array of an ``.npz`` from its name, shape and dtype (None: nothing).
FormCheck = Callable[[str, tuple[int, ...], np.dtype], str | None]


def read_npz(path: Path, form: FormCheck | None = None, keys: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """Load the arrays of an ``.npz`` (only ``keys``, when given) without unpickling; a
    corrupt or pickled file raises DataError.

    Each member's ``.npy`` header is read first, and an array whose shape or dtype ``form``
    refuses is refused from it: inflated, a header claiming (2000, 2000, 160) over a few
    bytes of data would have numpy allocate its 640 MB first."""
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic != b"PK\x03\x04":  # np.load would take any other bytes for a pickle
        raise DataError(f"{path}: corrupt or truncated .npz (not a zip archive); re-create it")
    pickled = f"{path}: holds an object (pickled) array; refusing to load it — re-save with plain arrays"
    try:
        # Members are inflated here, inside the try: a corrupt deflate stream raises
        # zlib.error only when an array is read, not when the archive is opened.
        for key, (shape, dtype) in _npy_headers(path, keys).items():
            if dtype.hasobject:
                raise DataError(pickled)
            problem = form(key, shape, dtype) if form else None
            if problem:
                raise DataError(f"{path}: {problem}")
        with np.load(path, allow_pickle=False) as npz:
            return {key: npz[key] for key in npz.files if keys is None or key in keys}
    except DataError:
        raise
    except ValueError as err:
        if "allow_pickle" in str(err):
            raise DataError(pickled) from None
        raise DataError(f"{path}: not a readable .npz ({_first_line(err)}); re-create it") from None
    except Exception as err:  # zlib.error, BadZipFile, EOFError, OSError, ...: all mean a damaged file
        raise DataError(
            f"{path}: corrupt or truncated .npz ({_error_name(err)}: {_first_line(err)}); re-create it"
        ) from None


def _npy_headers(path: Path, keys: tuple[str, ...] | None) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """(shape, dtype) of each array of an ``.npz`` (of ``keys``), as its header declares:
    only the first bytes of each member are inflated."""
    fmt = np.lib.format
    found = {}
    with zipfile.ZipFile(path) as archive:
        for info in archive.infolist():
            key = info.filename.removesuffix(".npy")
            if keys is not None and key not in keys:
                continue
            with archive.open(info) as member:
                version = fmt.read_magic(member)
                if version not in ((1, 0), (2, 0)):  # 3.0 is for non-latin-1 field names: no label has them
                    raise ValueError(f"member {info.filename}: .npy format version {version} is not read here")
                read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
                shape, _, dtype = read(member)
            found[key] = (tuple(shape), dtype)
    return found


def _first_line(err: BaseException) -> str:
    return str(err).splitlines()[0] if str(err) else type(err).__name__


def _error_name(err: BaseException) -> str:
    """``zlib.error``, ``BadZipFile``: qualified where the bare name says nothing."""
    kind = type(err)
    return kind.__name__ if kind.__module__ in ("builtins", "zipfile") else f"{kind.__module__}.{kind.__name__}"


def load_labels(path: str | Path, require_masks: bool = True) -> dict[str, np.ndarray]:
    """Load and validate one Occ3D ``labels.npz``; masks come back as uint8 0/1."""
    path = Path(path)
    arrays = read_npz(path, label_form_problem, LABEL_KEYS)
    validate_labels(arrays, str(path), require_masks)
    out = {"semantics": arrays["semantics"]}
    for key in LABEL_KEYS[1:]:
        if key in arrays:
            out[key] = arrays[key].astype(np.uint8, copy=False)
    return out
