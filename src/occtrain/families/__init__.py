"""One folder per paper family: its configs, model pieces, prompt and task formats, scorers,
paper figures and one registration (``core.registry.FamilySpec``). The registry finds each
sub-package of this package; nothing outside a family's folder imports it, and a family
imports no other. Blocks the families share live in ``occtrain.core`` and ``occtrain.models``."""
