"""Sequence packing: which laid-out sequences share a row of a training batch.

A batch of a world model's tasks mixes short sequences (a question about one scene) with
long ones (a forecast over several): padded one to a row, most of a row can be padding,
and the LLM computes over it all the same. Packed, several sequences share a row, each
attending only to itself (``models.attention.allowed_pairs``' sample ids) at its own
positions, so every token's loss is what it would be alone while the batch holds fewer
rows. The attention itself stays torch's SDPA under the boolean mask the batch carries.
"""

from __future__ import annotations


def pack_rows(lengths: list[int], capacity: int = 0) -> list[list[int]]:
    """The sequences (indices into ``lengths``) of each row, first-fit decreasing: longest
    first, each into the first row with room for it. A row holds ``capacity`` tokens, or
    the longest sequence's when that is longer (a sequence is never cut), so the packed
    batch is never longer than the padded one. Each row lists its sequences in order;
    rows come in the order of their first sequence."""
    capacity = max([capacity, *lengths])
    order = sorted(range(len(lengths)), key=lambda i: (-lengths[i], i))
    rows: list[list[int]] = []
    room: list[int] = []
    for i in order:
        r = next((r for r, free in enumerate(room) if lengths[i] <= free), None)
        if r is None:
            rows.append([])
            room.append(capacity)
            r = len(rows) - 1
        rows[r].append(i)
        room[r] -= lengths[i]
    return sorted((sorted(row) for row in rows), key=lambda row: row[0])
