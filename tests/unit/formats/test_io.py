"""occtrain.formats.io: the one door every deletion goes through, outputs checked before work, and JSON read
in one line whatever it holds."""

from __future__ import annotations

import errno
import os

import pytest

import occtrain.formats.io
from occtrain.formats.io import OutsideError, WriteError, check_output, parse_json, remove_inside


@pytest.fixture
def run_dir(tmp_path):
    """A run directory beside a victim directory that no deletion may reach."""
    (tmp_path / "victim").mkdir()
    (tmp_path / "victim" / "precious.txt").write_text("mine")
    run = tmp_path / "runs" / "r"
    (run / "stage" / "checkpoints").mkdir(parents=True)
    (run / "stage" / "checkpoints" / "last.ckpt").write_bytes(b"PK")
    return run


@pytest.mark.parametrize(
    "target",
    ["../../victim", "../../victim/precious.txt", "{tmp}/victim", "stage/../../../victim", ".", "", "stage/.."],
    ids=["dotdot", "dotdot-file", "absolute", "dotdot-inside-a-name", "the-run-itself", "empty", "back-to-the-run"],
)
def test_a_deletion_that_reaches_outside_the_run_is_refused(run_dir, tmp_path, target):
    with pytest.raises(OutsideError, match="refusing to delete"):
        remove_inside(run_dir / target.format(tmp=tmp_path), run_dir)
    assert (tmp_path / "victim" / "precious.txt").read_text() == "mine"
    assert (run_dir / "stage" / "checkpoints" / "last.ckpt").is_file()


def test_a_link_inside_the_run_is_removed_as_a_link(run_dir, tmp_path):
    os.symlink(tmp_path / "victim", run_dir / "link")
    assert remove_inside(run_dir / "link", run_dir)
    assert not (run_dir / "link").exists() and (tmp_path / "victim" / "precious.txt").read_text() == "mine"


def test_a_link_to_outside_is_not_a_way_out(run_dir, tmp_path):
    """The run's parent reached through a link: what it points at lies outside."""
    os.symlink(tmp_path, run_dir / "up")
    with pytest.raises(OutsideError):
        remove_inside(run_dir / "up" / "victim", run_dir)
    assert (tmp_path / "victim" / "precious.txt").read_text() == "mine"


def test_inside_the_run_files_and_trees_go(run_dir):
    assert remove_inside(run_dir / "stage" / "checkpoints" / "last.ckpt", run_dir)
    assert remove_inside(run_dir / "stage", run_dir)
    assert not (run_dir / "stage").exists() and run_dir.is_dir()
    assert remove_inside(run_dir / "stage", run_dir) is False  # nothing there: nothing to do


@pytest.mark.parametrize(
    "make, kind, overwrite, says",
    [
        (lambda t: (t / "f").write_text("x"), "dir", True, "{tmp}/f: is a file; --out takes a directory"),
        (lambda t: (t / "f").mkdir(), "file", True, "{tmp}/f: is a directory; --out takes a file name"),
        (
            lambda t: (t / "f").write_text("x"),
            "file",
            False,
            "{tmp}/f: exists; choose another --out or remove it first",
        ),
    ],
    ids=["file-where-a-dir-goes", "dir-where-a-file-goes", "file-exists"],
)
def test_an_output_in_the_way_is_refused_before_any_work(tmp_path, make, kind, overwrite, says):
    make(tmp_path)
    with pytest.raises(WriteError) as err:
        check_output(tmp_path / "f", "--out", kind, overwrite)
    assert str(err.value).startswith(says.format(tmp=tmp_path))


def test_an_output_under_a_file_is_refused(tmp_path):
    (tmp_path / "a").write_text("x")
    with pytest.raises(WriteError, match=f"{tmp_path / 'a'} is a file, not a directory"):
        check_output(tmp_path / "a" / "b" / "c.json", "--out")


def test_an_unwritable_place_is_found_by_a_probe_that_leaves_nothing(tmp_path, monkeypatch):
    check_output(tmp_path / "new" / "deeper", "--out", kind="dir")
    assert list(tmp_path.iterdir()) == []  # the probe went, and no directory was made

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(occtrain.formats.io.tempfile, "mkstemp", read_only)
    with pytest.raises(WriteError, match="cannot write .*new: the file system is read-only"):
        check_output(tmp_path / "new", "--out", kind="dir")


@pytest.mark.parametrize(
    "text, says",
    [
        ("[" * 100_000 + "]" * 100_000, "nested deeper than Python's JSON reader goes"),
        ('{"n": ' + "9" * 5016 + "}", "an integer of 5016 digits, more than Python reads (4300)"),
        ("{not json", "Expecting property name enclosed in double quotes"),
        (b"\xff\xfe{", "can't decode byte"),
    ],
    ids=["nested-100000-deep", "integer-of-5016-digits", "syntax", "not-utf8"],
)
def test_every_json_a_file_can_hold_parses_or_is_one_value_error_line(text, says):
    with pytest.raises(ValueError) as err:
        parse_json(text)
    assert says in str(err.value) and "\n" not in str(err.value)
    assert parse_json('{"a": [1, 2.5, NaN]}')["a"][:2] == [1, 2.5]  # as json.loads: NaN is the schemas' to refuse
