"""The declared types of the dataset's JSON files, checked on reading by :mod:`occtrain.data.validate`.

FrameAnnotation is the per-frame record that the synthetic world writes and every reader
returns; QAQuestion is NuScenes-QA's; Occ3DAnnotations is Occ3D's ``annotations.json``. A
real Occ3D-nuScenes directory supplies the occupancy and ego poses; everything else here
comes from occtrain's sidecar files (``occtrain/<scene>.json``), which real data may lack.
All coordinates are metres in the *current* ego frame (x forward, y left) unless a field
says "global". Yaw is in radians, counter-clockwise from +x.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal, NotRequired, TypedDict, get_args

from occtrain.data.validate import Len
from occtrain.formats.nuscenes_qa import TemplateType
from occtrain.formats.occ3d import CLASS_NAMES, FUTURE_STEPS, PAST_STEPS

# Each closed vocabulary is a Literal (the schema checks it) and a tuple of its values (code iterates it).

#: High-level driving command, as in ST-P3 / UniAD: the lateral offset of a point 3 s ahead
#: against COMMAND_LATERAL_THRESHOLD. The synthetic world (dataset and closed loop alike)
#: takes that point on the route at the current speed (``data/synth/road_context.py``,
#: ``route_command``); an import of a real release, which has no route, takes the logged
#: future pose, as ST-P3 does (``data.geometry.driving_command``).
Command = Literal["turn right", "turn left", "go straight"]
COMMANDS: tuple[str, ...] = get_args(Command)
COMMAND_LATERAL_THRESHOLD = 2.0  # metres of lateral offset at +3 s

#: OccVLA meta actions: a speed part and a direction part.
MetaSpeed = Literal["accelerate", "decelerate", "maintain"]
MetaDirection = Literal["straight", "left", "right", "bear left", "bear right", "stop"]
META_SPEEDS: tuple[str, ...] = get_args(MetaSpeed)
META_DIRECTIONS: tuple[str, ...] = get_args(MetaDirection)
#: |longitudinal acceleration| below this (m/s^2, averaged over the next 1 s) is "maintain".
META_ACCEL_THRESHOLD = 0.5
#: Ego speed (m/s) at or below which the ego is "stopped".
STOP_SPEED = 0.3

#: NuScenes-QA status answers (nuScenes attribute names without their prefix).
Status = Literal["moving", "parked", "stopped", "standing", "with rider", "without rider"]
STATUS_VALUES: tuple[str, ...] = get_args(Status)

#: NuScenes-QA question template types (the vocabulary lives in occtrain.formats.nuscenes_qa).
TEMPLATE_TYPES: tuple[TemplateType, ...] = get_args(TemplateType)

#: Box categories: the Occ3D object classes (CLASS_NAMES[0:11]), built from occ3d's list
#: so the two cannot drift. A static type checker cannot evaluate that Literal: to it a
#: category is a string; the schema check reads the Literal.
if TYPE_CHECKING:
    Category = str
else:
    Category = Literal[CLASS_NAMES[:11]]

#: A traffic light's state as the ego sees it: amber is the last AMBER seconds of green.
LightState = Literal["green", "amber", "red"]
LIGHT_STATES: tuple[str, ...] = get_args(LightState)

#: The road context (``RoadContext``): arc lengths (m) along the route, from the ego's
#: projection on it, of the centreline points ``route`` holds (0, 2.5, ..., 60).
ROUTE_ARC: tuple[float, ...] = tuple(2.5 * k for k in range(25))
#: How fast an ego's sideways offset from its route fades (s) in a label or a prior laid
#: along the route: the expert's label from an ego off its lane returns to the lane this way
#: (not a jump onto it), and a planning head's route prior keeps the ego's offset this way.
LATERAL_DECAY_S = 1.0
#: How far along the route (m) the road context looks for curvature, a lead vehicle and a stop line.
ROAD_REACH = 60.0
#: The pedestrian corridor: this far along the route (m) and this far either side of its centreline.
PEDESTRIAN_REACH = 40.0
PEDESTRIAN_CORRIDOR = 3.0

#: nuScenes' visibility levels of an annotated object (percent of it visible in the cameras).
Visibility = Literal["v0-40", "v40-60", "v60-80", "v80-100"]

Vec2 = Annotated[list[float], Len(2)]
Vec3 = Annotated[list[float], Len(3)]
Quaternion = Annotated[list[float], Len(4)]  # w, x, y, z, as nuScenes stores rotations
Flag = Literal[0, 1]


# ----------------------------------------------------------------------------- occtrain's sidecar


class EgoPose(TypedDict):
    translation: Vec3  # global [x, y, z]
    yaw: float  # global heading


class MetaAction(TypedDict):
    speed: MetaSpeed
    direction: MetaDirection


class Box(TypedDict):
    track_id: int  # stable across the frames of a scene
    category: Category
    center: Vec3  # [x, y, z], ego frame
    size: Vec3  # [length, width, height]
    yaw: float  # ego frame
    velocity: Vec2  # [vx, vy] m/s, ego frame
    attribute: Status | Literal[""]  # "" for static objects (barrier, cone)
    #: nuScenes' visibility level (share visible in the six cameras), where a release gives it.
    visibility: NotRequired[Visibility]


class LeadVehicle(TypedDict):
    """The vehicle the ego follows: the nearest vehicle or cycle whose centre lies on the route
    ahead (0 < its arc length from the ego's projection <= ROAD_REACH), whose box overlaps the
    ego's sideways (|offset from the centreline| < (ego width + its width) / 2 + 0.2 m) and
    which heads the route's way there (cos of the angle > 0.5): the synthetic expert's leader
    test (``MoverTraffic.advance``), measured along the route instead of the ego's axis."""

    gap: float  # m along the route, the ego's front bumper to the lead's rear (ego length / 2 + its length / 2 off)
    speed: float  # m/s along the route (its speed x cos of its heading against the route's)


class CorridorAgent(TypedDict):
    """The nearest pedestrian in the route's corridor: 0 <= arc length from the ego's projection
    <= PEDESTRIAN_REACH and |offset| <= PEDESTRIAN_CORRIDOR."""

    distance: float  # m along the route from the ego's projection to its centre's
    offset: float  # m left of the centreline (negative: right)
    speed: float  # m/s, its own (any direction)


class StopLine(TypedDict):
    """The route's next stop line: the first that the ego's front bumper has not passed by more
    than 0.5 m (the expert still stops for it), if it lies within ROAD_REACH."""

    distance: float  # m along the route from the ego's front bumper, as the expert measures its line gap
    light: LightState  # red when green_left < 0, amber when it is below AMBER (3 s), else green
    green_left: float  # s until the light turns red (amber included), -1 while red (roads.green_left's convention)


class RoadContext(TypedDict):
    """What a map and a tracker tell a planner about the road ahead of the frame. The route is
    the one the ego follows; every distance along it is measured from the ego's projection
    on it (the ego's own arc length when it drives on it). Ego frame, metres, m/s."""

    route: Annotated[list[Vec2], Len(len(ROUTE_ARC))]  # centreline points at ROUTE_ARC, current ego frame
    curvature: float  # the largest |curvature| (1/m) of the route in the next ROAD_REACH m
    lead: LeadVehicle | None
    pedestrian: CorridorAgent | None
    stop_line: StopLine | None


class FrameAnnotation(TypedDict):
    scene: str
    token: str  # sample token, unique in the dataset
    index: int  # position of the frame in its scene
    timestamp: int  # microseconds
    ego_pose: EgoPose
    ego_speed: float  # m/s
    ego_accel: float  # m/s^2, longitudinal
    ego_yaw_rate: float  # rad/s
    command: Command
    meta_action: MetaAction
    ego_future: Annotated[list[Vec2], Len(FUTURE_STEPS)]  # [x, y] per step
    ego_future_mask: Annotated[list[Flag], Len(FUTURE_STEPS)]  # 1 where the waypoint exists (scene end cuts it)
    ego_past: Annotated[list[Vec2], Len(PAST_STEPS)]  # oldest first
    ego_past_mask: Annotated[list[Flag], Len(PAST_STEPS)]
    boxes: list[Box]  # agents and objects inside the grid's x-y range
    agent_futures: list[Annotated[list[Vec2], Len(FUTURE_STEPS)]]  # per box, current ego frame
    agent_future_mask: list[Annotated[list[Flag], Len(FUTURE_STEPS)]]  # per box
    #: The route ahead, the lead vehicle, the pedestrian in the corridor and the next stop
    #: line (synthetic world v6 on, in the dataset and the closed loop alike); absent on real
    #: data (a map and a tracker would give it) and on older worlds: every reader copes.
    road: NotRequired[RoadContext]
    caption: str
    narration: str  # chain-of-thought: surroundings -> movers -> ego plan -> meta action


class QAQuestion(TypedDict):
    """One question in NuScenes-QA's own JSON format."""

    question: str
    answer: str
    sample_token: str
    template_type: TemplateType
    num_hop: Literal[0, 1]


class QAFile(TypedDict):
    """``nuscenes_qa/NuScenes_<split>_questions.json`` (NuScenes-QA also stores an ``info`` object)."""

    questions: list[QAQuestion]


# ----------------------------------------------------------------------------- Occ3D's annotations.json
# As the Occ3D-nuScenes release documents it; occtrain reads the samples' order, ego poses
# and ground-truth paths. Camera records are checked when present but never needed.


class Occ3DPose(TypedDict):
    translation: Vec3
    rotation: Quaternion


class Occ3DCamera(TypedDict):
    # Two forms: the Occ3D README documents records keyed by camera token with ``intrinsic``
    # and ``img_path`` relative to the root; the released files key them by channel
    # (CAM_FRONT, ...) with ``intrinsics`` and ``img_path`` relative to ``imgs/``. Both read.
    img_path: str
    intrinsic: NotRequired[Annotated[list[Vec3], Len(3)]]
    intrinsics: NotRequired[Annotated[list[Vec3], Len(3)]]
    extrinsic: Occ3DPose
    ego_pose: Occ3DPose


class Occ3DSample(TypedDict):
    # Documented as "timestamp (or token), unique by sample": a string, of digits in the
    # release; occtrain's writer stores an int. Numeric ones are microseconds.
    timestamp: int | str
    ego_pose: Occ3DPose
    camera_sensor: NotRequired[dict[str, Occ3DCamera]]
    gt_path: NotRequired[str]  # relative to the root; the test split has none
    prev: NotRequired[str]  # "" (or absent) at the scene's ends
    next: NotRequired[str]


class Occ3DAnnotations(TypedDict):
    train_split: NotRequired[list[str]]
    val_split: NotRequired[list[str]]
    scene_infos: dict[str, dict[str, Occ3DSample]]  # scene name -> sample token -> sample
