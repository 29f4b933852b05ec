"""Constants shared by every stage: actions, state keys, grid, target categories.

Conventions follow AI2-THOR (DESIGN.md, "The offline dataset"): y is up; rotation 0 faces +z and 90
faces +x; RotateRight adds 45 degrees, RotateLeft subtracts 45; a positive horizon looks down.
"""

from __future__ import annotations

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
    "AlarmClock", "Book", "Bowl", "CellPhone", "Chair", "CoffeeMachine", "DeskLamp", "FloorLamp",
    "Fridge", "GarbageCan", "Kettle", "Laptop", "LightSwitch", "Microwave", "Pan", "Plate", "Pot",
    "RemoteControl", "Sink", "StoveBurner", "Television", "Toaster",
)
NUM_CATEGORIES = len(TARGET_CATEGORIES)
CATEGORY_INDEX = {c: i for i, c in enumerate(TARGET_CATEGORIES)}

ROOM_TYPES = ("kitchen", "living_room", "bedroom", "bathroom")

#: Per-room-type target sets: 15 / 10 / 8 / 3 categories, whose union is the 22 classes; exactly the targets
#: that occur in the lineage's 22-class test splits (``test_val_split/{room}_test_22.pkl``).
ROOM_TARGETS = {
    "kitchen": ("Bowl", "CellPhone", "Chair", "CoffeeMachine", "Fridge", "GarbageCan", "Kettle", "LightSwitch",
                "Microwave", "Pan", "Plate", "Pot", "Sink", "StoveBurner", "Toaster"),
    "living_room": ("Book", "CellPhone", "Chair", "DeskLamp", "FloorLamp", "GarbageCan", "Laptop",
                    "LightSwitch", "RemoteControl", "Television"),
    "bedroom": ("AlarmClock", "Book", "CellPhone", "Chair", "DeskLamp", "GarbageCan", "Laptop",
                "LightSwitch"),
    "bathroom": ("GarbageCan", "LightSwitch", "Sink"),
}


def room_target_mask(room_type: str) -> np.ndarray:
    """``(22,)`` bool: the classes :data:`ROOM_TARGETS` allows as targets in a room of ``room_type``; every class
    when the room type is unknown (no restriction)."""
    if room_type not in ROOM_TARGETS:
        return np.ones(NUM_CATEGORIES, dtype=bool)
    mask = np.zeros(NUM_CATEGORIES, dtype=bool)
    mask[[CATEGORY_INDEX[c] for c in ROOM_TARGETS[room_type]]] = True
    return mask


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
    return (table[:, 0].astype(np.float32), table[:, 1].astype(np.float32),
            np.round(table[:, 2]).astype(np.int16) % 360, np.round(table[:, 3]).astype(np.int16))
