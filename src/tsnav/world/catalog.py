"""Furniture and object models: sizes (metres) and shapes made of boxes, in AI2-THOR's image.

A model is a list of local boxes ``(center, size, material_role)`` with the object's base at y = 0, its
front facing local +z. Sizes are drawn per instance within plausible ranges; materials come from
per-category palettes with per-instance variation, so that seeing an object is a perception problem
rather than a colour lookup.
"""

from __future__ import annotations

import math

import numpy as np

from .spec import CHECKER, PLAIN, SPECKLE, STRIPES, TILES, WOOD, Part

# ---------------------------------------------------------------------------------------------- sizes
#: (width x, height y, depth z) ranges in metres: ((min...), (max...)).
FURNITURE_SIZES = {
    "CounterTop": ((1.2, 0.9, 0.6), (2.6, 0.92, 0.7)),
    "Cabinet": ((0.8, 0.9, 0.5), (1.4, 0.92, 0.6)),
    "Stove": ((0.7, 0.9, 0.6), (0.8, 0.92, 0.65)),
    "DiningTable": ((1.0, 0.75, 0.8), (1.8, 0.78, 1.1)),
    "KitchenIsland": ((1.2, 0.9, 0.7), (2.0, 0.92, 0.9)),
    "ShelvingUnit": ((0.8, 1.6, 0.35), (1.4, 2.0, 0.45)),
    "Sofa": ((1.8, 0.85, 0.85), (2.4, 0.9, 0.95)),
    "ArmChair": ((0.75, 0.85, 0.75), (0.9, 0.9, 0.85)),
    "CoffeeTable": ((0.8, 0.4, 0.5), (1.3, 0.45, 0.7)),
    "TVStand": ((1.2, 0.5, 0.4), (1.8, 0.6, 0.5)),
    "SideTable": ((0.4, 0.55, 0.4), (0.55, 0.7, 0.55)),
    "Desk": ((1.0, 0.74, 0.55), (1.5, 0.76, 0.7)),
    "Bed": ((1.4, 0.55, 1.9), (1.8, 0.6, 2.1)),
    "Dresser": ((0.9, 0.8, 0.45), (1.4, 1.0, 0.55)),
    "Wardrobe": ((0.9, 2.0, 0.55), (1.3, 2.1, 0.6)),
    "Toilet": ((0.4, 0.75, 0.65), (0.45, 0.8, 0.7)),
    "Bathtub": ((1.5, 0.55, 0.7), (1.7, 0.6, 0.8)),
    "Vanity": ((0.7, 0.85, 0.45), (1.2, 0.88, 0.55)),
}

OBJECT_SIZES = {
    "AlarmClock": ((0.12, 0.1, 0.07), (0.18, 0.14, 0.09)),
    "Book": ((0.15, 0.04, 0.22), (0.2, 0.06, 0.28)),
    "Bowl": ((0.14, 0.07, 0.14), (0.2, 0.09, 0.2)),
    "CellPhone": ((0.07, 0.012, 0.14), (0.08, 0.015, 0.16)),
    "Chair": ((0.42, 0.9, 0.45), (0.5, 1.0, 0.5)),
    "CoffeeMachine": ((0.2, 0.35, 0.25), (0.3, 0.42, 0.32)),
    "DeskLamp": ((0.15, 0.4, 0.15), (0.2, 0.5, 0.2)),
    "FloorLamp": ((0.3, 1.5, 0.3), (0.4, 1.75, 0.4)),
    "Fridge": ((0.7, 1.75, 0.7), (0.85, 1.9, 0.75)),
    "GarbageCan": ((0.28, 0.4, 0.28), (0.36, 0.55, 0.36)),
    "Kettle": ((0.16, 0.2, 0.16), (0.2, 0.25, 0.2)),
    "Laptop": ((0.32, 0.22, 0.22), (0.36, 0.25, 0.25)),
    "LightSwitch": ((0.08, 0.12, 0.02), (0.1, 0.14, 0.03)),
    "Microwave": ((0.45, 0.28, 0.35), (0.55, 0.32, 0.4)),
    "Pan": ((0.26, 0.05, 0.26), (0.3, 0.06, 0.3)),
    "Plate": ((0.22, 0.02, 0.22), (0.27, 0.025, 0.27)),
    "Pot": ((0.22, 0.16, 0.22), (0.28, 0.2, 0.28)),
    "RemoteControl": ((0.05, 0.025, 0.17), (0.06, 0.03, 0.2)),
    "Sink": ((0.45, 0.06, 0.38), (0.6, 0.08, 0.45)),
    "StoveBurner": ((0.2, 0.02, 0.2), (0.24, 0.025, 0.24)),
    "Television": ((0.8, 0.5, 0.08), (1.2, 0.75, 0.1)),
    "Toaster": ((0.25, 0.18, 0.15), (0.3, 0.2, 0.18)),
}

