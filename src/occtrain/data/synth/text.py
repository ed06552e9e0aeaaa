"""The synthetic world's text, derived only from one frame's truth.

Three products per frame:

- NuScenes-QA questions (:func:`questions_for_frame`) in NuScenes-QA's own JSON records,
  with its five template types, zero- and one-hop questions and answer vocabulary;
- a one- or two-sentence caption (:func:`caption_for_frame`);
- an OccVLA-style chain-of-thought narration (:func:`narration_for_frame`) whose last
  line is the meta action in the fixed form of ``occtrain.data.text_formats``.

Only the ten nuScenes detection classes take part in questions: boxes of Occ3D's
``others`` class have no NuScenes-QA name, so they are neither asked about nor used to
decide whether a description ("the moving thing") is unique.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal, TypeVar

import numpy as np

from occtrain.data.schema import (
    COMMANDS,
    META_DIRECTIONS,
    META_SPEEDS,
    STATUS_VALUES,
    STOP_SPEED,
    TEMPLATE_TYPES,
    FrameAnnotation,
    QAQuestion,
)
from occtrain.data.text_formats import EGO_MOTION_OPENING, format_meta_action
from occtrain.errors import DataError
from occtrain.formats.occ3d import CLASS_NAMES, FRAME_DT

# ---------------------------------------------------------------- vocabularies

#: Occ3D object class -> its NuScenes-QA name (nuScenes detection class wording).
QA_CLASS_NAMES: dict[str, str] = {name: name.replace("_", " ") for name in CLASS_NAMES[1:11]}
QA_CLASSES: tuple[str, ...] = tuple(QA_CLASS_NAMES.values())

#: The statuses each QA class can have (nuScenes attribute families): vehicles are
#: moving/parked/stopped, pedestrians moving/standing, cycles with/without rider, and
#: barriers and cones have none. Questions about absent objects draw from these pairs.
CLASS_STATUSES: dict[str, tuple[str, ...]] = {
    "barrier": (),
    "bicycle": ("with rider", "without rider"),
    "bus": ("moving", "parked", "stopped"),
    "car": ("moving", "parked", "stopped"),
    "construction vehicle": ("moving", "parked", "stopped"),
    "motorcycle": ("with rider", "without rider"),
    "pedestrian": ("moving", "standing"),
    "traffic cone": (),
    "trailer": ("moving", "parked", "stopped"),
    "truck": ("moving", "parked", "stopped"),
}

#: NuScenes-QA answers counts 0..10 only; a count question with a larger answer is not asked.
MAX_COUNT_ANSWER = 10
#: Every answer a question of this module can have.
ANSWERS: tuple[str, ...] = (
    tuple(str(n) for n in range(MAX_COUNT_ANSWER + 1)) + ("no", "yes") + QA_CLASSES + STATUS_VALUES
)

#: Spatial relations, counter-clockwise from the ego's forward axis; see spatial_relation.
RELATIONS: tuple[str, ...] = ("front", "front left", "back left", "back", "back right", "front right")

# Share of existence questions about something present (the rest ask about absent
# things), and of count questions whose answer is 0: keeps "yes"/"no" balanced and
# "0" common but not dominant.
PRESENT_SHARE = 0.5
ZERO_COUNT_SHARE = 0.25
# Tries per wanted question: a draw can fail (nothing unique to ask about) or repeat.
ATTEMPTS_PER_QUESTION = 8

# Narration / caption geometry (metres, ego frame).
LANE_HALF_WIDTH = 1.8  # |y| within which an object ahead is "in the ego's lane"
LANE_LOOKAHEAD = 30.0  # how far ahead the lane check looks
MOVER_MIN_SPEED = 0.5  # m/s of average future displacement that counts as moving
CONFLICT_DISTANCE = 3.0  # an agent this close to the ego's planned position at the same step
NARRATED_OBJECTS = 5
NARRATED_MOVERS = 3

VEHICLE_CLASSES = ("car", "truck", "bus", "trailer", "construction_vehicle")
_NOUNS: dict[str, str] = {**QA_CLASS_NAMES, "others": "unidentified object"}
# Statuses that read after the noun ("a bicycle with a rider"): (singular, plural).
_POST_NOMINAL = {"with rider": ("with a rider", "with riders"), "without rider": ("without a rider", "without riders")}

# Eight 45-degree sectors, counter-clockwise from ahead: where an object is ...
_POSITION_WORDS = (
    "ahead",
    "ahead on the left",
    "to the left",
    "behind on the left",
    "behind",
    "behind on the right",
    "to the right",
    "ahead on the right",
)
# ... and where it is going.
_HEADING_WORDS = (
    "forward",
    "forward and to the left",
    "to the left",
    "backward and to the left",
    "backward",
    "backward and to the right",
    "to the right",
    "forward and to the right",
)
_CAPTION_MOTION = {
    "straight": "driving straight",
    "left": "turning left",
    "right": "turning right",
    "bear left": "bearing left",
    "bear right": "bearing right",
}
_CAPTION_SPEED = {"accelerate": " and speeding up", "decelerate": " and slowing down", "maintain": ""}


# ---------------------------------------------------------------- geometry


def spatial_relation(reference_xy: np.ndarray, target_xy: np.ndarray) -> np.ndarray:
    """Index into RELATIONS of where ``target_xy`` lies as seen from ``reference_xy``.

    As in NuScenes-QA, directions are those of the *ego* frame (front = +x, left = +y),
    whatever the reference object's own heading. With ``theta`` the angle in degrees of
    ``target - reference`` counter-clockwise from +x, the six 60-degree sectors are
    (lower bound included, upper excluded):

    front [-30, 30), front left [30, 90), back left [90, 150), back [150, 180] or
    (-180, -150), back right [-150, -90), front right [-90, -30).

    Broadcasts over leading dimensions (the last one holds x, y); returns integer indices.
    """
    d = np.asarray(target_xy, dtype=np.float64) - np.asarray(reference_xy, dtype=np.float64)
    theta = np.degrees(np.arctan2(d[..., 1], d[..., 0]))
    return (np.floor(np.mod(theta + 30.0, 360.0) / 60.0) % 6).astype(np.int64)


def _sector8(xy: np.ndarray) -> np.ndarray:
    """Index of the 45-degree sector (counter-clockwise from +x) each vector points into."""
    theta = np.degrees(np.arctan2(xy[..., 1], xy[..., 0]))
    return (np.floor(np.mod(theta + 22.5, 360.0) / 45.0) % 8).astype(np.int64)


def _in_lane_ahead(xy: np.ndarray) -> np.ndarray:
    return (xy[..., 0] > 0) & (xy[..., 0] <= LANE_LOOKAHEAD) & (np.abs(xy[..., 1]) <= LANE_HALF_WIDTH)


# ---------------------------------------------------------------- frame checks


def _where(frame: FrameAnnotation) -> str:
    return f"frame '{frame.get('token', '?')}' of scene '{frame.get('scene', '?')}'"


def _check_boxes(frame: FrameAnnotation) -> None:
    for i, box in enumerate(frame["boxes"]):
        if box["category"] not in _NOUNS:
            raise DataError(
                f"{_where(frame)}: box {i} has category {box['category']!r}; "
                f"use an Occ3D object class ({', '.join(CLASS_NAMES[:11])})"
            )
        if box["attribute"] not in STATUS_VALUES and box["attribute"] != "":
            raise DataError(
                f"{_where(frame)}: box {i} has attribute {box['attribute']!r}; "
                f"use one of {', '.join(STATUS_VALUES)} or '' for static objects"
            )


def _check_meta(frame: FrameAnnotation) -> None:
    meta = frame["meta_action"]
    if meta.get("speed") not in META_SPEEDS or meta.get("direction") not in META_DIRECTIONS:
        raise DataError(
            f"{_where(frame)}: meta_action {meta!r} is not a (speed, direction) pair from "
            f"{'/'.join(META_SPEEDS)} x {'/'.join(META_DIRECTIONS)}"
        )
    if frame["command"] not in COMMANDS:
        raise DataError(f"{_where(frame)}: command {frame['command']!r} is not one of {', '.join(COMMANDS)}")


# ---------------------------------------------------------------- noun phrases


def _plural(noun: str) -> str:
    return noun + ("es" if noun.endswith(("s", "x", "ch", "sh")) else "s")


def _noun_phrase(noun: str, status: str | None, plural: bool) -> str:
    """'parked cars', 'moving thing', 'bicycle with a rider', ... (no article)."""
    head = _plural(noun) if plural else noun
    if status is None:
        return head
    if status in _POST_NOMINAL:
        return f"{head} {_POST_NOMINAL[status][int(plural)]}"
    return f"{status} {head}"


def _article(phrase: str) -> str:
    return ("an " if phrase[0] in "aeiou" else "a ") + phrase


def _counted(n: int, noun: str, status: str | None) -> str:
    return f"{n} {_noun_phrase(noun, status, plural=n != 1)}"


def _join(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


# ---------------------------------------------------------------- questions


# A description: (class index or None for "thing", status index or None for any).
_Desc = tuple[int | None, int | None]

#: Every class and class+status description a question may name, present or not.
_VOCAB: tuple[_Desc, ...] = tuple(
    d
    for c, noun in enumerate(QA_CLASSES)
    for d in [(c, None)] + [(c, STATUS_VALUES.index(s)) for s in CLASS_STATUSES[noun]]
)
#: Descriptions of a "thing" by status alone (object questions).
_THINGS: tuple[_Desc, ...] = tuple((None, s) for s in range(len(STATUS_VALUES)))


@dataclass(frozen=True)
class _Objects:
    """The frame's QA-nameable boxes as arrays."""

    cls: np.ndarray  # (N,) index into QA_CLASSES
    status: np.ndarray  # (N,) index into STATUS_VALUES, -1 for none
    relation: np.ndarray  # (N, N) RELATIONS index of object j seen from object i
    vocab: np.ndarray  # (len(_VOCAB), N) which objects each _VOCAB description matches
    things: np.ndarray  # (len(_THINGS), N) likewise for _THINGS

    @classmethod
    def of(cls, frame: FrameAnnotation) -> _Objects:
        boxes = [b for b in frame["boxes"] if b["category"] in QA_CLASS_NAMES]
        xy = np.array([b["center"][:2] for b in boxes], dtype=np.float64).reshape(-1, 2)
        c = np.array([QA_CLASSES.index(QA_CLASS_NAMES[b["category"]]) for b in boxes], dtype=np.int64)
        s = np.array([STATUS_VALUES.index(b["attribute"]) if b["attribute"] else -1 for b in boxes], dtype=np.int64)
        dc = np.array([d[0] for d in _VOCAB])[:, None]
        ds = np.array([-2 if d[1] is None else d[1] for d in _VOCAB])[:, None]
        return cls(
            cls=c,
            status=s,
            relation=spatial_relation(xy[:, None, :], xy[None, :, :]),
            vocab=(dc == c) & ((ds == -2) | (ds == s)),
            things=np.arange(len(_THINGS))[:, None] == s,
        )


