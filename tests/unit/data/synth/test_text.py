"""The synthetic world's text: NuScenes-QA questions, captions and narrations from hand-built frames.

Every answer is checked against truth computed here, independently of the module: the
question text is parsed back with this file's own regexes and answered by plain loops
over the boxes, with the relation rule of ``spatial_relation``'s docstring re-implemented
as an if-chain.
"""

from __future__ import annotations

import itertools
import json
import math
import re

import numpy as np
import pytest

from occtrain.data.schema import META_DIRECTIONS, META_SPEEDS
from occtrain.data.synth.text import (
    ANSWERS,
    RELATIONS,
    TEMPLATE_TYPES,
    caption_for_frame,
    narration_for_frame,
    questions_for_frame,
    spatial_relation,
)
from occtrain.data.text_formats import caption_surroundings, format_meta_action, parse_meta_action
from occtrain.errors import DataError

# ---------------------------------------------------------------- hand-built frames


def box(cat: str, x: float, y: float, attr: str = "", vx: float = 0.0, vy: float = 0.0) -> dict:
    return {
        "track_id": 0,
        "category": cat,
        "center": [x, y, 0.8],
        "size": [4.0, 1.9, 1.6],
        "yaw": 0.0,
        "velocity": [vx, vy],
        "attribute": attr,
    }


def make_frame(
    boxes: list[dict],
    *,
    token: str = "tok0",
    speed: float = 8.0,
    command: str = "go straight",
    meta: tuple[str, str] = ("maintain", "straight"),
    ego_future: list | None = None,
) -> dict:
    """A frame whose agents keep their velocity for 3 s and whose ego drives along +x at ``speed``."""
    for i, b in enumerate(boxes):
        b["track_id"] = i
    steps = np.arange(1, 7) * 0.5
    futures = [(np.asarray(b["center"][:2]) + np.outer(steps, b["velocity"])).tolist() for b in boxes]
    return {
        "scene": "scene-test",
        "token": token,
        "index": 0,
        "timestamp": 0,
        "ego_pose": {"translation": [0.0, 0.0, 0.0], "yaw": 0.0},
        "ego_speed": speed,
        "ego_accel": 0.0,
        "ego_yaw_rate": 0.0,
        "command": command,
        "meta_action": {"speed": meta[0], "direction": meta[1]},
        "ego_future": ego_future if ego_future is not None else [[speed * t, 0.0] for t in steps],
        "ego_future_mask": [1] * 6,
        "ego_past": [[-speed * t, 0.0] for t in (2.0, 1.5, 1.0, 0.5)],
        "ego_past_mask": [1] * 4,
        "boxes": boxes,
        "agent_futures": futures,
        "agent_future_mask": [[1] * 6 for _ in boxes],
        "caption": "",
        "narration": "",
    }


STATUSES_OF = {
    "car": ["moving", "parked", "stopped"],
    "truck": ["moving", "parked", "stopped"],
    "bus": ["moving", "parked", "stopped"],
    "trailer": ["moving", "parked", "stopped"],
    "construction_vehicle": ["moving", "parked", "stopped"],
    "pedestrian": ["moving", "standing"],
    "bicycle": ["with rider", "without rider"],
    "motorcycle": ["with rider", "without rider"],
    "barrier": [""],
    "traffic_cone": [""],
    "others": [""],
}


def random_frame(seed: int) -> dict:
    """A crowded random frame; cars are often more than 10, to exercise the count cap."""
    rng = np.random.default_rng(seed)
    boxes = []
    for cat, statuses in STATUSES_OF.items():
        n = int(rng.integers(0, 14 if cat == "car" else 4))
        for _ in range(n):
            x, y = rng.uniform(-39, 39, size=2)
            boxes.append(box(cat, float(x), float(y), str(rng.choice(statuses)), *rng.uniform(-3, 3, size=2)))
    return make_frame(boxes, token=f"tok{seed}")


