"""Procedural houses in the image of AI2-THOR (iTHOR single rooms, RoboTHOR-like apartments).

Deterministic: a scene name (plus the generator version) fixes every random draw, so the same name gives
the same scene, byte for byte. Names and splits follow AI2-THOR and the lineage:

* kitchens ``FloorPlan1``-``30``, living rooms ``FloorPlan201``-``230``, bedrooms ``301``-``330``,
  bathrooms ``401``-``430``; numbers 1-20 train, odd 21-29 val, even 22-30 test;
* apartments ``FloorPlan_Train{1..12}_{1..5}`` (train) and ``FloorPlan_Val{1..3}_{1..5}`` (val).
"""

from __future__ import annotations

import math
import zlib

import numpy as np
from shapely.geometry import Polygon, box
from shapely.ops import unary_union

from ..constants import ROOM_TARGETS, ROOM_TYPES, object_id
from ..data.names import scene_info
from .catalog import FLOORS, FURNITURE_SIZES, OBJECT_SIZES, WALLS, build_parts, draw_size, jitter
from .spec import Furniture, ObjectInstance, Part, SceneSpec, box_footprint

#: Part of every scene seed. 3: the lineage's room target sets (CellPhone in kitchens and living rooms) and
#: AI2-THOR's object-id format (issue 13); 2: the world of docs/RESULTS.md.
GENERATOR_VERSION = 3
#: Wall thickness, metres: procedural rooms draw a WALL_T / 2 slab inside each room (two rooms sharing an edge
#: make one WALL_T wall), real scenes one WALL_T slab outside the room polygon (world/real.py).
WALL_T = 0.1
DOOR_W = 1.0

ROOM_SIZE = {  # (width range, depth range), metres
    "kitchen": ((3.5, 6.0), (4.0, 7.0)),
    "living_room": ((4.5, 7.0), (5.0, 8.5)),
    "bedroom": ((3.5, 5.5), (4.0, 6.0)),
    "bathroom": ((2.25, 3.5), (2.75, 4.0)),
}
COMPACT_SIZE = {t: ((2.5, 3.25), (2.75, 3.5)) for t in ROOM_TYPES}


def scene_seed(name: str, seed: int = 0) -> int:
    return zlib.crc32(f"tsnav-world-v{GENERATOR_VERSION}|{name}|{seed}".encode())


# -------------------------------------------------------------------------------------- placement
#: Which furniture holds each target category (first fitting support wins, in random order).
SUPPORTS = {
    "Toaster": ("CounterTop", "KitchenIsland"),
    "CoffeeMachine": ("CounterTop", "KitchenIsland"),
    "Microwave": ("CounterTop",),
    "Kettle": ("Stove", "CounterTop", "KitchenIsland"),
    "Pot": ("Stove", "CounterTop"),
    "Pan": ("Stove", "CounterTop"),
    "Bowl": ("CounterTop", "DiningTable", "KitchenIsland", "CoffeeTable", "ShelvingUnit"),
    "Plate": ("DiningTable", "CounterTop", "KitchenIsland", "ShelvingUnit"),
    "Book": ("ShelvingUnit", "CoffeeTable", "Desk", "SideTable", "DiningTable", "Bed", "Dresser"),
    "Laptop": ("Desk", "CoffeeTable", "DiningTable", "Bed", "Sofa"),
    "RemoteControl": ("CoffeeTable", "Sofa", "SideTable", "TVStand"),
    "CellPhone": (
        "Bed",
        "Desk",
        "SideTable",
        "Dresser",
        "CounterTop",
        "DiningTable",
        "KitchenIsland",
        "CoffeeTable",
        "Sofa",
        "TVStand",
    ),
    "AlarmClock": ("SideTable", "Dresser", "Desk"),
    "DeskLamp": ("Desk", "SideTable", "Dresser"),
    "Television": ("TVStand", "Dresser"),
    "Sink": ("CounterTop", "Vanity"),
    "StoveBurner": ("Stove",),
}
FLOOR_OBJECTS = {"Fridge", "GarbageCan", "FloorLamp", "Chair"}
#: Furniture per room type: (category, where, probability).
TEMPLATES = {
    "kitchen": [
        ("Stove", "wall", 1.0),
        ("CounterTop", "wall", 1.0),
        ("CounterTop", "wall", 0.9),
        ("CounterTop", "wall", 0.5),
        ("Cabinet", "wall", 0.5),
        ("ShelvingUnit", "wall", 0.5),
        ("KitchenIsland", "center", 0.5),
        ("DiningTable", "center", 0.6),
    ],
    "living_room": [
        ("Sofa", "wall", 1.0),
        ("TVStand", "wall", 1.0),
        ("CoffeeTable", "center", 1.0),
        ("ArmChair", "center", 0.6),
        ("ShelvingUnit", "wall", 0.8),
        ("ShelvingUnit", "wall", 0.4),
        ("SideTable", "wall", 0.7),
        ("Desk", "wall", 0.6),
        ("DiningTable", "center", 0.4),
    ],
    "bedroom": [
        ("Bed", "wall", 1.0),
        ("SideTable", "wall", 1.0),
        ("Dresser", "wall", 0.9),
        ("Desk", "wall", 0.8),
        ("Wardrobe", "wall", 0.6),
        ("ShelvingUnit", "wall", 0.5),
    ],
    "bathroom": [("Vanity", "wall", 1.0), ("Toilet", "wall", 1.0), ("Bathtub", "wall", 0.7), ("Cabinet", "wall", 0.3)],
}
COUNTS = {"StoveBurner": (2, 4), "Chair": (1, 4), "Book": (1, 3), "Plate": (1, 2), "Bowl": (1, 2)}