def _phrase(desc: _Desc, plural: bool = False) -> str:
    noun = "thing" if desc[0] is None else QA_CLASSES[desc[0]]
    return _noun_phrase(noun, None if desc[1] is None else STATUS_VALUES[desc[1]], plural)


@dataclass(frozen=True)
class _Scope:
    """The objects a question talks about: all (H0) or those in one relation to a reference (H1)."""

    mask: np.ndarray
    clause: str  # "" or " to the front left of the parked truck"


# What an asker returns: a key that is the same for paraphrases of one question (so a
# frame never gets the same question twice in other words), the question, the answer.
_QA = tuple[tuple, str, str]


T = TypeVar("T")


def _pick(rng: np.random.Generator, items: Sequence[T]) -> T:
    return items[int(rng.integers(len(items)))]


def _ask_exist(objs: _Objects, scope: _Scope, rng: np.random.Generator) -> _QA | None:
    counts = objs.vocab[:, scope.mask].sum(axis=1)
    present = [d for d, n in zip(_VOCAB, counts) if n > 0]
    absent = [d for d, n in zip(_VOCAB, counts) if n == 0]
    pool = present if present and (not absent or rng.random() < PRESENT_SHARE) else absent
    desc = _pick(rng, pool)
    if rng.random() < 0.5:
        question = f"Are there any {_phrase(desc, plural=True)}{scope.clause}?"
    else:
        question = f"Is there {_article(_phrase(desc))}{scope.clause}?"
    return ("exist", scope.clause, desc), question, "yes" if desc in present else "no"


