"""nuScenes' categories and attributes in occtrain's terms, and back.

A box's category is one of Occ3D's object classes (``formats.occ3d.CLASS_NAMES[:11]``).
nuScenes' 23 annotation categories map onto them as nuScenes-lidarseg's 16-class challenge
mapping does (Occ3D-nuScenes labels its voxels from lidarseg): the categories that mapping
leaves out of every class (animals, personal mobility, strollers, wheelchairs, debris,
pushable-pullable objects, bicycle racks, ambulances and police vehicles) are Occ3D's
``others``. A nuScenes attribute is written without its prefix (``vehicle.parked`` ->
``parked``, ``cycle.with_rider`` -> ``with rider``); ``pedestrian.sitting_lying_down``, which
the NuScenes-QA status vocabulary does not hold, is ``standing`` (a pedestrian not moving).
"""

from __future__ import annotations

from occtrain.data.schema import STATUS_VALUES
from occtrain.formats.occ3d import CLASS_NAMES

#: nuScenes category -> Occ3D class name.
CATEGORY_TO_CLASS: dict[str, str] = {
    "animal": "others",
    "human.pedestrian.adult": "pedestrian",
    "human.pedestrian.child": "pedestrian",
    "human.pedestrian.construction_worker": "pedestrian",
    "human.pedestrian.personal_mobility": "others",
    "human.pedestrian.police_officer": "pedestrian",
    "human.pedestrian.stroller": "others",
    "human.pedestrian.wheelchair": "others",
    "movable_object.barrier": "barrier",
    "movable_object.debris": "others",
    "movable_object.pushable_pullable": "others",
    "movable_object.trafficcone": "traffic_cone",
    "static_object.bicycle_rack": "others",
    "vehicle.bicycle": "bicycle",
    "vehicle.bus.bendy": "bus",
    "vehicle.bus.rigid": "bus",
    "vehicle.car": "car",
    "vehicle.construction": "construction_vehicle",
    "vehicle.emergency.ambulance": "others",
    "vehicle.emergency.police": "others",
    "vehicle.motorcycle": "motorcycle",
    "vehicle.trailer": "trailer",
    "vehicle.truck": "truck",
}
#: Occ3D class -> the nuScenes category an export writes for it (the commonest of its kind).
CLASS_TO_CATEGORY: dict[str, str] = {
    "others": "movable_object.debris",
    "barrier": "movable_object.barrier",
    "bicycle": "vehicle.bicycle",
    "bus": "vehicle.bus.rigid",
    "car": "vehicle.car",
    "construction_vehicle": "vehicle.construction",
    "motorcycle": "vehicle.motorcycle",
    "pedestrian": "human.pedestrian.adult",
    "traffic_cone": "movable_object.trafficcone",
    "trailer": "vehicle.trailer",
    "truck": "vehicle.truck",
}
assert set(CLASS_TO_CATEGORY) == set(CLASS_NAMES[:11])
assert all(CATEGORY_TO_CLASS[c] == k for k, c in CLASS_TO_CATEGORY.items())

#: nuScenes' eight attributes.
ATTRIBUTES = (
    "cycle.with_rider",
    "cycle.without_rider",
    "pedestrian.moving",
    "pedestrian.sitting_lying_down",
    "pedestrian.standing",
    "vehicle.moving",
    "vehicle.parked",
    "vehicle.stopped",
)
#: nuScenes' visibility levels by token: the share of the object visible in the six cameras.
VISIBILITY_LEVELS = {"1": "v0-40", "2": "v40-60", "3": "v60-80", "4": "v80-100"}


def box_class(category: str) -> str | None:
    """The Occ3D class of a nuScenes category; None for a category nuScenes does not define."""
    if category in CATEGORY_TO_CLASS:
        return CATEGORY_TO_CLASS[category]
    return None


def status(attribute: str) -> str:
    """The Status of a nuScenes attribute name (see the module docstring)."""
    word = attribute.split(".", 1)[-1].replace("_", " ")
    if word == "sitting lying down":
        return "standing"
    return word if word in STATUS_VALUES else ""


def attribute_name(status_value: str, category: str) -> str | None:
    """The nuScenes attribute an export writes for a box's Status (None for "")."""
    if not status_value:
        return None
    if status_value in ("with rider", "without rider"):
        return f"cycle.{status_value.replace(' ', '_')}"
    if category.startswith("human.") and status_value in ("moving", "standing"):
        return f"pedestrian.{status_value}"
    if status_value == "standing":
        return "pedestrian.standing"
    return f"vehicle.{status_value}"
