"""tools/results_pages.py: every results page from run directories found by what their
manifests record, each page the very output of the command it names; a mistake is one
line naming its file, and no page is written."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from builders import read_only_disk, snapshot
from conftest import REPO, load_tool, run_cli
from unit.report.test_results import scored_run


@pytest.fixture()
def tool():
    return load_tool("results_pages")


def _pages(tmp_path: Path, *pages: dict) -> Path:
    file = tmp_path / "pages.yaml"
    file.write_text(yaml.safe_dump({"pages": list(pages)}))
    return file


def test_a_page_is_occtrain_reports_output_for_the_runs_it_names(tool, tmp_path):
    # Run directories named anything, anywhere: found by recipe and training seed.
    a = scored_run(tmp_path / "somewhere" / "x", 0, 12.0, 50.0)
    b = scored_run(tmp_path / "elsewhere" / "quickstart-7", 1, 13.0, 52.0)
    title = "The quickstart, two seeds"
    pages = _pages(tmp_path, {"file": "q.md", "title": title, "runs": ["quickstart@1", "quickstart@0"]})
    out = tmp_path / "out"
    out.mkdir()
    assert tool.main([str(tmp_path / "somewhere"), str(b), "--pages", str(pages), "--out", str(out)]) == 0
    res = run_cli("report", str(b), str(a), "--title", title, "--out", str(tmp_path / "by-hand.md"))
    assert res.returncode == 0, res.stderr
    assert (out / "q.md").read_text() == (tmp_path / "by-hand.md").read_text()


def test_a_page_whose_runs_are_absent_is_left_as_it_is(tool, tmp_path, capsys):
    scored_run(tmp_path / "runs" / "a", 0, 12.0, 50.0)
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.md").write_text("kept")
    pages = _pages(
        tmp_path,
        {"file": "old.md", "title": "t", "runs": ["quickstart@0", "quickstart@5"]},
        {"file": "new.md", "title": "t", "runs": ["quickstart@0"], "note": "**Superseded.** Why."},
    )
    tool.main([str(tmp_path / "runs"), "--pages", str(pages), "--out", str(out)])
    assert (out / "old.md").read_text() == "kept"
    assert "old.md (needs quickstart@5)" in capsys.readouterr().out
    new = (out / "new.md").read_text()
    assert new.startswith("# t\n\n> **Superseded.** Why.\n\nWorld v4;")


def test_a_pages_pictures_are_placed_under_its_table(tool, tmp_path):
    scored_run(tmp_path / "runs" / "a", 0, 12.0, 50.0)
    out = tmp_path / "out"
    out.mkdir()
    pictures = ["quickstart/reconstruction", "quickstart/forecast"]
    pages = _pages(tmp_path, {"file": "p.md", "title": "t", "runs": ["quickstart@0"], "pictures": pictures})
    tool.main([str(tmp_path / "runs"), "--pages", str(pages), "--out", str(out)])
    text = (out / "p.md").read_text()
    table, _, under = text.partition("\n## Pictures\n\n")
    assert "| all stages | 150 |" in table  # the report is whole, the pictures after it
    assert under == "<!-- picture: quickstart/reconstruction -->\n\n<!-- picture: quickstart/forecast -->\n"


def test_one_recipe_and_seed_of_two_codes_must_be_told_apart(tool, tmp_path, capsys):
    scored_run(tmp_path / "runs" / "a", 0, 12.0, 50.0, code="0.1.0+aaa1111")
    scored_run(tmp_path / "runs" / "b", 0, 14.0, 50.0, code="0.1.0+bbb2222")
    out = tmp_path / "out"
    out.mkdir()
    pages = _pages(tmp_path, {"file": "p.md", "title": "t", "runs": ["quickstart@0"]})
    assert tool.main([str(tmp_path / "runs"), "--pages", str(pages), "--out", str(out)]) == 2
    assert "p.md: quickstart@0 is 2 runs" in capsys.readouterr().err
    pages = _pages(tmp_path, {"file": "p.md", "title": "t", "runs": ["quickstart@0@bbb2222"]})
    tool.main([str(tmp_path / "runs"), "--pages", str(pages), "--out", str(out)])
    assert "code 0.1.0+bbb2222" in (out / "p.md").read_text()


def test_the_shipped_page_list_names_every_results_page():
    listed = {p["file"] for p in yaml.safe_load((REPO / "docs" / "results" / "pages.yaml").read_text())["pages"]}
    shipped = {p.name for p in (REPO / "docs" / "results").glob("*.md") if p.name != "index.md"}
    assert listed == shipped


@dataclass(frozen=True)
class Case:
    """One mistake: ``setup(tmp)`` breaks a copy of two scored runs (quickstart@0 in runs/a,
    quickstart@1 in runs/b), their page list (q.md and r.md) and an out/ holding q.md;
    ``argv`` (``{tmp}`` filled in) replaces the arguments it names; the error line says ``says``."""

    id: str
    says: str
    argv: dict[str, str]
    setup: Callable[[Path], None] = lambda tmp: None
    patch: Callable[[pytest.MonkeyPatch], None] | None = None


def _unscore(run: Path) -> None:
    for evaluation in run.glob("*/eval"):
        shutil.rmtree(evaluation)


CASES = [
    Case("missing run dir", "{tmp}/runs/nonexistent: no such directory", {"runs": "{tmp}/runs/nonexistent"}),
    Case(
        "a file as the run dir",
        "{tmp}/runs/a/manifest.json: is a file",
        {"runs": "{tmp}/runs/a/manifest.json"},
    ),
    Case(
        "a folder holding no run",
        "{tmp}/empty: holds no run",
        {"runs": "{tmp}/empty"},
        setup=lambda tmp: (tmp / "empty").mkdir(),
    ),
    Case(
        "--out onto a file",
        "{tmp}/out/q.md: is a file; --out takes a directory",
        {"--out": "{tmp}/out/q.md"},
    ),
    Case(
        "--out read-only",
        "cannot write {tmp}/out: the file system is read-only",
        {},
        patch=read_only_disk,
    ),
    Case("pages file missing", "config file not found: {tmp}/nope.yaml", {"--pages": "{tmp}/nope.yaml"}),
    Case(
        "pages file not YAML",
        "{tmp}/pages.yaml line 2: not valid YAML",
        {},
        setup=lambda tmp: (tmp / "pages.yaml").write_text("pages: [{file: q.md\n"),
    ),
    Case(
        "pages file of another shape",
        "{tmp}/pages.yaml: pages[0].runs is the string",
        {},
        setup=lambda tmp: (tmp / "pages.yaml").write_text("pages:\n- {file: q.md, runs: quickstart@0}\n"),
    ),
    Case(
        "a page with neither runs nor drive",
        "{tmp}/pages.yaml: pages[0] (q.md) gives neither runs nor drive",
        {},
        setup=lambda tmp: (tmp / "pages.yaml").write_text("pages:\n- {file: q.md, title: t}\n"),
    ),
    Case(
        "a page outside --out",
        "{tmp}/pages.yaml: pages[0].file '../q.md' lies outside --out",
        {},
        setup=lambda tmp: (tmp / "pages.yaml").write_text("pages:\n- {file: ../q.md, runs: [quickstart@0]}\n"),
    ),
    Case(
        "an unscored run (after a page that is written first)",
        "{tmp}/runs/b: no stage is scored on 'val'",
        {},
        setup=lambda tmp: _unscore(tmp / "runs" / "b"),
    ),
    Case(
        "a corrupt manifest",
        "{tmp}/runs/b/manifest.json: not a run manifest (JSONDecodeError",
        {},
        setup=lambda tmp: (tmp / "runs" / "b" / "manifest.json").write_text('{"name": "quick'),
    ),
    Case(
        "a manifest of another shape",
        "{tmp}/runs/b/manifest.json: not a run manifest (AttributeError",
        {},
        setup=lambda tmp: (tmp / "runs" / "b" / "manifest.json").write_text(json.dumps(["quickstart"])),
    ),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_a_mistake_is_one_line_naming_its_file_and_writes_nothing(case, tool, tmp_path, capsys, monkeypatch):
    scored_run(tmp_path / "runs" / "a", 0, 12.0, 50.0)
    scored_run(tmp_path / "runs" / "b", 1, 13.0, 52.0)
    _pages(
        tmp_path, {"file": "q.md", "title": "t", "runs": ["quickstart@0"]}, {"file": "r.md", "runs": ["quickstart@1"]}
    )
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "q.md").write_text("kept")
    case.setup(tmp_path)
    args = {"runs": "{tmp}/runs", "--pages": "{tmp}/pages.yaml", "--out": "{tmp}/out"} | case.argv
    argv = [args.pop("runs")] + [part for flag_value in args.items() for part in flag_value]
    before = snapshot(tmp_path)
    if case.patch is not None:
        case.patch(monkeypatch)
    code = tool.main([a.format(tmp=tmp_path) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    assert code == 2, out + err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert case.says.format(tmp=tmp_path) in err, err
    assert out == ""
    assert snapshot(tmp_path) == before