def _ask_count(objs: _Objects, scope: _Scope, rng: np.random.Generator) -> _QA | None:
    counts = objs.vocab[:, scope.mask].sum(axis=1)
    some = [(d, n) for d, n in zip(_VOCAB, counts) if 0 < n <= MAX_COUNT_ANSWER]
    none = [(d, n) for d, n in zip(_VOCAB, counts) if n == 0]
    pool = none if none and (not some or rng.random() < ZERO_COUNT_SHARE) else some
    if not pool:
        return None
    desc, n = _pick(rng, pool)
    if rng.random() < 0.5:
        question = f"How many {_phrase(desc, plural=True)} are there{scope.clause}?"
    else:
        question = f"What is the number of {_phrase(desc, plural=True)}{scope.clause}?"
    return ("count", scope.clause, desc), question, str(int(n))


def _ask_object(objs: _Objects, scope: _Scope, rng: np.random.Generator) -> _QA | None:
    hits = objs.things & scope.mask
    options = [(d, int(np.flatnonzero(h)[0])) for d, h in zip(_THINGS, hits) if h.sum() == 1]
    if scope.clause and scope.mask.sum() == 1:
        # "the thing" alone names one object only within a relation holding one object.
        options.append(((None, None), int(np.flatnonzero(scope.mask)[0])))
    if not options:
        return None
    desc, i = _pick(rng, options)
    if rng.random() < 0.5:
        question = f"What is the {_phrase(desc)}{scope.clause}?"
    else:
        question = f"What kind of object is the {_phrase(desc)}{scope.clause}?"
    return ("object", scope.clause, desc), question, QA_CLASSES[objs.cls[i]]


