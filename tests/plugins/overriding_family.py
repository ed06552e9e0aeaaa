"""A plugin that replaces a shipped family on purpose (``override=True``): every command
that discovers families says so in one note."""

from dataclasses import replace

from occtrain.core.registry import get_family, register_family

OCCLLAMA = register_family(replace(get_family("occllama"), paper="OccLLaMA, as a plugin retrained it"), override=True)