# ------------------------------------------------------------------------------------------- palettes
#: role -> list of (base colour, pattern, pattern scale, second colour offset)
PALETTES = {
    "wood": [
        ((0.55, 0.38, 0.22), WOOD),
        ((0.42, 0.28, 0.16), WOOD),
        ((0.7, 0.55, 0.38), WOOD),
        ((0.3, 0.2, 0.13), WOOD),
        ((0.82, 0.72, 0.58), WOOD),
    ],
    "painted": [
        ((0.92, 0.92, 0.9), PLAIN),
        ((0.25, 0.3, 0.38), PLAIN),
        ((0.6, 0.68, 0.62), PLAIN),
        ((0.75, 0.62, 0.5), PLAIN),
        ((0.35, 0.35, 0.36), PLAIN),
        ((0.88, 0.85, 0.78), SPECKLE),
    ],
    "stone": [
        ((0.85, 0.85, 0.83), SPECKLE),
        ((0.2, 0.2, 0.22), SPECKLE),
        ((0.6, 0.55, 0.5), SPECKLE),
        ((0.9, 0.88, 0.82), PLAIN),
    ],
    "fabric": [
        ((0.45, 0.5, 0.58), PLAIN),
        ((0.62, 0.3, 0.28), PLAIN),
        ((0.3, 0.45, 0.35), STRIPES),
        ((0.7, 0.65, 0.55), CHECKER),
        ((0.2, 0.22, 0.3), PLAIN),
        ((0.8, 0.75, 0.6), STRIPES),
    ],
    "metal": [
        ((0.75, 0.76, 0.78), PLAIN),
        ((0.55, 0.56, 0.58), PLAIN),
        ((0.15, 0.15, 0.16), PLAIN),
        ((0.85, 0.84, 0.8), PLAIN),
    ],
    "plastic": [
        ((0.9, 0.9, 0.9), PLAIN),
        ((0.12, 0.12, 0.13), PLAIN),
        ((0.8, 0.2, 0.18), PLAIN),
        ((0.2, 0.45, 0.75), PLAIN),
        ((0.95, 0.8, 0.25), PLAIN),
        ((0.3, 0.65, 0.4), PLAIN),
    ],
    "ceramic": [
        ((0.95, 0.95, 0.93), PLAIN),
        ((0.85, 0.9, 0.95), PLAIN),
        ((0.9, 0.82, 0.7), PLAIN),
        ((0.35, 0.45, 0.6), PLAIN),
        ((0.7, 0.3, 0.25), PLAIN),
    ],
    "screen": [((0.03, 0.03, 0.05), PLAIN), ((0.05, 0.07, 0.12), PLAIN)],
    "paper": [
        ((0.8, 0.15, 0.15), STRIPES),
        ((0.15, 0.3, 0.7), STRIPES),
        ((0.2, 0.55, 0.3), STRIPES),
        ((0.9, 0.75, 0.3), STRIPES),
        ((0.4, 0.2, 0.5), STRIPES),
    ],
    "lamp": [((0.98, 0.95, 0.8), PLAIN), ((0.95, 0.9, 0.7), PLAIN), ((0.9, 0.92, 0.95), PLAIN)],
    "bedding": [
        ((0.92, 0.92, 0.95), PLAIN),
        ((0.55, 0.65, 0.8), STRIPES),
        ((0.85, 0.75, 0.7), CHECKER),
        ((0.5, 0.55, 0.45), PLAIN),
    ],
}
WALLS = [
    ((0.93, 0.91, 0.86), PLAIN),
    ((0.82, 0.86, 0.88), PLAIN),
    ((0.9, 0.84, 0.74), SPECKLE),
    ((0.72, 0.78, 0.7), PLAIN),
    ((0.95, 0.95, 0.95), TILES),
    ((0.85, 0.8, 0.85), STRIPES),
    ((0.68, 0.6, 0.55), PLAIN),
]
FLOORS = [
    ((0.6, 0.45, 0.3), WOOD),
    ((0.45, 0.33, 0.22), WOOD),
    ((0.8, 0.8, 0.78), TILES),
    ((0.35, 0.35, 0.37), TILES),
    ((0.7, 0.68, 0.6), CHECKER),
    ((0.55, 0.5, 0.48), SPECKLE),
    ((0.76, 0.62, 0.45), WOOD),
]