def _unique_of_class(objs: _Objects, mask: np.ndarray) -> dict[int, int]:
    """Class index -> its only object within ``mask``, for classes with exactly one there."""
    members = np.flatnonzero(mask)
    classes, first, counts = np.unique(objs.cls[members], return_index=True, return_counts=True)
    return {int(c): int(members[f]) for c, f, n in zip(classes, first, counts) if n == 1}


def _ask_status(objs: _Objects, scope: _Scope, rng: np.random.Generator) -> _QA | None:
    options = [(c, i) for c, i in _unique_of_class(objs, scope.mask).items() if objs.status[i] >= 0]
    if not options:
        return None
    c, i = _pick(rng, options)
    if rng.random() < 0.5:
        question = f"What status is the {QA_CLASSES[c]}{scope.clause}?"
    else:
        question = f"What is the status of the {QA_CLASSES[c]}{scope.clause}?"
    return ("status", scope.clause, c), question, STATUS_VALUES[objs.status[i]]


def _compare_counts(objs: _Objects, scope: _Scope, rng: np.random.Generator) -> _QA | None:
    counts = objs.vocab[:, scope.mask].sum(axis=1)
    pairs = [
        (a, b)
        for a in range(len(_VOCAB))
        for b in range(len(_VOCAB))
        if _VOCAB[a][0] != _VOCAB[b][0] and counts[a] + counts[b] > 0
    ]
    if not pairs:
        return None
    # Most descriptions are absent from a frame; comparing two present ones half the
    # time keeps "more cars than buses" from being mostly "N vs 0".
    kind = _pick(rng, ["more", "fewer", "same"])
    if kind == "same":
        # Equal non-zero counts are rare by chance; seek them half the time so "yes" occurs.
        preferred = [(a, b) for a, b in pairs if counts[a] == counts[b]]
    else:
        preferred = [(a, b) for a, b in pairs if counts[a] and counts[b]]
    a, b = _pick(rng, preferred if preferred and rng.random() < 0.5 else pairs)
    p1, p2 = _phrase(_VOCAB[a], plural=True), _phrase(_VOCAB[b], plural=True)
    key = ("comparison", scope.clause, kind, _VOCAB[a], _VOCAB[b])
    if kind == "same":
        return (
            key,
            f"Are there the same number of {p1} and {p2}{scope.clause}?",
            "yes" if counts[a] == counts[b] else "no",
        )
    truth = counts[a] > counts[b] if kind == "more" else counts[a] < counts[b]
    return key, f"Are there {kind} {p1} than {p2}{scope.clause}?", "yes" if truth else "no"


