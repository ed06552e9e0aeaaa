"""The blanked-camera view of a dataset: black images at the source's sizes, everything
else linked, an identity and caches of its own, and no half view after a failure."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from occtrain.data.blank_cameras import BLANK_SUFFIX, blank_camera_view, camera_images
from occtrain.data.identity import world_identity
from occtrain.data.layout import DatasetIndex, generator_record
from occtrain.data.shards import world_key
from occtrain.errors import DataError
from occtrain.formats.io import WriteError


def test_every_camera_image_is_black_at_its_size_and_the_rest_is_the_sources(synth_dataset, tmp_path):
    view = blank_camera_view(synth_dataset, tmp_path / "blank")
    assert view.name == synth_dataset.name + BLANK_SUFFIX
    source, blanked = DatasetIndex.open(synth_dataset), DatasetIndex.open(view)
    assert list(blanked.samples()) == list(source.samples())
    scene, token = next(iter(source.samples("val")))
    real, black = source.images(scene, token), blanked.images(scene, token)
    assert black.shape == real.shape and real.any() and not black.any()
    # Labels and the synthetic class/depth maps (targets, not inputs) are the source's.
    np.testing.assert_array_equal(blanked.labels(scene, token)["semantics"], source.labels(scene, token)["semantics"])
    maps, view_maps = source.camera_targets(scene, token), blanked.camera_targets(scene, token)
    assert maps is not None and view_maps is not None and np.array_equal(maps[0], view_maps[0])
    assert not (view / "shards").exists()  # built for the view, from its own images
    # Another dataset to every key: its identity, its name, its caches.
    assert world_identity(view).key != world_identity(synth_dataset).key
    assert world_identity(view).name == world_identity(synth_dataset).name + ", its camera images blanked"
    assert world_key(view) != world_key(synth_dataset)
    assert generator_record(view) == {**generator_record(synth_dataset), "cameras": "blanked"}
    assert not any(p.is_symlink() for p in camera_images(blanked))


def test_the_view_is_made_once_and_a_failed_build_leaves_nothing(synth_dataset, tmp_path, monkeypatch):
    view = blank_camera_view(synth_dataset, tmp_path / "blank")
    stamp = (view / "occtrain" / "dataset.json").stat().st_mtime_ns
    assert blank_camera_view(synth_dataset, tmp_path / "blank") == view
    assert (view / "occtrain" / "dataset.json").stat().st_mtime_ns == stamp

    import occtrain.data.blank_cameras as blank

    def broken(image, target):
        raise OSError("disk full")

    monkeypatch.setattr(blank, "_write_black", broken)
    with pytest.raises(OSError, match="disk full"):
        blank_camera_view(synth_dataset, tmp_path / "other")
    assert list((tmp_path / "other").iterdir()) == []


def test_a_dataset_without_cameras_is_refused(hand_dataset, tmp_path):
    with pytest.raises(DataError, match="has no camera images to blank"):
        blank_camera_view(hand_dataset, tmp_path)


def test_a_view_that_cannot_be_written_is_one_line_naming_it(synth_dataset, tmp_path, monkeypatch):
    import errno
    import tempfile

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkdtemp", read_only)
    with pytest.raises(WriteError) as err:
        blank_camera_view(synth_dataset, tmp_path / "blank")
    view = tmp_path / "blank" / (synth_dataset.name + BLANK_SUFFIX)
    assert str(err.value) == (
        f"cannot write {view}: the file system is read-only; point the run (--run-dir) or --out at a writable place"
    )


def test_an_unreadable_camera_image_is_one_line_naming_it_and_leaves_nothing(synth_dataset, tmp_path):
    source = tmp_path / "world"
    shutil.copytree(synth_dataset, source, symlinks=True)
    index = DatasetIndex.open(source)
    broken = sorted(camera_images(index))[3]
    broken.write_bytes(broken.read_bytes()[:100])  # cut off mid-file, as a failed copy leaves it
    with pytest.raises(DataError) as err:
        blank_camera_view(source, tmp_path / "blank")
    assert str(err.value).startswith(f"{broken}: unreadable camera image (") and "\n" not in str(err.value)
    assert list((tmp_path / "blank").iterdir()) == []


def test_two_builds_at_once_both_end_with_the_one_view(synth_dataset, tmp_path, monkeypatch):
    """Another eval renames its view into place while this one builds: this one's is dropped."""
    import occtrain.data.blank_cameras as blank

    into = tmp_path / "blank"
    other = blank_camera_view(synth_dataset, tmp_path / "first")
    real_mirror = blank._mirror

    def meanwhile(src, dst, images, record, top=False):
        real_mirror(src, dst, images, record, top)
        if top:  # the other build finishes first
            shutil.copytree(other, into / other.name, symlinks=True)

    monkeypatch.setattr(blank, "_mirror", meanwhile)
    view = blank_camera_view(synth_dataset, into)
    assert view == into / other.name and sorted(p.name for p in into.iterdir()) == [other.name]