def material(rng: np.random.Generator, role: str):
    """A (colour, colour2, pattern, scale) drawn from ``role``'s palette with per-instance jitter."""
    base, pattern = PALETTES[role][rng.integers(len(PALETTES[role]))]
    return jitter(rng, base, pattern)


def jitter(rng: np.random.Generator, base, pattern):
    c = np.clip(np.asarray(base) * rng.uniform(0.85, 1.15) + rng.normal(0, 0.03, 3), 0, 1)
    c2 = np.clip(c * rng.uniform(0.6, 0.85), 0, 1) if pattern != PLAIN else c
    scale = {
        PLAIN: 1.0,
        STRIPES: rng.uniform(0.04, 0.12),
        CHECKER: rng.uniform(0.05, 0.3),
        WOOD: rng.uniform(0.03, 0.08),
        TILES: rng.uniform(0.2, 0.5),
        SPECKLE: rng.uniform(0.01, 0.03),
    }[pattern]
    return tuple(float(v) for v in c), tuple(float(v) for v in c2), int(pattern), float(scale)


def draw_size(rng: np.random.Generator, table: dict, category: str) -> tuple[float, float, float]:
    lo, hi = table[category]
    return tuple(float(round(rng.uniform(a, b), 3)) for a, b in zip(lo, hi))


# ---------------------------------------------------------------------------------------------- shapes
def _box(cx, cy, cz, sx, sy, sz, role):
    return ((cx, cy, cz), (sx, sy, sz), role)


def shape(category: str, size, rng: np.random.Generator) -> list:
    """Local boxes of one model: base at y = 0, front towards local +z; ``role`` names a material slot.
    ``rng`` is not drawn from (the shapes are fixed by the size)."""
    w, h, d = size
    return SHAPES.get(category, _block)(category, w, h, d)


# ---- furniture
def _table(category, w, h, d):
    leg, top = 0.05, 0.04
    out = [_box(0, h - top / 2, 0, w, top, d, "main")]
    for sx in (-1, 1):
        for sz in (-1, 1):
            out.append(_box(sx * (w / 2 - leg), (h - top) / 2, sz * (d / 2 - leg), leg, h - top, leg, "main"))
    if category == "Desk":
        out.append(_box(w / 2 - 0.22, (h - top) / 2, 0, 0.4, h - top, d - 0.05, "main"))
    return out


def _chair(category, w, h, d):
    seat = 0.46
    out = [
        _box(0, seat - 0.025, 0, w, 0.05, d, "main"),
        _box(0, (seat + h) / 2, -d / 2 + 0.03, w, h - seat, 0.05, "main"),
    ]
    for sx in (-1, 1):
        for sz in (-1, 1):
            out.append(_box(sx * (w / 2 - 0.03), seat / 2, sz * (d / 2 - 0.03), 0.04, seat, 0.04, "main"))
    return out


def _sofa(category, w, h, d):
    arm = 0.18
    return [
        _box(0, 0.22, 0.05, w, 0.44, d - 0.1, "main"),
        _box(0, h / 2, -d / 2 + 0.1, w, h, 0.2, "main"),
        _box(-w / 2 + arm / 2, 0.3, 0.0, arm, 0.6, d, "main"),
        _box(w / 2 - arm / 2, 0.3, 0.0, arm, 0.6, d, "main"),
        _box(0, 0.47, 0.08, w - 2 * arm, 0.08, d - 0.3, "accent"),
    ]


def _bed(category, w, h, d):
    return [
        _box(0, 0.2, 0, w, 0.4, d, "main"),
        _box(0, h - 0.1, 0.05, w - 0.04, 0.2, d - 0.1, "accent"),
        _box(0, 0.5, -d / 2 + 0.04, w, 1.0, 0.08, "main"),
        _box(0, h + 0.05, -d / 2 + 0.3, w * 0.7, 0.12, 0.35, "accent"),
    ]


