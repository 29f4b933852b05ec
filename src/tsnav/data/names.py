"""AI2-THOR's scene names and the lineage's splits (used by every producer of scene folders).

* kitchens ``FloorPlan1``-``30``, living rooms ``FloorPlan201``-``230``, bedrooms ``301``-``330``,
  bathrooms ``401``-``430``; numbers 1-20 train, odd 21-29 val, even 22-30 test;
* apartments ``FloorPlan_Train{1..12}_{1..5}`` (train) and ``FloorPlan_Val{1..3}_{1..5}`` (val).
"""

from __future__ import annotations

import re

from ..constants import ROOM_TYPES

#: First FloorPlan number minus one of each iTHOR room type.
ITHOR_BASE = {"kitchen": 0, "living_room": 200, "bedroom": 300, "bathroom": 400}


def ithor_scenes(room_type: str | None = None, split: str | None = None) -> list[str]:
    """iTHOR single-room scene names, optionally of one room type and one split."""
    out = []
    for t in ROOM_TYPES if room_type is None else (room_type,):
        for i in range(1, 31):
            if split is None or ithor_split(i) == split:
                out.append(f"FloorPlan{ITHOR_BASE[t] + i}")
    return out


def ithor_split(i: int) -> str:
    """Split of the ``i``-th scene (1..30) of a room type."""
    return "train" if i <= 20 else ("val" if i % 2 == 1 else "test")


def robothor_scenes(split: str | None = None) -> list[str]:
    """RoboTHOR-like apartment scene names, optionally of one split."""
    out = []
    if split in (None, "train"):
        out += [f"FloorPlan_Train{a}_{b}" for a in range(1, 13) for b in range(1, 6)]
    if split in (None, "val"):
        out += [f"FloorPlan_Val{a}_{b}" for a in range(1, 4) for b in range(1, 6)]
    return out


def scene_info(name: str) -> tuple[str, str]:
    """``(room_type, split)`` of a scene name; ``ValueError`` for names that are not scenes of this world."""
    m = re.fullmatch(r"FloorPlan(\d+)", name)
    if m:
        n = int(m.group(1))
        for t, base in ITHOR_BASE.items():
            if base + 1 <= n <= base + 30:
                return t, ithor_split(n - base)
    m = re.fullmatch(r"FloorPlan_(Train|Val)(\d+)_(\d+)", name)
    if m:
        a, b = int(m.group(2)), int(m.group(3))
        if 1 <= b <= 5 and ((m.group(1) == "Train" and 1 <= a <= 12) or (m.group(1) == "Val" and 1 <= a <= 3)):
            return "apartment", m.group(1).lower()
    raise ValueError(
        f"unknown scene name {name!r} (expected FloorPlan1-30, 201-230, 301-330, 401-430, "
        f"FloorPlan_Train1-12_1-5 or FloorPlan_Val1-3_1-5)"
    )


def scene_base_name(name: str) -> str:
    """``FloorPlan24_physics`` -> ``FloorPlan24``: the scene name without the ``_physics`` suffix of the lineage's
    folder names and AI2-THOR's metadata files (the episode lists and tsnav's folders do not carry it)."""
    return name.removesuffix("_physics")


def lineage_scene_info(name: str) -> tuple[str, str | None]:
    """Room type and split of an AI2-THOR scene name (``FloorPlan1`` or the lineage's ``FloorPlan1_physics``);
    ``("unknown", None)`` for other names."""
    try:
        return scene_info(scene_base_name(name))
    except ValueError:
        return "unknown", None