def _compare_status(objs: _Objects, scope: _Scope, rng: np.random.Generator) -> _QA | None:
    # The subject is the only one of its class in scope; the other, the only one of its
    # class in the frame, so "the car" and "the bus" each name one object. Classes that
    # share no possible status (a truck and a bicycle) would always answer "no".
    everywhere = _unique_of_class(objs, np.ones(len(objs.cls), dtype=bool))
    pairs = [
        (a, b)
        for ca, a in _unique_of_class(objs, scope.mask).items()
        for cb, b in everywhere.items()
        if ca != cb
        and objs.status[a] >= 0
        and objs.status[b] >= 0
        and set(CLASS_STATUSES[QA_CLASSES[ca]]) & set(CLASS_STATUSES[QA_CLASSES[cb]])
    ]
    if not pairs:
        return None
    a, b = _pick(rng, pairs)
    na, nb = QA_CLASSES[objs.cls[a]], QA_CLASSES[objs.cls[b]]
    question = f"Does the {na}{scope.clause} have the same status as the {nb}?"
    return ("comparison", scope.clause, "status", na, nb), question, "yes" if objs.status[a] == objs.status[b] else "no"


def _ask_comparison(objs: _Objects, scope: _Scope, rng: np.random.Generator) -> _QA | None:
    # Count comparisons are NuScenes-QA's usual kind; status comparisons the minority.
    first, second = (_compare_counts, _compare_status) if rng.random() < 0.75 else (_compare_status, _compare_counts)
    return first(objs, scope, rng) or second(objs, scope, rng)


_ASKERS: dict[str, Callable[[_Objects, _Scope, np.random.Generator], _QA | None]] = {
    "exist": _ask_exist,
    "count": _ask_count,
    "object": _ask_object,
    "status": _ask_status,
    "comparison": _ask_comparison,
}


def _references(objs: _Objects) -> list[tuple[int, _Desc]]:
    """(object, description) for every description in _VOCAB that names exactly one object."""
    unique = np.flatnonzero(objs.vocab.sum(axis=1) == 1)
    return [(int(np.flatnonzero(objs.vocab[v])[0]), _VOCAB[v]) for v in unique]


def _relation_scope(objs: _Objects, ref: int, desc: _Desc, rng: np.random.Generator) -> _Scope:
    others = np.arange(len(objs.cls)) != ref
    rel = int(_pick(rng, np.unique(objs.relation[ref][others]).tolist()))
    mask = (objs.relation[ref] == rel) & others
    return _Scope(mask, f" to the {RELATIONS[rel]} of the {_phrase(desc)}")


def questions_for_frame(frame: FrameAnnotation, rng: np.random.Generator, max_questions: int = 12) -> list[QAQuestion]:
    """Up to ``max_questions`` distinct NuScenes-QA questions about ``frame``, answered from its boxes.

    Each draw picks a template type uniformly, then zero hops (the whole frame) or one hop
    (objects in one RELATIONS sector of a uniquely described reference object, chosen
    among the sectors that hold some object), then a question whose answer is defined:
    "the X" always names exactly one object and counts never exceed MAX_COUNT_ANSWER.
    Deterministic given the state of ``rng``.
    """
    _check_boxes(frame)
    objs = _Objects.of(frame)
    refs = _references(objs) if len(objs.cls) > 1 else []
    everything = _Scope(np.ones(len(objs.cls), dtype=bool), "")
    asked: dict[tuple, QAQuestion] = {}
    for _ in range(ATTEMPTS_PER_QUESTION * max_questions):
        if len(asked) >= max_questions:
            break
        kind = _pick(rng, list(TEMPLATE_TYPES))
        hop: Literal[0, 1] = 1 if refs and rng.integers(2) == 1 else 0
        scope = _relation_scope(objs, *_pick(rng, refs), rng) if hop else everything
        qa = _ASKERS[kind](objs, scope, rng)
        if qa is None or qa[0] in asked:
            continue
        key, question, answer = qa
        asked[key] = QAQuestion(
            question=question, answer=answer, sample_token=frame["token"], template_type=kind, num_hop=hop
        )
    return list(asked.values())


# ---------------------------------------------------------------- caption