def _counter(category, w, h, d):
    out = [_box(0, (h - 0.04) / 2, 0, w, h - 0.04, d, "main"), _box(0, h - 0.02, 0, w + 0.02, 0.04, d + 0.02, "accent")]
    n = max(1, int(w / 0.5))
    for i in range(n):
        x = -w / 2 + (i + 0.5) * w / n
        out.append(_box(x, h * 0.55, d / 2 + 0.005, w / n - 0.04, h * 0.7, 0.01, "trim"))
    if category == "Stove":
        out.append(_box(0, h + 0.35, -d / 2 + 0.03, w, 0.7, 0.06, "trim"))
    return out


def _shelves(category, w, h, d):
    out = [
        _box(-w / 2 + 0.02, h / 2, 0, 0.04, h, d, "main"),
        _box(w / 2 - 0.02, h / 2, 0, 0.04, h, d, "main"),
        _box(0, h - 0.02, 0, w, 0.04, d, "main"),
        _box(0, h / 2, -d / 2 + 0.01, w, h, 0.02, "main"),
    ]
    if category in ("Wardrobe", "Dresser", "TVStand"):
        out.append(_box(0, h / 2, d / 2 - 0.02, w - 0.06, h - 0.06, 0.03, "accent"))
    n = max(2, int(h / 0.4))
    for i in range(n):
        out.append(_box(0, i * h / n + 0.02, 0, w - 0.06, 0.03, d - 0.02, "main"))
    return out


def _toilet(category, w, h, d):
    return [
        _box(0, 0.2, 0.05, w * 0.8, 0.4, d * 0.7, "main"),
        _box(0, 0.42, 0.05, w, 0.05, d * 0.75, "main"),
        _box(0, 0.6, -d / 2 + 0.1, w, 0.4, 0.2, "main"),
    ]


def _bathtub(category, w, h, d):
    return [_box(0, h / 2, 0, w, h, d, "main"), _box(0, h - 0.01, 0, w - 0.12, 0.02, d - 0.12, "accent")]


# ---- target objects
def _fridge(category, w, h, d):
    return [
        _box(0, h / 2, 0, w, h, d, "main"),
        _box(0, h * 0.78, d / 2 + 0.01, w - 0.04, h * 0.4, 0.02, "main"),
        _box(w / 2 - 0.08, h * 0.6, d / 2 + 0.04, 0.03, 0.4, 0.04, "trim"),
    ]


def _microwave(category, w, h, d):
    return [
        _box(0, h / 2, 0, w, h, d, "main"),
        _box(-0.06, h / 2, d / 2 + 0.005, w * 0.62, h * 0.7, 0.01, "screen"),
        _box(w / 2 - 0.07, h / 2, d / 2 + 0.005, 0.08, h * 0.7, 0.01, "trim"),
    ]


def _television(category, w, h, d):
    return [
        _box(0, 0.05 + h / 2, 0, w, h, d, "trim"),
        _box(0, 0.05 + h / 2, d / 2 + 0.003, w - 0.04, h - 0.04, 0.005, "screen"),
        _box(0, 0.025, 0, w * 0.3, 0.05, 0.2, "trim"),
    ]


def _laptop(category, w, h, d):
    return [
        _box(0, 0.01, 0.02, w, 0.02, d * 0.9, "main"),
        _box(0, h / 2, -d / 2 + 0.01, w, h, 0.015, "main"),
        _box(0, h / 2, -d / 2 + 0.02, w - 0.03, h - 0.04, 0.004, "screen"),
    ]


def _floor_lamp(category, w, h, d):
    return [
        _box(0, 0.02, 0, w * 0.8, 0.04, d * 0.8, "trim"),
        _box(0, h / 2, 0, 0.035, h, 0.035, "trim"),
        _box(0, h - 0.15, 0, w, 0.3, d, "lamp"),
    ]


def _desk_lamp(category, w, h, d):
    return [
        _box(0, 0.015, 0, w, 0.03, d, "trim"),
        _box(0, h * 0.45, 0, 0.025, h * 0.9, 0.025, "trim"),
        _box(0, h - 0.07, 0.03, w * 0.9, 0.14, d * 0.9, "lamp"),
    ]


