"""The tree stays clean under the checkers pyproject.toml configures: ruff's rules (pyflakes,
pycodestyle within 120 columns, import order, pyupgrade, bugbear), its formatter, and mypy
(over the whole package, every definition annotated in families/, core/ and engine/)."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

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


def _mypy(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mypy", *args], cwd=cwd, capture_output=True, text=True)


def test_mypy_is_clean_over_the_whole_package():
    """mypy over what pyproject.toml names, the whole of src/occtrain, with untyped
    definitions disallowed in families/, core/ and engine/: the families, the seams they plug
    into and the engine that runs them meet through types it checks, none of them skipped."""
    result = _mypy("--no-error-summary", "--cache-dir", str(REPO / ".mypy_cache"))
    assert result.returncode == 0, result.stdout + result.stderr


def test_mypy_refuses_an_untyped_definition_in_families_core_and_engine_only(tmp_path):
    """The configuration names the whole package, and its override fires: an unannotated
    function in a module resolved as ``occtrain.<package>._probe`` is an error under
    families/, core/ and engine/, and passes under data/, where one is still allowed (its
    body goes unchecked)."""
    mypy = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["mypy"]
    assert mypy["files"] == ["src/occtrain"]
    strict = [o for o in mypy.get("overrides", []) if o.get("disallow_untyped_defs")]
    wanted = {"occtrain.families.*", "occtrain.core.*", "occtrain.engine.*"}
    assert any(wanted <= set(o["module"]) for o in strict), strict

    packages = ("families", "core", "engine", "data")
    (tmp_path / "occtrain").mkdir()
    (tmp_path / "occtrain" / "__init__.py").write_text("")
    for package in packages:
        (tmp_path / "occtrain" / package).mkdir()
        (tmp_path / "occtrain" / package / "__init__.py").write_text("")
        (tmp_path / "occtrain" / package / "_probe.py").write_text("def same(x):\n    return x\n")
    result = _mypy(
        "--config-file",
        str(REPO / "pyproject.toml"),
        "--cache-dir",
        str(tmp_path / "cache"),
        "--no-error-summary",
        *(f"occtrain/{package}/_probe.py" for package in packages),
        cwd=tmp_path,
    )
    refused = {line.split("/")[1] for line in result.stdout.splitlines() if "[no-untyped-def]" in line}
    assert refused == {"families", "core", "engine"}, result.stdout + result.stderr


def test_mypy_catches_a_wrong_type_through_the_configured_settings(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("from occtrain.core.vocab import JointVocab\n\nx: JointVocab = 3\n")
    result = _mypy("--config-file", str(REPO / "pyproject.toml"), "--cache-dir", str(REPO / ".mypy_cache"), str(bad))
    assert result.returncode == 1 and "Incompatible types in assignment" in result.stdout, result.stdout