def rich_frame() -> dict:
    return make_frame(
        [
            box("car", 12, 0.5, "moving", 5, 0),
            box("car", -10, 3.5, "parked"),
            box("car", 30, 6, "parked"),
            box("truck", 20, -6, "parked"),
            box("pedestrian", 8, 5, "moving", 0, -1.4),
            box("pedestrian", 9, 8, "standing"),
            box("traffic_cone", 15, -2),
            box("traffic_cone", 16, -2.5),
            box("bus", -25, -3.5, "moving", 8, 0),
            box("bicycle", 5, -8, "with rider", 4, 0),
            box("others", 2, 9),
        ]
    )


# ---------------------------------------------------------------- independent truth


def hand_relation(ref: tuple[float, float], target: tuple[float, float]) -> str:
    """The documented sector rule, written out as comparisons."""
    ang = math.degrees(math.atan2(target[1] - ref[1], target[0] - ref[0]))
    if -30 <= ang < 30:
        return "front"
    if 30 <= ang < 90:
        return "front left"
    if 90 <= ang < 150:
        return "back left"
    if -90 <= ang < -30:
        return "front right"
    if -150 <= ang < -90:
        return "back right"
    return "back"


NOUNS = {
    "car": "car",
    "cars": "car",
    "truck": "truck",
    "trucks": "truck",
    "bus": "bus",
    "buses": "bus",
    "trailer": "trailer",
    "trailers": "trailer",
    "construction vehicle": "construction_vehicle",
    "construction vehicles": "construction_vehicle",
    "pedestrian": "pedestrian",
    "pedestrians": "pedestrian",
    "bicycle": "bicycle",
    "bicycles": "bicycle",
    "motorcycle": "motorcycle",
    "motorcycles": "motorcycle",
    "barrier": "barrier",
    "barriers": "barrier",
    "traffic cone": "traffic_cone",
    "traffic cones": "traffic_cone",
    "thing": None,
}
RIDER = {
    "with a rider": "with rider",
    "with riders": "with rider",
    "without a rider": "without rider",
    "without riders": "without rider",
}
REL = r"(?: to the (front left|front right|back left|back right|front|back) of the (.+?))?"


def parse_noun(phrase: str) -> tuple[str | None, str | None]:
    """'parked cars' -> ('car', 'parked'); 'thing with a rider' -> (None, 'with rider')."""
    status = None
    for words, value in RIDER.items():
        if phrase.endswith(" " + words):
            phrase, status = phrase[: -len(words) - 1], value
    first, _, rest = phrase.partition(" ")
    if first in ("moving", "parked", "stopped", "standing"):
        phrase, status = rest, first
    assert phrase in NOUNS, f"unknown noun phrase {phrase!r}"
    return NOUNS[phrase], status