def _garbage_can(category, w, h, d):
    return [_box(0, h / 2, 0, w, h, d, "main"), _box(0, h + 0.01, 0, w + 0.02, 0.02, d + 0.02, "trim")]


def _appliance(category, w, h, d):
    out = [_box(0, h / 2, 0, w, h, d, "main")]
    if category == "CoffeeMachine":
        out += [
            _box(0, h * 0.3, d / 2 - 0.02, w * 0.6, h * 0.35, 0.06, "screen"),
            _box(0, h * 0.85, 0.02, w, h * 0.3, d, "trim"),
        ]
    elif category == "Toaster":
        out += [
            _box(-w / 4, h + 0.005, 0, w * 0.3, 0.01, d * 0.6, "screen"),
            _box(w / 4, h + 0.005, 0, w * 0.3, 0.01, d * 0.6, "screen"),
        ]
    elif category == "Kettle":
        out += [
            _box(0, h + 0.03, -d / 2 + 0.03, 0.03, 0.06, 0.06, "trim"),
            _box(0, h * 0.7, d / 2 + 0.03, 0.04, 0.04, 0.06, "main"),
        ]
    else:
        out += [_box(0, h / 2, d / 2 + 0.003, w * 0.75, h * 0.6, 0.006, "screen")]
    return out


def _vessel(category, w, h, d):
    wall = 0.015
    return [
        _box(0, 0.01, 0, w * 0.6, 0.02, d * 0.6, "main"),
        _box(0, h / 2, -d / 2 + wall / 2, w, h, wall, "main"),
        _box(0, h / 2, d / 2 - wall / 2, w, h, wall, "main"),
        _box(-w / 2 + wall / 2, h / 2, 0, wall, h, d, "main"),
        _box(w / 2 - wall / 2, h / 2, 0, wall, h, d, "main"),
    ] + (
        [
            _box(w / 2 + 0.05, h * 0.8, 0, 0.1, 0.02, 0.03, "trim"),
            _box(-w / 2 - 0.05, h * 0.8, 0, 0.1, 0.02, 0.03, "trim"),
        ]
        if category == "Pot"
        else []
    )


def _pan(category, w, h, d):
    return [_box(0, h / 2, 0, w, h, d, "main"), _box(0, h * 0.7, d / 2 + 0.1, 0.03, 0.02, 0.2, "trim")]


def _sink(category, w, h, d):
    return [
        _box(0, -0.0, 0, w, 0.02, d, "trim"),
        _box(0, 0.12, -d / 2 - 0.03, 0.04, 0.25, 0.04, "metal"),
        _box(0, 0.23, -d / 2 + 0.05, 0.03, 0.03, 0.14, "metal"),
    ]


def _stove_burner(category, w, h, d):
    return [_box(0, h / 2, 0, w, h, d, "main"), _box(0, h, 0, w * 0.55, 0.006, d * 0.55, "trim")]


def _light_switch(category, w, h, d):
    return [_box(0, h / 2, 0, w, h, d, "main"), _box(0, h / 2, d / 2 + 0.004, w * 0.3, h * 0.45, 0.008, "trim")]


def _flat(category, w, h, d):
    out = [_box(0, h / 2, 0, w, h, d, "main")]
    if category == "CellPhone":
        out.append(_box(0, h + 0.001, 0, w * 0.9, 0.002, d * 0.9, "screen"))
    if category == "RemoteControl":
        out.append(_box(0, h + 0.003, -0.03, w * 0.6, 0.006, d * 0.5, "trim"))
    return out


def _block(category, w, h, d):
    return [_box(0, h / 2, 0, w, h, d, "main")]


