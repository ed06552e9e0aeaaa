"""tools/results_pages.py: every results page from run directories found by what their
manifests record, each page the very output of the command it names."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

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


def test_one_recipe_and_seed_of_two_codes_must_be_told_apart(tool, tmp_path):
    scored_run(tmp_path / "runs" / "a", 0, 12.0, 50.0, code="0.1.0+aaa1111")
    scored_run(tmp_path / "runs" / "b", 0, 14.0, 50.0, code="0.1.0+bbb2222")
    out = tmp_path / "out"
    out.mkdir()
    pages = _pages(tmp_path, {"file": "p.md", "title": "t", "runs": ["quickstart@0"]})
    with pytest.raises(SystemExit, match="is 2 runs"):
        tool.main([str(tmp_path / "runs"), "--pages", str(pages), "--out", str(out)])
    pages = _pages(tmp_path, {"file": "p.md", "title": "t", "runs": ["quickstart@0@bbb2222"]})
    tool.main([str(tmp_path / "runs"), "--pages", str(pages), "--out", str(out)])
    assert "code 0.1.0+bbb2222" in (out / "p.md").read_text()


def test_the_shipped_page_list_names_every_results_page():
    listed = {p["file"] for p in yaml.safe_load((REPO / "docs" / "results" / "pages.yaml").read_text())["pages"]}
    shipped = {p.name for p in (REPO / "docs" / "results").glob("*.md") if p.name != "index.md"}
    assert listed == shipped