class Truth:
    """Answers a question from the frame's boxes, asserting every 'the X' names one object."""

    def __init__(self, frame: dict):
        self.objects = [b for b in frame["boxes"] if b["category"] != "others"]

    def matches(self, objs, desc):
        cat, status = desc
        return [
            o for o in objs if (cat is None or o["category"] == cat) and (status is None or o["attribute"] == status)
        ]

    def the(self, objs, desc):
        found = self.matches(objs, desc)
        assert len(found) == 1, f"{desc} names {len(found)} objects"
        return found[0]

    def scope(self, rel, ref_phrase):
        if rel is None:
            return self.objects
        ref = self.the(self.objects, parse_noun(ref_phrase))
        r = tuple(ref["center"][:2])
        return [o for o in self.objects if o is not ref and hand_relation(r, tuple(o["center"][:2])) == rel]

    def answer(self, q: dict) -> str:
        text, kind = q["question"], q["template_type"]
        patterns = {
            "exist": [rf"Are there any (.+?){REL}\?", rf"Is there an? (.+?){REL}\?"],
            "count": [rf"How many (.+?) are there{REL}\?", rf"What is the number of (.+?){REL}\?"],
            "object": [rf"What is the (.+?){REL}\?", rf"What kind of object is the (.+?){REL}\?"],
            "status": [rf"What status is the (.+?){REL}\?", rf"What is the status of the (.+?){REL}\?"],
        }
        if kind in patterns:
            m = next((m for p in patterns[kind] if (m := re.fullmatch(p, text))), None)
            assert m, f"{kind} question in no known form: {text}"
            noun, rel, ref = m.groups()
            assert (rel is not None) == (q["num_hop"] == 1), text
            scope = self.scope(rel, ref)
            desc = parse_noun(noun)
            if kind == "exist":
                return "yes" if self.matches(scope, desc) else "no"
            if kind == "count":
                n = len(self.matches(scope, desc))
                assert n <= 10, f"count question answered {n}: {text}"
                return str(n)
            found = self.the(scope, desc)
            return found["category"].replace("_", " ") if kind == "object" else found["attribute"]
        if m := re.fullmatch(rf"Are there (more|fewer) (.+?) than (.+?){REL}\?", text):
            which, a, b, rel, ref = m.groups()
            scope = self.scope(rel, ref)
            na, nb = len(self.matches(scope, parse_noun(a))), len(self.matches(scope, parse_noun(b)))
            return "yes" if (na > nb if which == "more" else na < nb) else "no"
        if m := re.fullmatch(rf"Are there the same number of (.+?) and (.+?){REL}\?", text):
            a, b, rel, ref = m.groups()
            scope = self.scope(rel, ref)
            return "yes" if len(self.matches(scope, parse_noun(a))) == len(self.matches(scope, parse_noun(b))) else "no"
        m = re.fullmatch(rf"Does the (.+?){REL} have the same status as the (.+?)\?", text)
        assert m and kind == "comparison", f"question in no known form: {text}"
        a, rel, ref, b = m.groups()
        first = self.the(self.scope(rel, ref), parse_noun(a))
        second = self.the(self.objects, parse_noun(b))
        assert first is not second
        return "yes" if first["attribute"] == second["attribute"] else "no"


# ---------------------------------------------------------------- questions


def test_relation_sectors_of_hand_placed_points():
    ref = (10.0, 0.0)
    cases = {
        (20.0, 1.0): "front",  # 5.7 deg
        (12.0, 5.0): "front left",  # 68 deg
        (5.0, 3.0): "back left",  # 149 deg
        (0.0, 0.0): "back",  # 180 deg
        (0.0, -1.0): "back",  # -174 deg
        (8.0, -5.0): "back right",  # -112 deg
        (15.0, -4.0): "front right",  # -39 deg
        (10.0, 1.0): "back left",  # exactly 90: lower bounds are included
        (10.0, -1.0): "front right",  # exactly -90
        (11.0, 0.0): "front",  # exactly 0
    }
    for target, expected in cases.items():
        assert RELATIONS[int(spatial_relation(ref, target))] == expected, target
    # Broadcast form agrees with the scalar one.
    got = spatial_relation(np.array(ref), np.array(list(cases)))
    assert [RELATIONS[i] for i in got] == list(cases.values())


def test_every_answer_matches_independent_truth_on_random_frames():
    kinds, hops, exist_answers = set(), set(), []
    for seed in range(25):
        frame = random_frame(seed)
        questions = questions_for_frame(frame, np.random.default_rng(seed), max_questions=30)
        assert questions
        truth = Truth(frame)
        for q in questions:
            assert q["answer"] == truth.answer(q), q
            kinds.add(q["template_type"])
            hops.add(q["num_hop"])
            if q["template_type"] == "exist":
                exist_answers.append(q["answer"])
    assert kinds == set(TEMPLATE_TYPES)
    assert hops == {0, 1}
    share_yes = exist_answers.count("yes") / len(exist_answers)
    assert 0.3 < share_yes < 0.7, share_yes


