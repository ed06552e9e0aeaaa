"""A plugin that registers a family under a shipped family's name without saying it
overrides it: refused in one line naming both registrations."""

from occtrain.core.registry import FamilySpec, register_family

register_family(FamilySpec(name="occllama", paper="a plugin's OccLLaMA, by mistake"))
