"""docs/real-data.md, "Training on the real releases": each ``occtrain plan-memory`` block
on it is the command's output (run again here and compared, so no figure on it is typed),
and the page is in the site's nav and the README's tour."""

from __future__ import annotations

import re
import sys

import pytest

from conftest import REPO
from occtrain.cli import main

PAGE = REPO / "docs" / "real-data.md"
#: A fenced block that opens with the command it holds the output of.
BLOCK = re.compile(r"^```text\n\$ occtrain (?P<argv>plan-memory [^\n]+)\n(?P<out>.*?)^```$", re.M | re.S)


def blocks() -> list[tuple[str, str]]:
    return [(m["argv"], m["out"]) for m in BLOCK.finditer(PAGE.read_text())]


def test_the_page_holds_a_plan_for_each_family_with_a_paper_scale_backbone() -> None:
    recipes = [argv.split()[1] for argv, _ in blocks()]
    assert [r.split("/")[-1].split("_")[0] for r in recipes] == ["occllama", "occvla", "sparseoccvla", "sparseoccvla"]


@pytest.mark.parametrize("argv, printed", blocks(), ids=[a.split()[1] for a, _ in blocks()])
def test_each_plan_on_the_page_is_the_commands_output(argv: str, printed: str, capsys, monkeypatch) -> None:
    monkeypatch.chdir(REPO)
    capsys.readouterr()
    assert main(argv.split()) == 0
    out = capsys.readouterr().out
    assert printed == out, f"rewrite the block of `occtrain {argv}` in {PAGE} with:\n{out}"


def test_the_page_is_in_the_nav_and_the_readmes_tour() -> None:
    assert "real-data.md" in (REPO / "mkdocs.yml").read_text()
    readme = (REPO / "README.md").read_text()
    tour = readme.split("<!-- --8<-- [start:tour] -->")[1].split("<!-- --8<-- [end:tour] -->")[0]
    assert "docs/real-data.md" in tour


if __name__ == "__main__":  # python tests/repo/test_real_data_page.py: write the blocks from the commands
    import contextlib
    import io

    text = PAGE.read_text()
    for argv, printed in blocks():
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            main(argv.split())
        text = text.replace(f"$ occtrain {argv}\n{printed}", f"$ occtrain {argv}\n{buf.getvalue()}", 1)
    PAGE.write_text(text)
    sys.exit(0)
