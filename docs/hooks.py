"""MkDocs hooks: pages generated from the code at build time, so they cannot drift from it."""

from __future__ import annotations

from mkdocs.structure.files import File


def on_files(files, config):
    from occtrain.stages.registered_schemas import config_reference

    files.append(File.generated(config, "reference/config.md", content=config_reference()))
    return files