def test_question_records_are_nuscenes_qa_json():
    frame = rich_frame()
    questions = questions_for_frame(frame, np.random.default_rng(3))
    assert 0 < len(questions) <= 12
    assert len({q["question"] for q in questions}) == len(questions)
    for q in questions:
        assert set(q) == {"question", "answer", "sample_token", "template_type", "num_hop"}
        assert isinstance(q["question"], str) and q["question"].endswith("?")
        assert isinstance(q["answer"], str) and q["answer"] in ANSWERS
        assert q["sample_token"] == "tok0"
        assert q["template_type"] in TEMPLATE_TYPES
        assert type(q["num_hop"]) is int and q["num_hop"] in (0, 1)
    doc = {"info": {"split": "train"}, "questions": questions}
    assert json.loads(json.dumps(doc)) == doc


def test_answer_vocabulary_uses_nuscenes_qa_wording():
    words = {str(n) for n in range(11)} | {"yes", "no"}
    words |= {
        "car",
        "truck",
        "bus",
        "trailer",
        "construction vehicle",
        "pedestrian",
        "motorcycle",
        "bicycle",
        "traffic cone",
        "barrier",
        "moving",
        "parked",
        "stopped",
        "standing",
        "with rider",
        "without rider",
    }
    assert set(ANSWERS) == words


def test_hand_placed_relations_to_a_unique_truck():
    # The parked truck is the only truck; targets sit at hand-computed angles from it.
    frame = make_frame(
        [
            box("truck", 0, 0, "parked"),
            box("pedestrian", 10, 5, "moving", 1, 0),  # 26.6 deg: front
            box("pedestrian", 5, 10, "standing"),  # 63.4 deg: front left
            box("pedestrian", -10, 2, "moving", 1, 0),  # 168.7 deg: back
            box("car", 3, -9, "parked"),  # -71.6 deg: front right
        ]
    )
    pedestrians = {"front": 1, "front left": 1, "back": 1}
    cars = {"front right": 1}
    seen = 0
    for seed in range(60):
        for q in questions_for_frame(frame, np.random.default_rng(seed), max_questions=30):
            m = re.fullmatch(
                r"How many (pedestrians|cars) are there to the (.+) of the (parked truck|truck)\?", q["question"]
            )
            if m:
                table = pedestrians if m.group(1) == "pedestrians" else cars
                assert q["answer"] == str(table.get(m.group(2), 0)), q
                assert q["num_hop"] == 1
                seen += 1
            m = re.fullmatch(r"What status is the pedestrian to the (.+) of the (parked truck|truck)\?", q["question"])
            if m:
                assert q["answer"] == {"front": "moving", "front left": "standing", "back": "moving"}[m.group(1)]
                seen += 1
    assert seen >= 3


def test_ambiguous_references_and_large_counts_are_never_asked():
    # Two parked cars (never "the parked car"), one moving car, twelve pedestrians.
    boxes = [box("car", 10, 2, "parked"), box("car", -12, 3, "parked"), box("car", 20, 0, "moving", 6, 0)]
    boxes += [box("pedestrian", -30 + 5 * i, 12, "standing") for i in range(12)]
    frame = make_frame(boxes)
    for seed in range(40):
        for q in questions_for_frame(frame, np.random.default_rng(seed), max_questions=30):
            text = q["question"]
            assert "the parked car" not in text, text
            if q["num_hop"] == 0:
                assert "the car" not in text and "the pedestrian" not in text, text
            assert "standing thing" not in text or q["num_hop"] == 1, text
            if q["template_type"] == "count":
                assert int(q["answer"]) <= 10
                assert not re.fullmatch(
                    r"(How many|What is the number of) (standing )?pedestrians( are there)?\?", text
                )
            assert q["answer"] == Truth(frame).answer(q)


def test_questions_are_deterministic_given_the_rng():
    frame = random_frame(7)
    a = questions_for_frame(frame, np.random.default_rng(11))
    b = questions_for_frame(frame, np.random.default_rng(11))
    c = questions_for_frame(frame, np.random.default_rng(12))
    assert a == b
    assert a != c