def _groups(boxes: list, classes: tuple[str, ...]) -> list[tuple[int, str]]:
    """(count, '3 moving cars') per (class, status) group of the boxes of ``classes``, largest first."""
    keys = [(b["category"], b["attribute"] or None) for b in boxes if b["category"] in classes]
    order = {c: i for i, c in enumerate(CLASS_NAMES)}
    tally = sorted(
        {k: keys.count(k) for k in keys}.items(),
        key=lambda kv: (-kv[1], order[kv[0][0]], STATUS_VALUES.index(kv[0][1]) if kv[0][1] else -1),
    )
    return [(n, _counted(n, _NOUNS[c], s)) for (c, s), n in tally]


def _describe(box, definite: bool) -> str:
    """'a parked car 12 m ahead on the left' / 'the ...'."""
    phrase = _noun_phrase(_NOUNS[box["category"]], box["attribute"] or None, plural=False)
    xy = np.asarray(box["center"][:2], dtype=np.float64)
    where = f"{np.hypot(*xy):.0f} m {_POSITION_WORDS[_sector8(xy)]}"
    return f"{'the ' + phrase if definite else _article(phrase)} {where}"


def _ego_motion(frame: FrameAnnotation) -> str:
    meta, speed = frame["meta_action"], frame["ego_speed"]
    if speed <= STOP_SPEED:
        return f"{EGO_MOTION_OPENING} stopped" + (" and about to pull away" if meta["speed"] == "accelerate" else "")
    if meta["direction"] == "stop":
        return f"{EGO_MOTION_OPENING} coming to a stop from {speed:.0f} m/s"
    motion = (
        f"{EGO_MOTION_OPENING} {_CAPTION_MOTION[meta['direction']]} at {speed:.0f} m/s{_CAPTION_SPEED[meta['speed']]}"
    )
    turn = frame["command"].removeprefix("turn ")
    if frame["command"] != "go straight" and turn not in meta["direction"]:
        motion += f" before a {turn} turn"
    return motion


def caption_for_frame(frame: FrameAnnotation) -> str:
    """One or two sentences: the ego's motion and nearby vehicles, then everything else.

    Counts are exact per (class, status) group; the nearest pedestrian or cyclist in the
    ego's lane ahead (|y| <= LANE_HALF_WIDTH, 0 < x <= LANE_LOOKAHEAD) is pointed out.
    """
    _check_boxes(frame)
    _check_meta(frame)
    boxes = frame["boxes"]
    vehicles = [text for _, text in _groups(boxes, VEHICLE_CLASSES)]
    first = _ego_motion(frame) + (
        f", with {_join(vehicles)} nearby." if vehicles else ", with no other vehicles nearby."
    )
    rest = _groups(boxes, tuple(c for c in CLASS_NAMES[:11] if c not in VEHICLE_CLASSES))
    if not rest:
        return first
    verb = "is" if sum(n for n, _ in rest) == 1 else "are"
    second = f"{_join([text for _, text in rest])} {verb} also around"
    vulnerable = [b for b in boxes if b["category"] in ("pedestrian", "bicycle", "motorcycle")]
    in_lane = [b for b in vulnerable if _in_lane_ahead(np.asarray(b["center"][:2], dtype=np.float64))]
    if in_lane:
        nearest = min(in_lane, key=lambda b: b["center"][0])
        second += f"; {_describe(nearest, definite=True)} is in the ego's lane"
    return f"{first} {second[0].upper()}{second[1:]}."


# ---------------------------------------------------------------- narration


def _surroundings(frame: FrameAnnotation) -> str:
    boxes = sorted(frame["boxes"], key=lambda b: float(np.hypot(b["center"][0], b["center"][1])))
    if not boxes:
        return "Surroundings: no other road users or objects are around the ego car."
    listed = "; ".join(_describe(b, definite=False) for b in boxes[:NARRATED_OBJECTS])
    more = f" ({len(boxes)} objects in total)" if len(boxes) > NARRATED_OBJECTS else ""
    return f"Surroundings: {listed}{more}."


def _ego_plan_points(frame: FrameAnnotation) -> np.ndarray:
    mask = np.asarray(frame["ego_future_mask"], dtype=bool)
    return np.asarray(frame["ego_future"], dtype=np.float64).reshape(-1, 2)[mask]


