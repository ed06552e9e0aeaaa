"""The tree stays clean under the checkers pyproject.toml configures: ruff's rules (pyflakes,
pycodestyle within 120 columns, import order, pyupgrade, bugbear), its formatter, and mypy."""

from __future__ import annotations

import subprocess
import sys

from conftest import REPO

TREES = ["src", "tests", "tools", "docs"]


def _ruff(*args: str) -> subprocess.CompletedProcess:
    # ruff is a compiled binary beside the interpreter; its Python module finds it.
    return subprocess.run([sys.executable, "-m", "ruff", *args], cwd=REPO, capture_output=True, text=True)


def test_ruff_check_is_clean():
    result = _ruff("check", "--output-format", "concise", *TREES)
    assert result.returncode == 0, result.stdout + result.stderr


def test_ruff_format_leaves_every_file_as_it_is():
    result = _ruff("format", "--check", *TREES)
    assert result.returncode == 0, result.stdout + result.stderr


def test_the_configured_rules_catch_a_long_line_and_an_unused_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("import os\n\nX = " + repr("x" * 130) + "\n")
    result = _ruff("check", "--output-format", "concise", "--config", str(REPO / "pyproject.toml"), str(bad))
    assert result.returncode == 1
    assert "E501" in result.stdout and "F401" in result.stdout


def _mypy(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mypy", *args], cwd=REPO, capture_output=True, text=True)


def test_mypy_is_clean_over_the_typed_seams():
    """mypy over what pyproject.toml names (core/, engine/, stages/, config/, api.py): the
    builder, the engine and the stages meet through types it can check."""
    result = _mypy("--no-error-summary", "--cache-dir", str(REPO / ".mypy_cache"))
    assert result.returncode == 0, result.stdout + result.stderr


def test_mypy_catches_a_wrong_type_through_the_configured_settings(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("from occtrain.core.vocab import JointVocab\n\nx: JointVocab = 3\n")
    result = _mypy("--config-file", str(REPO / "pyproject.toml"), "--cache-dir", str(REPO / ".mypy_cache"), str(bad))
    assert result.returncode == 1 and "Incompatible types in assignment" in result.stdout, result.stdout