def test_empty_frame_asks_only_about_absence():
    frame = make_frame([])
    questions = questions_for_frame(frame, np.random.default_rng(0))
    assert questions
    for q in questions:
        assert q["num_hop"] == 0
        assert q["template_type"] in ("exist", "count")
        assert q["answer"] in ("no", "0")


def test_unknown_category_or_attribute_is_a_data_error():
    with pytest.raises(DataError, match="box 0 has category 'tram'"):
        questions_for_frame(make_frame([box("tram", 5, 0)]), np.random.default_rng(0))
    with pytest.raises(DataError, match="box 0 has attribute 'flying'"):
        questions_for_frame(make_frame([box("car", 5, 0, "flying")]), np.random.default_rng(0))
    with pytest.raises(DataError, match="meta_action"):
        narration_for_frame(make_frame([], meta=("hover", "straight")))


# ---------------------------------------------------------------- caption


def caption_counts(caption: str) -> dict[str, int]:
    return {
        m.group(2): int(m.group(1))
        for m in re.finditer(r"(\d+) ([a-z][a-z ]*?)(?=,| and | nearby| is | are )", caption)
    }


def test_caption_counts_every_group_exactly():
    boxes = [box("car", 12 + 8 * i, 0.3, "moving", 7, 0) for i in range(3)]
    boxes += [box("truck", -15, 6, "parked"), box("truck", 25, -7, "parked")]
    boxes += [box("pedestrian", 9, 1.0, "moving", 0, 1.2), box("pedestrian", 5, 9, "moving", 1, 0)]
    boxes += [box("pedestrian", -6, -9, "moving", 1, 0), box("pedestrian", 3, 10, "standing")]
    caption = caption_for_frame(make_frame(boxes, meta=("maintain", "straight")))
    assert caption.startswith("The ego car is driving straight at 8 m/s, with ")
    assert caption_counts(caption.split(";")[0]) == {
        "moving cars": 3,
        "parked trucks": 2,
        "moving pedestrians": 3,
        "standing pedestrian": 1,
    }
    # The moving pedestrian at (9, 1) is inside the lane (|y| <= 1.8) ahead.
    assert "the moving pedestrian 9 m ahead is in the ego's lane" in caption
    assert caption.count(".") == 2


def test_caption_of_a_stopped_ego_with_no_vehicles():
    frame = make_frame([box("traffic_cone", 6, 3)], speed=0.0, meta=("accelerate", "stop"), command="turn left")
    caption = caption_for_frame(frame)
    assert caption == (
        "The ego car is stopped and about to pull away, with no other vehicles nearby. 1 traffic cone is also around."
    )


def test_caption_names_the_coming_turn_and_speed_change():
    frame = make_frame([], speed=6.0, meta=("decelerate", "straight"), command="turn right")
    assert caption_for_frame(frame) == (
        "The ego car is driving straight at 6 m/s and slowing down before a right turn, with no other vehicles nearby."
    )


def test_caption_surroundings_drop_the_ego_motion_and_keep_the_rest():
    # The same frames as above: every caption opening with the ego's motion loses exactly it.
    stopped = caption_for_frame(make_frame([box("traffic_cone", 6, 3)], speed=0.0, meta=("accelerate", "stop")))
    assert caption_surroundings(stopped) == "Nearby: no other vehicles. 1 traffic cone is also around."
    turning = caption_for_frame(
        make_frame(
            [box("car", 12, 0.3, "moving", 7, 0)], speed=6.0, meta=("decelerate", "straight"), command="turn right"
        )
    )
    assert caption_surroundings(turning) == "Nearby: 1 moving car."
    # Captions that do not open with the ego (real data) pass through unchanged.
    assert (
        caption_surroundings("A wet road with two buses. A cyclist waits.")
        == "A wet road with two buses. A cyclist waits."
    )