class RoomBuilder:
    """Places furniture and objects in one rectangular room of a :class:`SceneSpec`."""

    def __init__(self, spec: SceneSpec, rect, room_type: str, rng: np.random.Generator, doors: list):
        self.spec, self.rect, self.type, self.rng = spec, rect, room_type, rng
        x0, z0, x1, z1 = rect
        self.occupied = [box(d["rect"][0], d["rect"][1], d["rect"][2], d["rect"][3]).buffer(0.45) for d in doors]
        self.surfaces: list[tuple[Furniture, float, float]] = []  # (furniture, height, inset)
        self.counter = 0

    def _free(self, poly: Polygon, margin: float = 0.05) -> bool:
        x0, z0, x1, z1 = self.rect
        if not box(x0, z0, x1, z1).buffer(1e-6).contains(poly):
            return False
        return not any(poly.buffer(margin).intersects(o) for o in self.occupied)

    def place_wall(self, category: str, size) -> tuple | None:
        """Back against a random wall; returns (center, yaw) or None when nothing fits."""
        x0, z0, x1, z1 = self.rect
        w, _, d = size
        for _ in range(40):
            side = int(self.rng.integers(4))
            # yaw: the front faces into the room. side 0: wall at z0 (front +z, yaw 0); 1: x1 (yaw 270);
            # 2: z1 (yaw 180); 3: x0 (yaw 90).
            if side == 0:
                cx, cz, yaw = self.rng.uniform(x0 + w / 2, max(x0 + w / 2, x1 - w / 2)), z0 + d / 2 + 0.06, 0.0
            elif side == 2:
                cx, cz, yaw = self.rng.uniform(x0 + w / 2, max(x0 + w / 2, x1 - w / 2)), z1 - d / 2 - 0.06, 180.0
            elif side == 1:
                cx, cz, yaw = x1 - d / 2 - 0.06, self.rng.uniform(z0 + w / 2, max(z0 + w / 2, z1 - w / 2)), 270.0
            else:
                cx, cz, yaw = x0 + d / 2 + 0.06, self.rng.uniform(z0 + w / 2, max(z0 + w / 2, z1 - w / 2)), 90.0
            poly = Polygon(box_footprint((cx, 0, cz), size, yaw))
            if self._free(poly):
                return (round(cx, 3), 0.0, round(cz, 3)), yaw
        return None

    def place_center(self, size) -> tuple | None:
        x0, z0, x1, z1 = self.rect
        for _ in range(40):
            yaw = float(self.rng.choice([0.0, 90.0, 180.0, 270.0]))
            cx = self.rng.uniform(x0 + 0.9, max(x0 + 0.9, x1 - 0.9))
            cz = self.rng.uniform(z0 + 0.9, max(z0 + 0.9, z1 - 0.9))
            poly = Polygon(box_footprint((cx, 0, cz), size, yaw))
            if self._free(poly, margin=0.5):
                return (round(cx, 3), 0.0, round(cz, 3)), yaw
        return None

    def add_furniture(self, category: str, where: str) -> Furniture | None:
        size = draw_size(self.rng, FURNITURE_SIZES, category)
        placed = self.place_wall(category, size) if where == "wall" else self.place_center(size)
        if placed is None:
            return None
        center, yaw = placed
        self.counter += 1
        fid = f"{category}|{len(self.spec.furniture) + 1}"
        inst = self.spec.new_inst(fid)
        f = Furniture(fid, category, center, size, yaw, True, None, inst)
        self.spec.furniture.append(f)
        self.spec.parts += build_parts(category, center, size, yaw, inst, self.rng)
        self.occupied.append(Polygon(f.footprint()))
        top = size[1]
        if category in ("Sofa", "ArmChair"):
            top = 0.51
        if category == "Bed":
            top = size[1] + 0.0
        if category not in ("Toilet", "Bathtub", "Wardrobe", "ArmChair"):
            self.surfaces.append((f, top, 0.08))
        if category == "ShelvingUnit":
            n = max(2, int(size[1] / 0.4))
            for i in range(1, n):
                self.surfaces.append((f, i * size[1] / n + 0.035, 0.06))
        return f

    def add_object(
        self,
        category: str,
        on: Furniture | None,
        height: float = 0.0,
        inset: float = 0.05,
        at=None,
        yaw: float | None = None,
    ) -> ObjectInstance | None:
        size = draw_size(self.rng, OBJECT_SIZES, category)
        if at is None:
            fx, _, fz = on.center
            fw, _, fd = on.size
            hx, hz = fw / 2 - inset - size[0] / 2, fd / 2 - inset - size[2] / 2
            if hx < 0 or hz < 0:  # too big for the margin: centre it when it fits at all (a sink in a vanity)
                if fw < size[0] or fd < size[2]:
                    return None
                hx, hz = max(hx, 0.0), max(hz, 0.0)
            for _ in range(20):
                lx, lz = self.rng.uniform(-hx, hx), self.rng.uniform(-hz, hz)
                if on.category == "Sofa":
                    lz = self.rng.uniform(0.0, hz)
                c, s = math.cos(math.radians(on.yaw)), math.sin(math.radians(on.yaw))
                cx, cz = fx + c * lx + s * lz, fz - s * lx + c * lz
                oyaw = on.yaw if yaw is None else yaw
                if category not in ("Television", "Microwave", "CoffeeMachine", "Toaster"):
                    oyaw = float(on.yaw + self.rng.choice([0, 90, 180, 270]) + self.rng.uniform(-15, 15))
                poly = Polygon(box_footprint((cx, 0, cz), size, oyaw))
                clash = any(
                    o.support == on.id
                    and abs(o.center[1] - height) < 0.05
                    and Polygon(box_footprint(o.center, o.size, o.yaw)).buffer(0.02).intersects(poly)
                    for o in self.spec.objects
                )
                if not clash:
                    break
            else:
                return None
            center, support = (round(cx, 3), round(height, 3), round(cz, 3)), on.id
        else:
            center, support, oyaw = at, ("wall" if category == "LightSwitch" else "floor"), yaw
        oid = object_id(category, *center)
        if any(o.objectId == oid for o in self.spec.objects):
            return None
        inst = self.spec.new_inst(oid)
        obj = ObjectInstance(oid, category, center, size, float(oyaw), support, inst)
        self.spec.objects.append(obj)
        self.spec.parts += build_parts(category, center, size, oyaw, inst, self.rng)
        if support == "floor":
            self.occupied.append(Polygon(box_footprint(center, size, oyaw)))
        return obj

    def floor_object(self, category: str) -> ObjectInstance | None:
        size = draw_size(self.rng, OBJECT_SIZES, category)
        if category == "Chair":
            tables = [f for f in self.spec.furniture if f.category in ("DiningTable", "Desk") and self._in_room(f)]
            self.rng.shuffle(tables)
            for t in tables:
                for _ in range(8):
                    side = int(self.rng.integers(4))
                    yaw = t.yaw + (0, 90, 180, 270)[side]
                    off = (t.size[2] if side % 2 == 0 else t.size[0]) / 2 + 0.12
                    along = self.rng.uniform(-0.25, 0.25)
                    # The chair stands on that side of the table, facing it.
                    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
                    cx, cz = t.center[0] - (s * off) + c * along, t.center[2] - (c * off) - s * along
                    poly = Polygon(box_footprint((cx, 0, cz), size, yaw))
                    if self._free(poly, margin=0.02):
                        return self.add_object("Chair", None, at=(round(cx, 3), 0.0, round(cz, 3)), yaw=float(yaw))
            placed = self.place_center(size)
        elif category == "Fridge":
            placed = self.place_wall(category, size)
        else:  # GarbageCan, FloorLamp: near a wall or in a corner
            placed = self.place_wall(category, size)
        if placed is None:
            return None
        center, yaw = placed
        return self.add_object(category, None, at=center, yaw=yaw)

    def light_switch(self) -> ObjectInstance | None:
        x0, z0, x1, z1 = self.rect
        for _ in range(20):
            side = int(self.rng.integers(4))
            t = self.rng.uniform(0.3, 0.7)
            if side == 0:
                c, yaw = (x0 + t * (x1 - x0), 1.2, z0 + 0.065), 0.0
            elif side == 2:
                c, yaw = (x0 + t * (x1 - x0), 1.2, z1 - 0.065), 180.0
            elif side == 1:
                c, yaw = (x1 - 0.065, 1.2, z0 + t * (z1 - z0)), 270.0
            else:
                c, yaw = (x0 + 0.065, 1.2, z0 + t * (z1 - z0)), 90.0
            poly = Polygon(box_footprint(c, (0.3, 0, 0.3), yaw))
            if not any(poly.intersects(o) for o in self.occupied[1:]):
                return self.add_object("LightSwitch", None, at=tuple(round(v, 3) for v in c), yaw=yaw)
        return None

    def _in_room(self, f: Furniture) -> bool:
        x0, z0, x1, z1 = self.rect
        return x0 <= f.center[0] <= x1 and z0 <= f.center[2] <= z1

    def populate(self, targets: tuple[str, ...]) -> None:
        for category, where, p in TEMPLATES[self.type]:
            if self.rng.random() < p:
                self.add_furniture(category, where)
        present = [c for c in targets if self.rng.random() < (0.85 if len(targets) > 3 else 1.0)]
        if not present:
            present = [targets[int(self.rng.integers(len(targets)))]]
        for category in present:
            lo, hi = COUNTS.get(category, (1, 1))
            for _ in range(int(self.rng.integers(lo, hi + 1))):
                if category == "LightSwitch":
                    self.light_switch()
                elif category in FLOOR_OBJECTS:
                    self.floor_object(category)
                else:
                    self.surface_object(category)

    def surface_object(self, category: str) -> ObjectInstance | None:
        options = [(f, h, inset) for f, h, inset in self.surfaces if f.category in SUPPORTS.get(category, ())]
        if not options:
            return None
        order = self.rng.permutation(len(options))
        for i in order[:4]:
            f, h, inset = options[int(i)]
            obj = self.add_object(category, f, height=h, inset=inset)
            if obj is not None:
                return obj
        return None


