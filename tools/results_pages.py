"""Regenerate every results page from a set of run directories.

    python tools/results_pages.py RUNS... [--only PAGE] [--out docs/results]

``docs/results/pages.yaml`` declares each page: its file, its title, and the runs it is
made from, each named by its recipe and training seed (``quickstart@1``, or
``quickstart@1/planner`` for a drive table's stage; ``quickstart@1@9683d16`` where the code
that trained it tells it from another), never by a directory. RUNS are run
directories, or folders holding them; a run is found by what its manifest records (the
recipe's name, the training seed and the code that trained it), so the same pages come
from run directories anywhere, on any machine. A page's runs must be scored already
(``occtrain eval`` of each stage it reports; ``--data FOLDER`` for a page on another
world, which names that folder as ``world:``; ``occtrain drive`` of a drive table's stages).

Each page is written by the command its own first lines name (``occtrain report`` or
``tools/drive_table.py``), so a regenerated page is that command's output, stamped with its
runs. A page whose runs are not all among RUNS is left as it is and listed; a recipe and
seed found twice (two codes) must be told apart by the code.

A mistake (a run directory that is not there, a broken page list or manifest, an unscored
run, an ``--out`` that cannot be written) is one line, ``error: ...`` naming the file, with
exit status 2, and no page is written: every page is rendered before the first is written.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import NotRequired, TypedDict

from occtrain.config.loading import read_yaml
from occtrain.data.layout import inside_root
from occtrain.data.validate import first_problem
from occtrain.errors import ConfigError, DataError, OcctrainError, cause_line
from occtrain.formats.io import atomic_write_text, check_output, parse_json
from occtrain.report.results import Run, command_line, report

REPO = Path(__file__).resolve().parents[1]
PAGES = REPO / "docs" / "results" / "pages.yaml"


@dataclass(frozen=True)
class Page:
    """One results page as ``pages.yaml`` declares it."""

    file: str
    title: str = ""
    #: Runs of an ``occtrain report`` page, ``recipe@seed``.
    runs: tuple[str, ...] = ()
    #: Stages of a drive table, ``recipe@seed/stage``.
    drive: tuple[str, ...] = ()
    #: A drive table's routes (``occtrain drive --scenes``), from seed 1000, 20 s each.
    scenes: int = 8
    #: The folder name of the world the runs were scored on with ``occtrain eval --data``
    #: (empty: the runs' own val split).
    world: str = ""
    #: The code version every run must carry (to tell apart runs of one recipe and seed).
    code: str = ""
    allow_mixed: bool = False
    #: A paragraph set under the heading (e.g. why the page is superseded).
    note: str = ""
    #: Pictures of the same runs set under the table, ``FOLDER/NAME`` of ``docs/img``
    #: (drawn by ``tools/docs_pictures.py``; ``docs/hooks.py`` places each with its caption).
    pictures: tuple[str, ...] = ()

    @classmethod
    def of(cls, entry: dict) -> Page:
        return cls(
            **{k: tuple(v) if k in ("runs", "drive", "pictures") else v for k, v in entry.items()},
        )


class PageEntry(TypedDict):
    """A page of ``pages.yaml`` as it is checked (:class:`Page` says what each key means)."""

    file: str
    title: NotRequired[str]
    runs: NotRequired[list[str]]
    drive: NotRequired[list[str]]
    scenes: NotRequired[int]
    world: NotRequired[str]
    code: NotRequired[str]
    allow_mixed: NotRequired[bool]
    note: NotRequired[str]
    pictures: NotRequired[list[str]]


class PagesFile(TypedDict):
    pages: list[PageEntry]


def read_pages(path: Path) -> list[Page]:
    """The pages ``path`` declares; a file that cannot be read or declares them wrongly is
    refused in one line naming it and the key."""
    raw = read_yaml(path)
    problem = first_problem(raw, PagesFile)
    if problem is None:
        for n, entry in enumerate(raw["pages"]):
            unknown = sorted(set(entry) - set(Page.__dataclass_fields__))
            if unknown:
                problem = f"pages[{n}] has unknown keys {', '.join(unknown)}"
            elif not inside_root(entry["file"]):
                problem = f"pages[{n}].file '{entry['file']}' lies outside --out; name a page inside it"
            elif bool(entry.get("runs")) == bool(entry.get("drive")):
                which = "both runs and drive" if entry.get("runs") else "neither runs nor drive"
                problem = f"pages[{n}] ({entry['file']}) gives {which}"
            if problem:
                break
    if problem:
        raise ConfigError(f"{path}: {problem}; each page gives file and either runs or drive")
    return [Page.of(entry) for entry in raw["pages"]]


@dataclass(frozen=True)
class FoundRun:
    path: Path
    recipe: str
    seed: str
    code: str


def find_runs(roots: list[Path]) -> list[FoundRun]:
    """Every run directory in ``roots`` (a run directory or a folder of them), with what
    its manifest says trained it."""
    found = []
    for root in roots:
        if not root.is_dir():
            what = "is a file" if root.exists() else "no such directory"
            raise DataError(f"{root}: {what}; pass run directories, or folders holding them")
        manifests = [root / "manifest.json"]
        if not manifests[0].is_file():
            manifests = sorted(root.glob("*/manifest.json"))
        if not manifests:
            raise DataError(f"{root}: holds no run (no manifest.json in it or its folders); pass run directories")
        found += [read_run(manifest_file) for manifest_file in manifests]
    return found


def read_run(manifest_file: Path) -> FoundRun:
    try:
        manifest = parse_json(manifest_file.read_bytes())
        stages = manifest.get("stages", {}).values()
        seeds = {str((e.get("config") or {}).get("trainer", {}).get("seed", "?")) for e in stages}
        codes = {e.get("code_version") or "?" for e in stages}
    except (OSError, ValueError, AttributeError, TypeError) as err:
        # AttributeError, TypeError: valid JSON of another shape (a list, a stage that is not an object).
        fix = "rerun `occtrain run` on it"
        raise DataError(f"{manifest_file}: not a run manifest ({cause_line(err)}); {fix}") from None
    name = str(manifest.get("name", ""))
    return FoundRun(manifest_file.parent, name, ",".join(sorted(seeds)), ",".join(sorted(codes)))


def resolve(name: str, page: Page, runs: list[FoundRun]) -> Path | None:
    """The run directory ``recipe@seed[@code]`` names among ``runs`` (None: not among them)."""
    recipe, _, rest = name.partition("@")
    seed, _, code = rest.partition("@")
    code = code or page.code
    matches = [r for r in runs if r.recipe == recipe and r.seed == seed and (not code or code in r.code)]
    if len(matches) > 1:
        raise ConfigError(
            f"{page.file}: {name} is {len(matches)} runs ({', '.join(sorted(r.code for r in matches))}); "
            "name the code in the page's code:"
        )
    return matches[0].path if matches else None


def split_of(page: Page, runs: list[Path]) -> str:
    """The eval split a page reports: ``val``, or that of the world folder it names."""
    if not page.world:
        return "val"
    keys = {
        d.parent.name
        for run in runs
        for d in run.glob(f"*/eval/{page.world}-*/val")
        if not d.parent.name.endswith("+blank_cameras")
    }
    if len(keys) != 1:
        raise DataError(
            f"{page.file}: its runs hold {len(keys)} evaluations on a world folder named "
            f"{page.world!r} ({', '.join(sorted(keys)) or 'none'}); score each stage with "
            f"`occtrain eval RUN/STAGE --data {page.world}` of one world"
        )
    return f"{keys.pop()}/val"


def with_note(text: str, note: str) -> str:
    if not note:
        return text
    head, _, rest = text.partition("\n\n")
    return f"{head}\n\n> {note.strip()}\n\n{rest}"


def with_pictures(text: str, pictures: tuple[str, ...]) -> str:
    """``text`` and, under it, a marker for each picture (``docs/hooks.py`` draws them in)."""
    if not pictures:
        return text
    return text.rstrip("\n") + "\n\n## Pictures\n\n" + "\n\n".join(f"<!-- picture: {p} -->" for p in pictures) + "\n"


def _drive_table():
    spec = importlib.util.spec_from_file_location("drive_table", REPO / "tools" / "drive_table.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def render(page: Page, runs: list[FoundRun]) -> tuple[str | None, list[str]]:
    """The page's text, or None and the runs it lacks."""
    if page.runs:
        paths = [resolve(name, page, runs) for name in page.runs]
        missing = [name for name, path in zip(page.runs, paths) if path is None]
        if missing:
            return None, missing
        found = [p for p in paths if p is not None]
        split = split_of(page, found)
        scored = [Run.read(path, split) for path in found]
        command = command_line(len(scored), split, page.title, page.allow_mixed)
        text = report(scored, split, command, page.title, page.allow_mixed)
        return with_pictures(with_note(text, page.note), page.pictures), []
    stages, missing = [], []
    for name in page.drive:
        run_name, _, stage = name.partition("/")
        path = resolve(run_name, page, runs)
        if path is None:
            missing.append(name)
        else:
            stages.append(path / stage)
    if missing:
        return None, missing
    table = _drive_table()
    text = table.markdown(table.summaries(stages, page.scenes, 1000, 20.0, drive=False))
    return with_pictures(with_note(text, page.note), page.pictures), []


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run directories, or folders holding them")
    parser.add_argument("--only", action="append", default=[], metavar="PAGE", help="regenerate this page alone")
    parser.add_argument("--out", type=Path, default=PAGES.parent, help="where the pages go (default docs/results)")
    parser.add_argument("--pages", type=Path, default=PAGES, help="the page list (default docs/results/pages.yaml)")
    args = parser.parse_args(argv)
    try:
        return regenerate(args.runs, args.pages, args.out, args.only)
    except OcctrainError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


def regenerate(roots: list[Path], pages_file: Path, out: Path, only: list[str]) -> int:
    pages = read_pages(pages_file)
    unknown = set(only) - {p.file for p in pages}
    if unknown:
        raise ConfigError(f"--only {sorted(unknown)[0]}: no such page in {pages_file}")
    check_output(out, "--out", kind="dir")
    runs = find_runs(roots)
    texts, left = [], []
    for page in pages:
        if only and page.file not in only:
            continue
        text, missing = render(page, runs)
        if text is None:
            left.append(f"{page.file} (needs {', '.join(missing)})")
        else:
            texts.append((page, text))
    for page, text in texts:
        atomic_write_text(out / page.file, text)
        print(f"{page.file} <- {', '.join(page.runs or page.drive)}")
    print(f"{len(texts)} page(s) written; {len(left)} left as they are" + "".join(f"\n  {p}" for p in left))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