def _movers(frame: FrameAnnotation) -> str:
    boxes, futures, masks = frame["boxes"], frame["agent_futures"], frame["agent_future_mask"]
    if len(futures) != len(boxes) or len(masks) != len(boxes):
        raise DataError(f"{_where(frame)}: agent_futures/agent_future_mask need one entry per box ({len(boxes)})")
    ego_mask = np.asarray(frame["ego_future_mask"], dtype=bool)
    ego_future = np.asarray(frame["ego_future"], dtype=np.float64).reshape(-1, 2)
    found = []
    for box, fut, mask in zip(boxes, futures, masks):
        valid = np.flatnonzero(mask)
        if len(valid) == 0:
            continue
        path = np.asarray(fut, dtype=np.float64).reshape(-1, 2)
        last = valid[-1]
        shift = path[last] - np.asarray(box["center"][:2], dtype=np.float64)
        horizon = (last + 1) * FRAME_DT
        if np.hypot(*shift) / horizon < MOVER_MIN_SPEED:
            continue
        heading = _HEADING_WORDS[_sector8(shift)]
        text = f"{_describe(box, definite=True)} will move {np.hypot(*shift):.0f} m {heading} in {horizon:g} s"
        both = np.asarray(mask, dtype=bool) & ego_mask
        if both.any() and np.hypot(*(path[both] - ego_future[both]).T).min() < CONFLICT_DISTANCE:
            text += " and come close to the ego's planned path"
        found.append((float(np.hypot(box["center"][0], box["center"][1])), text))
    if not found:
        return "Movement: nothing around is expected to move much in the next few seconds."
    found.sort(key=lambda f: f[0])
    listed = "; ".join(t for _, t in found[:NARRATED_MOVERS])
    more = f" ({len(found)} moving agents in total)" if len(found) > NARRATED_MOVERS else ""
    return f"Movement: {listed}{more}."


def _plan(frame: FrameAnnotation) -> str:
    points = _ego_plan_points(frame)
    route = f"the route says to {frame['command']}"
    if len(points) == 0:
        return f"Plan: {route}; the rest of the trajectory is unknown, so the ego car should keep its current motion."
    horizon = len(points) * FRAME_DT
    length = float(np.hypot(*np.diff(np.vstack([[0.0, 0.0], points]), axis=0).T).sum())
    if length / horizon <= STOP_SPEED:
        action = f"the ego car should stay stopped for the next {horizon:g} s"
    else:
        lateral = points[-1, 1]
        side = (
            f", ending {abs(lateral):.1f} m to the {'left' if lateral > 0 else 'right'}" if abs(lateral) >= 0.5 else ""
        )
        action = (
            f"the ego car should cover about {length:.0f} m in the next {horizon:g} s "
            f"(average {length / horizon:.0f} m/s, now {frame['ego_speed']:.0f} m/s){side}"
        )
    ahead = [b for b in frame["boxes"] if _in_lane_ahead(np.asarray(b["center"][:2], dtype=np.float64))]
    gap = ""
    if ahead:
        lead = min(ahead, key=lambda b: b["center"][0])
        gap = f", keeping a safe gap to {_describe(lead, definite=True)}"
    return f"Plan: {route}; {action}{gap}."


def narration_for_frame(frame: FrameAnnotation) -> str:
    """Chain-of-thought in four lines: surroundings, movers, the ego's plan, the meta action.

    Surroundings list the NARRATED_OBJECTS nearest boxes with distance and direction;
    movers are agents whose future (``agent_futures``, up to 3 s) averages at least
    MOVER_MIN_SPEED, flagged when they come within CONFLICT_DISTANCE of the ego's planned
    position at the same step; the plan comes from ``ego_future`` and ``command``; the
    last line is :func:`format_meta_action`, which :func:`parse_meta_action` reads back.
    """
    _check_boxes(frame)
    _check_meta(frame)
    parts = [_surroundings(frame), _movers(frame), _plan(frame), format_meta_action(frame["meta_action"])]
    return "\n".join(parts)


__all__ = [
    "ANSWERS",
    "CLASS_STATUSES",
    "QA_CLASS_NAMES",
    "RELATIONS",
    "TEMPLATE_TYPES",
    "caption_for_frame",
    "narration_for_frame",
    "questions_for_frame",
    "spatial_relation",
]
