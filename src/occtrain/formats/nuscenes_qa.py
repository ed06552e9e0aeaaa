"""NuScenes-QA's question vocabulary: the one place the template types and hop counts live.

The dataset schema (what a question record holds) and the metric (accuracy by type and
hop) both read them from here, so neither layer imports the other.
"""

from __future__ import annotations

from typing import Literal, get_args

#: NuScenes-QA question template types.
TemplateType = Literal["exist", "count", "object", "status", "comparison"]
TEMPLATE_TYPES: tuple[str, ...] = get_args(TemplateType)
#: Reasoning hops of a question: H0 (zero-hop) and H1 (one-hop).
HOPS: tuple[int, ...] = (0, 1)
