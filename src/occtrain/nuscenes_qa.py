"""NuScenes-QA's question vocabulary: the one place the template types and hop counts live.

The dataset schema (what a question record holds) and the metric (accuracy by type and
hop) both read them from here, so neither layer imports the other.
"""

from __future__ import annotations

#: NuScenes-QA question template types.
TEMPLATE_TYPES: tuple[str, ...] = ("exist", "count", "object", "status", "comparison")
#: Reasoning hops of a question: H0 (zero-hop) and H1 (one-hop).
HOPS: tuple[int, ...] = (0, 1)