# ---------------------------------------------------------------------------------------- scenes
def _room_rect(rng, room_type, compact, x0=0.0, z0=0.0):
    (wl, wh), (dl, dh) = (COMPACT_SIZE if compact else ROOM_SIZE)[room_type]
    w = round(rng.uniform(wl, wh) * 4) / 4
    d = round(rng.uniform(dl, dh) * 4) / 4
    return [x0, z0, x0 + w, z0 + d]


def generate(name: str, seed: int = 0, compact: bool = False) -> SceneSpec:
    """Generate scene ``name`` deterministically. ``compact`` draws small rooms (for fast tests)."""
    room_type, split = scene_info(name)
    rng = np.random.default_rng(scene_seed(name, seed) + (7 if compact else 0))
    # Grid-aligned origin offset, as AI2-THOR scenes are not centred at 0.
    ox, oz = float(rng.integers(-8, 9)) * 0.25, float(rng.integers(-8, 9)) * 0.25
    if room_type != "apartment":
        rooms = [{"type": room_type, "rect": _room_rect(rng, room_type, compact, ox, oz)}]
        doors = []
    else:
        rooms, doors = _apartment_layout(rng, ox, oz, compact)
    spec = SceneSpec(name=name, room_type=room_type, split=split, seed=seed, rooms=rooms, floor=[], doors=doors)
    spec.light = {
        "direction": [float(v) for v in rng.normal(0, 1, 3) * [1, 0, 1] + [0, -2.5, 0]],
        "ambient": float(rng.uniform(0.45, 0.6)),
        "diffuse": float(rng.uniform(0.35, 0.5)),
        "tint": [float(v) for v in rng.uniform(0.92, 1.0, 3)],
    }
    _structure(spec, rng)
    for r in rooms:
        builder = RoomBuilder(spec, r["rect"], r["type"], rng, doors)
        builder.populate(ROOM_TARGETS[r["type"]])
    return spec


