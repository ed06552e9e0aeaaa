"""The README stays short and the documentation site builds with ``--strict``: every page in
the nav, every internal link and anchor resolves, every snippet of the README it includes
exists, and the API reference renders from the docstrings."""

from __future__ import annotations

from pathlib import Path

import pytest

from conftest import REPO

mkdocs_config = pytest.importorskip("mkdocs.config", reason="mkdocs is a dev dependency: pip install -e '.[dev]'")
from mkdocs.commands.build import build  # noqa: E402
from mkdocs.exceptions import Abort  # noqa: E402


def _config(site: Path, **overrides):
    return mkdocs_config.load_config(config_file=str(REPO / "mkdocs.yml"), site_dir=str(site), strict=True, **overrides)


def test_the_readme_is_short_and_holds_the_two_setup_commands():
    readme = (REPO / "README.md").read_text()
    assert readme.count("\n") <= 250
    assert "pip install -e '.[dev]' && occtrain run recipes/quickstart.yaml\npytest\n" in readme


def test_the_site_builds_strict(tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)  # the snippets (README sections) are read from the repository root
    monkeypatch.setenv("NO_MKDOCS_2_WARNING", "1")
    build(_config(tmp_path / "site"))
    site = tmp_path / "site"
    home = (site / "index.html").read_text()
    assert "first public implementation" in home and "A short tour" in home  # the README's sections came in
    for page in (
        "getting-started",
        "world",
        "families/occllm",
        "families/sparseoccvla",
        "performance",
        "reference/config",
    ):
        assert (site / page / "index.html").is_file(), page
    api = (site / "api" / "index.html").read_text()
    assert "TrainedModel" in api and "export_dir" in api  # rendered from src/occtrain/api.py


def test_a_broken_link_fails_the_build(tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)
    monkeypatch.setenv("NO_MKDOCS_2_WARNING", "1")
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "index.md").write_text("# Home\n\nSee [the world](world.md).\n")
    with pytest.raises(Abort, match="strict mode"):
        build(_config(tmp_path / "site", docs_dir=str(docs), nav=[{"Home": "index.md"}]))
