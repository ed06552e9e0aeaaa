"""Text forms that training, evaluation and the synthetic world agree on.

The caption opens with the ego's own motion (``EGO_MOTION_OPENING``), which states the
frame's meta action; ``caption_surroundings`` reads the caption without it.

The meta action (OccVLA: speed x direction) is written in one fixed sentence at the end of
a chain of thought, so a generated one can be parsed back and scored. The synthetic
generator writes it, real-data sidecars may carry it, and models generate it: it lives
here, beside the annotation schema, not in the generator.
"""

from __future__ import annotations

import re

from occtrain.data.schema import MetaAction, MetaDirection, MetaSpeed

META_SPEED_WORDS: dict[MetaSpeed, str] = {
    "accelerate": "accelerate",
    "decelerate": "decelerate",
    "maintain": "maintain speed",
}
META_DIRECTION_WORDS: dict[MetaDirection, str] = {
    "straight": "go straight",
    "left": "turn left",
    "right": "turn right",
    "bear left": "bear left",
    "bear right": "bear right",
    "stop": "stop",
}
#: How a caption's first sentence opens: the ego's motion over the next seconds, then
#: ", with <vehicles> nearby."
EGO_MOTION_OPENING = "The ego car is"
_VEHICLES_CLAUSE = ", with "

#: The meta action sentence's words for "the same as the last past one".
AS_BEFORE = "as before"
_META_RE = re.compile(
    rf"meta action:\s*(?:({AS_BEFORE})|({'|'.join(META_SPEED_WORDS.values())})\s*,\s*"
    rf"({'|'.join(META_DIRECTION_WORDS.values())}))\b",
    re.IGNORECASE,
)


def meta_action_words(meta: MetaAction) -> str:
    """A meta action in words: 'decelerate, turn left'."""
    return f"{META_SPEED_WORDS[meta['speed']]}, {META_DIRECTION_WORDS[meta['direction']]}"


def format_meta_action(meta: MetaAction, previous: MetaAction | None = None) -> str:
    """The fixed, parseable last line of a narration: 'Meta action: decelerate, turn left.'
    Given ``previous`` (the last past meta action), one equal to it is 'Meta action: as before.'"""
    if previous is not None and dict(previous) == dict(meta):
        return f"Meta action: {AS_BEFORE}."
    return f"Meta action: {meta_action_words(meta)}."


def parse_meta_action(text: str, previous: MetaAction | None = None) -> MetaAction | None:
    """The last meta action written in :func:`format_meta_action`'s form in ``text``, or None.
    'As before' reads as ``previous`` (None without one).

    Case and spacing are free and the final period optional, since generated text varies.
    """
    matches = list(_META_RE.finditer(text))
    if not matches:
        return None
    as_before, speed_word, direction_word = matches[-1].groups()
    if as_before:
        return MetaAction(speed=previous["speed"], direction=previous["direction"]) if previous else None
    speed_word, direction_word = speed_word.lower(), direction_word.lower()
    speed = next(k for k, v in META_SPEED_WORDS.items() if v == speed_word)
    direction = next(k for k, v in META_DIRECTION_WORDS.items() if v == direction_word)
    return MetaAction(speed=speed, direction=direction)


def caption_surroundings(caption: str) -> str:
    """The caption without its opening clause on the ego's motion (which states the frame's
    meta action): "The ego car is turning left at 6 m/s, with a moving car nearby. X." ->
    "Nearby: a moving car. X." A caption that does not open that way is returned as is."""
    if not caption.startswith(EGO_MOTION_OPENING):
        return caption
    first, stop, rest = caption.partition(". ")
    first = first.removesuffix(".")
    _, clause, vehicles = first.partition(_VEHICLES_CLAUSE)
    opening = f"Nearby: {vehicles.removesuffix(' nearby')}." if clause else ""
    return " ".join(part for part in (opening, rest) if part)