def _apartment_layout(rng, ox, oz, compact):
    cols, rows = (2, 2) if rng.random() < 0.6 else ((3, 1) if rng.random() < 0.5 else (3, 2))
    types = list(
        rng.choice(
            ["living_room", "kitchen", "bedroom", "bedroom", "bathroom", "living_room"], size=cols * rows, replace=True
        )
    )
    if "living_room" not in types:
        types[0] = "living_room"
    widths = [round(rng.uniform(3.0, 4.75 if not compact else 3.25) * 4) / 4 for _ in range(cols)]
    depths = [round(rng.uniform(3.0, 4.75 if not compact else 3.25) * 4) / 4 for _ in range(rows)]
    xs = np.concatenate([[ox], ox + np.cumsum(widths)])
    zs = np.concatenate([[oz], oz + np.cumsum(depths)])
    rooms = [
        {"type": str(types[r * cols + c]), "rect": [float(xs[c]), float(zs[r]), float(xs[c + 1]), float(zs[r + 1])]}
        for r in range(rows)
        for c in range(cols)
    ]
    # Doors along a spanning tree of the room grid, plus one extra where possible.
    edges = [((r, c), (r, c + 1)) for r in range(rows) for c in range(cols - 1)] + [
        ((r, c), (r + 1, c)) for r in range(rows - 1) for c in range(cols)
    ]
    order = rng.permutation(len(edges))
    parent = {(r, c): (r, c) for r in range(rows) for c in range(cols)}

    def find(a):
        while parent[a] != a:
            a = parent[a]
        return a

    chosen = []
    for i in order:
        a, b = edges[int(i)]
        if find(a) != find(b):
            parent[find(a)] = find(b)
            chosen.append((a, b))
    extra = [edges[int(i)] for i in order if edges[int(i)] not in chosen]
    if extra and rng.random() < 0.5:
        chosen.append(extra[0])
    doors = []
    for (r1, c1), (r2, c2) in chosen:
        if r1 == r2:  # vertical wall at x = xs[c2]
            x = float(xs[c2])
            lo, hi = float(zs[r1]) + 0.4, float(zs[r1 + 1]) - 0.4 - DOOR_W
            z = round(rng.uniform(lo, hi) * 4) / 4
            doors.append({"rect": [x - 0.2, z, x + 0.2, z + DOOR_W], "axis": "x"})
        else:  # horizontal wall at z = zs[r2]
            z = float(zs[r2])
            lo, hi = float(xs[c1]) + 0.4, float(xs[c1 + 1]) - 0.4 - DOOR_W
            x = round(rng.uniform(lo, hi) * 4) / 4
            doors.append({"rect": [x, z - 0.2, x + DOOR_W, z + 0.2], "axis": "z"})
    return rooms, doors