#: The model of each category (:func:`shape`); a category not listed is one box.
SHAPES = {
    **dict.fromkeys(("DiningTable", "Desk", "CoffeeTable", "SideTable"), _table),
    "Chair": _chair,
    **dict.fromkeys(("Sofa", "ArmChair"), _sofa),
    "Bed": _bed,
    **dict.fromkeys(("CounterTop", "Cabinet", "Vanity", "Stove", "KitchenIsland"), _counter),
    **dict.fromkeys(("ShelvingUnit", "Wardrobe", "Dresser", "TVStand"), _shelves),
    "Toilet": _toilet,
    "Bathtub": _bathtub,
    "Fridge": _fridge,
    "Microwave": _microwave,
    "Television": _television,
    "Laptop": _laptop,
    "FloorLamp": _floor_lamp,
    "DeskLamp": _desk_lamp,
    "GarbageCan": _garbage_can,
    **dict.fromkeys(("CoffeeMachine", "Toaster", "Kettle", "AlarmClock"), _appliance),
    **dict.fromkeys(("Bowl", "Pot"), _vessel),
    "Pan": _pan,
    "Sink": _sink,
    "StoveBurner": _stove_burner,
    "LightSwitch": _light_switch,
    **dict.fromkeys(("Book", "CellPhone", "RemoteControl", "Plate"), _flat),
}


#: material roles per category (main, accent, trim); "screen", "lamp" and "metal" are fixed roles.
ROLES = {
    "CounterTop": ("painted", "stone", "painted"),
    "Cabinet": ("painted", "stone", "wood"),
    "Vanity": ("painted", "stone", "wood"),
    "Stove": ("metal", "metal", "metal"),
    "KitchenIsland": ("wood", "stone", "painted"),
    "DiningTable": ("wood",),
    "Desk": ("wood",),
    "CoffeeTable": ("wood",),
    "SideTable": ("wood",),
    "ShelvingUnit": ("wood", "wood"),
    "Wardrobe": ("wood", "painted"),
    "Dresser": ("wood", "painted"),
    "TVStand": ("wood", "painted"),
    "Sofa": ("fabric", "fabric"),
    "ArmChair": ("fabric", "fabric"),
    "Bed": ("wood", "bedding"),
    "Toilet": ("ceramic",),
    "Bathtub": ("ceramic", "ceramic"),
    "Chair": ("wood",),
    "Fridge": ("metal", "metal", "metal"),
    "Microwave": ("metal", "metal", "plastic"),
    "Television": ("plastic", "plastic", "plastic"),
    "Laptop": ("metal",),
    "FloorLamp": ("metal", "metal", "metal"),
    "DeskLamp": ("metal", "metal", "metal"),
    "GarbageCan": ("plastic", "plastic", "plastic"),
    "CoffeeMachine": ("plastic", "plastic", "metal"),
    "Toaster": ("metal", "metal", "plastic"),
    "Kettle": ("metal", "metal", "plastic"),
    "AlarmClock": ("plastic",),
    "Bowl": ("ceramic",),
    "Pot": ("metal", "metal", "plastic"),
    "Pan": ("metal", "metal", "plastic"),
    "Sink": ("metal", "metal", "metal"),
    "StoveBurner": ("metal", "metal", "metal"),
    "LightSwitch": ("plastic", "plastic", "plastic"),
    "Book": ("paper",),
    "CellPhone": ("plastic",),
    "RemoteControl": ("plastic", "plastic", "plastic"),
    "Plate": ("ceramic",),
}


def materials_for(category: str, rng: np.random.Generator, roles: tuple[str, ...] | None = None) -> dict:
    """Material slots (main, accent, trim, screen, lamp, metal) of one model, drawn from ``roles`` (default:
    the category's :data:`ROLES`)."""
    roles = roles or ROLES.get(category, ("painted",))
    mats = {}
    for i, name in enumerate(("main", "accent", "trim")):
        mats[name] = material(rng, roles[min(i, len(roles) - 1)])
    mats["screen"] = material(rng, "screen")
    mats["lamp"] = material(rng, "lamp")
    mats["metal"] = material(rng, "metal")
    return mats


def build_parts(
    category: str, center, size, yaw: float, inst: int, rng: np.random.Generator, mats: dict | None = None
) -> list[Part]:
    """World-space parts of one model placed with its base centre at ``center`` and rotated by ``yaw``;
    ``mats`` (from :func:`materials_for`) fixes the materials instead of drawing them from ``rng``."""
    if mats is None:
        mats = materials_for(category, rng)
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    out = []
    for (lx, ly, lz), lsize, role in shape(category, size, rng):
        col, col2, pat, scale = mats[role]
        wx = center[0] + c * lx + s * lz
        wz = center[2] - s * lx + c * lz
        out.append(Part((wx, center[1] + ly, wz), lsize, yaw, col, col2, pat, scale, inst))
    return out