# ---------------------------------------------------------------- narration


def test_meta_action_round_trips_for_every_pair():
    for speed, direction in itertools.product(META_SPEEDS, META_DIRECTIONS):
        meta = {"speed": speed, "direction": direction}
        assert parse_meta_action("Some reasoning.\n" + format_meta_action(meta)) == meta
    assert format_meta_action({"speed": "decelerate", "direction": "left"}) == "Meta action: decelerate, turn left."
    # Against the last past meta action: an equal one is "as before", read back as it.
    last = {"speed": "decelerate", "direction": "left"}
    assert format_meta_action(last, previous=last) == "Meta action: as before."
    assert (
        format_meta_action({"speed": "maintain", "direction": "left"}, previous=last)
        == "Meta action: maintain speed, turn left."
    )
    assert parse_meta_action("History: ... Meta action: As before.", last) == last
    assert parse_meta_action("Meta action: as before.") is None  # nothing to repeat
    assert parse_meta_action("meta action: Maintain Speed, bear right.  ") == {
        "speed": "maintain",
        "direction": "bear right",
    }
    # The last one wins (a model may revise itself); unparseable text gives None.
    two = "Meta action: accelerate, go straight. On reflection: Meta action: decelerate, stop."
    assert parse_meta_action(two) == {"speed": "decelerate", "direction": "stop"}
    assert parse_meta_action("Meta action: accelerate, go straight") == {"speed": "accelerate", "direction": "straight"}
    assert parse_meta_action("Meta action: slow down, turn left.") is None
    assert parse_meta_action("Meta action: accelerate, turn leftwards.") is None
    assert parse_meta_action("") is None


def test_narration_has_four_parts_and_ends_with_the_meta_action():
    frame = make_frame(
        [
            box("pedestrian", 10, 4, "moving", 0, -1.2),  # crosses toward the ego's path
            box("car", 20, 0, "moving", 8, 0),  # leads in the ego's lane
            box("car", -8, 5, "parked"),
        ],
        meta=("decelerate", "left"),
        command="turn left",
    )
    lines = narration_for_frame(frame).split("\n")
    assert [line.split(":")[0] for line in lines] == ["Surroundings", "Movement", "Plan", "Meta action"]
    assert lines[-1] == "Meta action: decelerate, turn left."
    assert parse_meta_action("\n".join(lines)) == frame["meta_action"]
    # Nearest first: the pedestrian at 10.8 m (21.8 deg: ahead), then the parked car (9.4 m is nearer).
    assert lines[0] == (
        "Surroundings: a parked car 9 m behind on the left; a moving pedestrian 11 m ahead; a moving car 20 m ahead."
    )
    # Pedestrian: 3.6 m toward -y over 3 s; at step 3 it is at (10, 2.2), 2.97 m from the ego at (12, 0).
    assert (
        "the moving pedestrian 11 m ahead will move 4 m to the right in 3 s and come close to the ego's planned path"
        in lines[1]
    )
    assert "the moving car 20 m ahead will move 24 m forward in 3 s" in lines[1]
    assert "parked car" not in lines[1]
    assert lines[2] == (
        "Plan: the route says to turn left; the ego car should cover about 24 m in the next 3 s "
        "(average 8 m/s, now 8 m/s), keeping a safe gap to the moving car 20 m ahead."
    )


def test_narration_of_a_stopped_ego_in_an_empty_scene():
    frame = make_frame([], speed=0.0, meta=("maintain", "stop"), ego_future=[[0.0, 0.0]] * 6)
    assert narration_for_frame(frame) == "\n".join(
        [
            "Surroundings: no other road users or objects are around the ego car.",
            "Movement: nothing around is expected to move much in the next few seconds.",
            "Plan: the route says to go straight; the ego car should stay stopped for the next 3 s.",
            "Meta action: maintain speed, stop.",
        ]
    )