#: Colour of the ceiling (both worlds).
CEILING_COLOUR = (0.96, 0.96, 0.95)


def floor_and_ceiling(rect, height: float, material, floor_inst: int, ceil_inst: int) -> list[Part]:
    """The floor slab (0.1 m thick, top at y = 0) and the ceiling slab (0.1 m, bottom at ``height``) over the
    rectangle ``rect`` = ``(x0, z0, x1, z1)``, metres; ``material`` the floor's (colour, colour 2, pattern, scale)
    as :func:`~tsnav.world.catalog.jitter` returns it. Used by the procedural rooms and the real scenes."""
    x0, z0, x1, z1 = rect
    fc, fc2, fp, fs = material
    centre, size = ((x0 + x1) / 2, (z0 + z1) / 2), (x1 - x0, 0.1, z1 - z0)
    return [
        Part((centre[0], -0.05, centre[1]), size, 0.0, fc, fc2, fp, fs, floor_inst),
        Part((centre[0], height + 0.05, centre[1]), size, 0.0, CEILING_COLOUR, CEILING_COLOUR, 0, 1.0, ceil_inst),
    ]


def _structure(spec: SceneSpec, rng) -> None:
    """Floor, ceiling and walls (with door openings) as parts; the floor polygon(s) of ``spec``."""
    floor_inst, wall_inst, ceil_inst = spec.new_inst("Floor"), spec.new_inst("Wall"), spec.new_inst("Ceiling")
    H = spec.wall_height
    union = unary_union([box(*r["rect"]) for r in spec.rooms] + [box(*d["rect"]) for d in spec.doors])
    for r in spec.rooms:
        floor_material = jitter(rng, *FLOORS[int(rng.integers(len(FLOORS)))])
        spec.parts += floor_and_ceiling(r["rect"], H, floor_material, floor_inst, ceil_inst)
        r["wall_material"] = jitter(rng, *WALLS[int(rng.integers(len(WALLS)))])
    for d in spec.doors:
        x0, z0, x1, z1 = d["rect"]
        spec.parts.append(
            Part(
                ((x0 + x1) / 2, -0.05, (z0 + z1) / 2),
                (x1 - x0, 0.1, z1 - z0),
                0.0,
                (0.5, 0.45, 0.4),
                (0.5, 0.45, 0.4),
                0,
                1.0,
                floor_inst,
            )
        )
    # Walls: every room edge, cut where a door crosses it; shared edges are drawn once from each side.
    door_boxes = [box(*d["rect"]) for d in spec.doors]
    for r in spec.rooms:
        x0, z0, x1, z1 = r["rect"]
        col, col2, pat, scale = r.pop("wall_material")
        for ax, az, bx, bz in ((x0, z0, x1, z0), (x1, z0, x1, z1), (x0, z1, x1, z1), (x0, z0, x0, z1)):
            horizontal = az == bz
            lo, hi = (ax, bx) if horizontal else (az, bz)
            cuts = []
            for db in door_boxes:
                dx0, dz0, dx1, dz1 = db.bounds
                if horizontal and dz0 < az < dz1:
                    cuts.append((dx0, dx1))
                if not horizontal and dx0 < ax < dx1:
                    cuts.append((dz0, dz1))
            segs, cur = [], lo
            for c0, c1 in sorted(cuts):
                if c0 > cur:
                    segs.append((cur, c0))
                cur = max(cur, c1)
            if cur < hi:
                segs.append((cur, hi))
            # Wall slab just inside the room: the room interior stays exactly its rectangle minus WALL_T/2.
            inward = {
                (x0, z0, x1, z0): (0, 1),
                (x1, z0, x1, z1): (-1, 0),
                (x0, z1, x1, z1): (0, -1),
                (x0, z0, x0, z1): (1, 0),
            }
            nx, nz = inward[(ax, az, bx, bz)]
            for s0, s1 in segs:
                if s1 - s0 < 1e-6:
                    continue
                if horizontal:
                    c = ((s0 + s1) / 2, H / 2, az + nz * WALL_T / 4)
                    size = (s1 - s0, H, WALL_T / 2)
                else:
                    c = (ax + nx * WALL_T / 4, H / 2, (s0 + s1) / 2)
                    size = (WALL_T / 2, H, s1 - s0)
                spec.parts.append(Part(c, size, 0.0, col, col2, pat, scale, wall_inst))
            # Door headers above openings.
            for c0, c1 in cuts:
                if horizontal:
                    spec.parts.append(
                        Part(
                            ((c0 + c1) / 2, H - 0.2, az + nz * WALL_T / 4),
                            (c1 - c0, 0.4, WALL_T / 2),
                            0.0,
                            col,
                            col2,
                            pat,
                            scale,
                            wall_inst,
                        )
                    )
                else:
                    spec.parts.append(
                        Part(
                            (ax + nx * WALL_T / 4, H - 0.2, (c0 + c1) / 2),
                            (WALL_T / 2, 0.4, c1 - c0),
                            0.0,
                            col,
                            col2,
                            pat,
                            scale,
                            wall_inst,
                        )
                    )
    geoms = list(union.geoms) if hasattr(union, "geoms") else [union]
    spec.floor = [[[round(x, 4), round(z, 4)] for x, z in list(g.exterior.coords)[:-1]] for g in geoms]
