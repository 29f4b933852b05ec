"""Constants shared by every stage: actions, state keys, grid, target categories.

Conventions follow AI2-THOR (DESIGN.md, "The offline dataset"): y is up; rotation 0 faces +z and 90
faces +x; RotateRight adds 45 degrees, RotateLeft subtracts 45; a positive horizon looks down.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

#: Grid step of reachable positions, metres.
GRID_SIZE = 0.25
#: Rotation step, degrees (RotateLeft / RotateRight).
ROTATE_STEP = 45
ROTATIONS = tuple(range(0, 360, ROTATE_STEP))  # 0, 45, ..., 315
#: Camera horizons, degrees; positive looks down. LookDown goes 0 -> 30, LookUp 30 -> 0.
HORIZONS = (0, 30)
#: Horizontal field of view of the agent camera, degrees.
FIELD_OF_VIEW = 90.0
#: Camera height above the floor, metres.
CAMERA_HEIGHT = 1.5


def camera_height_of(meta: dict) -> float:
    """The camera height a scene was rendered from: its ``scene.json``'s ``camera.height`` (:data:`CAMERA_HEIGHT`
    when it records none: every scene built before the height was recorded)."""
    return float((meta.get("camera") or {}).get("height", CAMERA_HEIGHT))


#: AI2-THOR's visibility distance used by `visible_object_map_1.5.json`, metres.
VISIBILITY_DISTANCE = 1.5
#: Success distance of the paper (section III-A), metres.
SUCCESS_DISTANCE = 1.0
#: C_target, the stage-switch threshold on the target confidence (paper III-B "Dividing point", IV-A: 0.7).
C_TARGET = 0.7

#: The action space of the paper (section III-A), in this order everywhere (array index = action id). The order
#: is the lineage's (IOM ``utils/action_util.py``): 0 MoveAhead, 1 RotateLeft, 2 RotateRight, 3 LookUp,
#: 4 LookDown, 5 Done, so action ids in tsnav's files and the lineage's ``optimal_action.json`` agree.
ACTIONS = ("MoveAhead", "RotateLeft", "RotateRight", "LookUp", "LookDown", "Done")
MOVE_AHEAD, ROTATE_LEFT, ROTATE_RIGHT, LOOK_UP, LOOK_DOWN, DONE = range(6)
NUM_ACTIONS = len(ACTIONS)
#: The order as one string, stored with every file that holds action ids (trained runs, trajectories).
ACTION_ORDER = ",".join(ACTIONS)
#: The order tsnav used before it followed the lineage (LookDown and LookUp swapped); files that carry no
#: ``action_order`` were written in it.
OLD_ACTION_ORDER = "MoveAhead,RotateLeft,RotateRight,LookDown,LookUp,Done"


def action_permutation(order: str) -> np.ndarray:
    """Index array ``p`` with ``new_id = p[old_id]`` for ids written in ``order`` (a comma-separated list of
    action names); ``ValueError`` naming the order when it is not a permutation of :data:`ACTIONS`."""
    names = [a.strip() for a in str(order).split(",")]
    if sorted(names) != sorted(ACTIONS):
        raise ValueError(f"unknown action order {order!r}; expected the six actions {ACTION_ORDER}")
    return np.array([ACTIONS.index(a) for a in names], dtype=np.int64)


def object_id(object_type: str, x: float, y: float, z: float) -> str:
    """An object id as AI2-THOR formats it: ``Plate|+00.52|+00.92|+03.73`` (sign, at least two integer digits,
    two decimals; ``-10.25`` stays ``-10.25``). Rounding to 0 keeps a + sign (``+00.00``)."""

    def f(v: float) -> str:
        v = round(float(v), 2) + 0.0  # no negative zero
        return f"{v:+06.2f}"

    return f"{object_type}|{f(x)}|{f(y)}|{f(z)}"


#: The 22 AI2-THOR target classes of the lineage's DETR detector (DESIGN.md, "Detector").
TARGET_CATEGORIES = (
    "AlarmClock",
    "Book",
    "Bowl",
    "CellPhone",
    "Chair",
    "CoffeeMachine",
    "DeskLamp",
    "FloorLamp",
    "Fridge",
    "GarbageCan",
    "Kettle",
    "Laptop",
    "LightSwitch",
    "Microwave",
    "Pan",
    "Plate",
    "Pot",
    "RemoteControl",
    "Sink",
    "StoveBurner",
    "Television",
    "Toaster",
)
NUM_CATEGORIES = len(TARGET_CATEGORIES)
CATEGORY_INDEX = {c: i for i, c in enumerate(TARGET_CATEGORIES)}

ROOM_TYPES = ("kitchen", "living_room", "bedroom", "bathroom")

#: Per-room-type target sets: 15 / 10 / 8 / 3 categories, whose union is the 22 classes; exactly the targets
#: that occur in the lineage's 22-class test splits (``test_val_split/{room}_test_22.pkl``).
ROOM_TARGETS = {
    "kitchen": (
        "Bowl",
        "CellPhone",
        "Chair",
        "CoffeeMachine",
        "Fridge",
        "GarbageCan",
        "Kettle",
        "LightSwitch",
        "Microwave",
        "Pan",
        "Plate",
        "Pot",
        "Sink",
        "StoveBurner",
        "Toaster",
    ),
    "living_room": (
        "Book",
        "CellPhone",
        "Chair",
        "DeskLamp",
        "FloorLamp",
        "GarbageCan",
        "Laptop",
        "LightSwitch",
        "RemoteControl",
        "Television",
    ),
    "bedroom": ("AlarmClock", "Book", "CellPhone", "Chair", "DeskLamp", "GarbageCan", "Laptop", "LightSwitch"),
    "bathroom": ("GarbageCan", "LightSwitch", "Sink"),
}

#: The 12 target types of the RoboTHOR ObjectNav challenge (``../shared/robothor/README.md``), sorted.
ROBOTHOR_CATEGORIES = (
    "AlarmClock",
    "Apple",
    "BaseballBat",
    "BasketBall",
    "Bowl",
    "GarbageCan",
    "HousePlant",
    "Laptop",
    "Mug",
    "SprayBottle",
    "Television",
    "Vase",
)


@dataclass(frozen=True)
class ClassSet:
    """A named list of target classes: the columns of every per-category table (success masks, distance fields,
    detection tables) and the target ids of episodes and agents are indices into :attr:`categories`.

    A scene folder declares its class set in ``scene.json`` (``"class_set"``; absent means :data:`ITHOR22`, the
    setting of every folder written before class sets existed); detection tables, detectors and agent
    checkpoints record the one they were made for, and a mismatch is refused in one line
    (:func:`check_same_class_set`).
    """

    name: str
    categories: tuple[str, ...]
    room_targets: dict = field(default_factory=dict, compare=False, hash=False)
    """Per-room-type target lists (the lineage's, for ``ithor22``); a room type not listed allows every class."""

    @property
    def size(self) -> int:
        return len(self.categories)

    @cached_property
    def index(self) -> dict[str, int]:
        """Category name -> column."""
        return {c: i for i, c in enumerate(self.categories)}

    def room_target_mask(self, room_type: str) -> np.ndarray:
        """``(size,)`` bool: the classes allowed as targets in a room of ``room_type`` (all when it has no list)."""
        if room_type not in self.room_targets:
            return np.ones(self.size, dtype=bool)
        idx = self.index
        mask = np.zeros(self.size, dtype=bool)
        mask[[idx[c] for c in self.room_targets[room_type]]] = True
        return mask


#: iTHOR's 22 classes (the lineage's and the paper's AI2-Thor setting; the default everywhere).
ITHOR22 = ClassSet("ithor22", TARGET_CATEGORIES, ROOM_TARGETS)
#: The RoboTHOR challenge's 12 target types (its apartments have no room types: every class is a target).
ROBOTHOR12 = ClassSet("robothor12", ROBOTHOR_CATEGORIES)
CLASS_SETS = {c.name: c for c in (ITHOR22, ROBOTHOR12)}
DEFAULT_CLASS_SET = ITHOR22.name


def class_set(name: "str | ClassSet | None") -> ClassSet:
    """The :class:`ClassSet` called ``name`` (None: the default, ``ithor22``); ``ValueError`` in one line when
    unknown."""
    if isinstance(name, ClassSet):
        return name
    if name is None:
        return ITHOR22
    if name not in CLASS_SETS:
        raise ValueError(f"unknown class set {name!r} (choose from {', '.join(CLASS_SETS)})")
    return CLASS_SETS[name]


def class_set_of(meta: dict | None) -> ClassSet:
    """The class set recorded in a file's metadata (``"class_set"``); absent means ``ithor22``."""
    return class_set((meta or {}).get("class_set") or DEFAULT_CLASS_SET)


def check_same_class_set(have: "str | ClassSet", need: "str | ClassSet", what: str, where: str) -> None:
    """``ValueError`` in one line when ``what`` (made for ``have``) is used on ``where`` (of ``need``)."""
    a, b = class_set(have).name, class_set(need).name
    if a != b:
        raise ValueError(
            f"{what} is for class set {a} but {where} uses {b} (class sets must match: "
            f"{class_set(a).size} vs {class_set(b).size} target classes)"
        )


def room_target_mask(room_type: str, classes: "str | ClassSet | None" = None) -> np.ndarray:
    """``(C,)`` bool: the classes the class set's room lists (:data:`ROOM_TARGETS` for ``ithor22``) allow as
    targets in a room of ``room_type``; every class when the room type is unknown (no restriction)."""
    return class_set(classes).room_target_mask(room_type)


def state_key(x: float, z: float, rotation: int, horizon: int) -> str:
    """The lineage's state key, e.g. ``0.50|3.50|315|30`` (x, z in metres; degrees)."""
    return f"{x:.2f}|{z:.2f}|{int(rotation) % 360:d}|{int(horizon):d}"


def parse_state_key(key: str) -> tuple[float, float, int, int]:
    """Inverse of :func:`state_key`; raises ``ValueError`` naming the key when malformed."""
    parts = key.split("|")
    if len(parts) != 4:
        raise ValueError(f"malformed state key {key!r}: expected 'x|z|rotation|horizon'")
    try:
        return float(parts[0]), float(parts[1]), int(round(float(parts[2]))), int(round(float(parts[3])))
    except ValueError:
        raise ValueError(f"malformed state key {key!r}: fields must be numbers") from None


def parse_state_keys(keys) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vectorised :func:`parse_state_key` over many keys: ``(x, z, rotation, horizon)`` arrays."""
    arr = np.asarray(keys, dtype=str)
    if arr.size == 0:
        e = np.zeros(0)
        return e.astype(np.float32), e.astype(np.float32), e.astype(np.int16), e.astype(np.int16)
    parts = np.char.split(arr, "|")
    try:
        table = np.array(parts.tolist(), dtype=np.float64)
    except ValueError:
        bad = [k for k, p in zip(arr.tolist(), parts.tolist()) if len(p) != 4][:1]
        raise ValueError(f"malformed state key {bad[0] if bad else '?'!r}: expected 'x|z|rotation|horizon'") from None
    if table.ndim != 2 or table.shape[1] != 4:
        raise ValueError("malformed state keys: expected 'x|z|rotation|horizon'")
    return (
        table[:, 0].astype(np.float32),
        table[:, 1].astype(np.float32),
        np.round(table[:, 2]).astype(np.int16) % 360,
        np.round(table[:, 3]).astype(np.int16),
    )
