"""MkDocs hooks: pages generated from the code at build time, so they cannot drift from it,
and pictures placed with the captions the run that drew them wrote."""

from __future__ import annotations

import json
import posixpath
import re
from pathlib import Path

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File

#: ``<!-- picture: quickstart/world -->`` on a line of its own: the picture ``world`` of
#: ``docs/img/quickstart/pictures.json`` (written by ``tools/docs_pictures.py``).
PICTURE = re.compile(r"^<!-- picture: (?P<folder>[\w./-]+)/(?P<name>\w+) -->$", re.MULTILINE)


def on_files(files, config):
    from occtrain.stages.registered_schemas import config_reference

    files.append(File.generated(config, "reference/config.md", content=config_reference()))
    return files


def picture_markdown(docs: Path, folder: str, name: str, page_uri: str) -> str:
    """The image (its alt text from the index) and its caption, linked relative to the page;
    a picture the index lacks, or whose file is missing, stops the build."""
    index = docs / "img" / folder / "pictures.json"
    if not index.is_file():
        draw = f"tools/docs_pictures.py RUN --out {index.parent}"
        raise PluginError(f"{page_uri}: no {index.relative_to(docs)}; draw it with {draw}")
    pictures = json.loads(index.read_text())["pictures"]
    if name not in pictures:
        raise PluginError(f"{page_uri}: {folder} has no picture '{name}'; it has {', '.join(pictures)}")
    entry = pictures[name]
    if not (index.parent / entry["file"]).is_file():
        raise PluginError(f"{page_uri}: {folder}/{entry['file']} is missing; draw it again with tools/docs_pictures.py")
    src = posixpath.relpath(f"img/{folder}/{entry['file']}", posixpath.dirname(page_uri) or ".")
    return f"![{entry['alt']}]({src})\n\n*{entry['caption']}*"


def on_page_markdown(markdown, page, config, files):
    docs = Path(config["docs_dir"])
    return PICTURE.sub(lambda m: picture_markdown(docs, m["folder"], m["name"], page.file.src_uri), markdown)
