"""The ``ithor-real`` world: the 120 real iTHOR scenes rebuilt from their recorded object layouts.

Each scene comes from its layout (:mod:`tsnav.world.layouts`, recorded from ai2thor 5 at reset) and becomes a
:class:`~tsnav.world.spec.SceneSpec` like a procedural one, so the same navgrid, renderer and writer make its
graph, grid, visible object map, images, depth and instance ids.

Room outline (the data holds no walls; ``docs/WORLD.md`` discusses the limits):

* **Outer walls.** The ``Floor`` object's box runs under and beyond the walls (about 0.3 m in most bedrooms).
  On each side the wall is put at the outermost object box (windows by their centre, as they sit in the wall)
  when that lies within :data:`WALL_SNAP` of the floor box's edge; otherwise nothing shows the wall and the
  floor box's edge is kept.
* **L-shapes and alcoves.** A wall fixture (light switch, painting, mirror, towel holder...) hanging deep inside
  that rectangle shows an inner wall: its back face is the wall plane and it faces into the room (AI2-THOR's
  rotation: 0 faces +z, 90 faces +x). Behind it, the corner region of the rectangle that no object occupies
  (from the wall plane to the outer side, and along the wall until the first object) is cut from the room when
  it holds the fixture's position along the wall and is at least :data:`MIN_ALCOVE` on both sides.

Reachability follows AI2-THOR's rule as far as the metadata tells it: the agent is a capsule of radius
:data:`~tsnav.world.navgrid.AGENT_RADIUS` and height :data:`AGENT_HEIGHT` on the 0.25 m grid; an object blocks
when it stands on the floor (its ``parentReceptacles`` hold the Floor, or it has none: fixed structure such as
counters, cabinets, fridges, toilets) and its box reaches below the capsule's top, unless it is a wall fixture
(:data:`WALL_FIXTURES`). Objects on receptacles never block (their receptacle does). Doors and openable objects
keep their reset state, which the recorded boxes already show (an open cabinet's box includes its door).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import replace

import numpy as np
from shapely.geometry import MultiPoint, Point, Polygon, box
from shapely.geometry.polygon import orient

from ..constants import TARGET_CATEGORIES
from ..data.names import scene_info
from .catalog import FLOORS, WALLS, build_parts, jitter, materials_for
from .house import WALL_T, floor_and_ceiling
from .layouts import Layout, LayoutObject, load_layout
from .spec import Furniture, ObjectInstance, Part, SceneSpec, box_footprint

#: Height of the agent's capsule, metres (AI2-THOR reports the agent's centre 0.9 m above the floor).
AGENT_HEIGHT = 1.8
#: Categories fixed to walls (or hanging from them): never obstacles, they mark where walls are.
WALL_FIXTURES = frozenset(
    {
        "LightSwitch",
        "Painting",
        "Poster",
        "Window",
        "Blinds",
        "Mirror",
        "Curtains",
        "ShowerHead",
        "ShowerCurtain",
        "TowelHolder",
        "HandTowelHolder",
        "ToiletPaperHanger",
    }
)
#: Furthest an outermost object may sit from the floor box's edge to be taken as lying against that wall, m.
WALL_SNAP = 0.6
#: Smallest side of a corner region cut from the room as an L-shape or alcove, metres.
MIN_ALCOVE = 1.0
#: Deepest a counter run is taken to be, metres; a counter box deeper on both sides is an L, U or island.
COUNTER_MAX_DEPTH = 1.2
#: Categories drawn with the procedural catalog's model scaled to the recorded box; others are plain boxes.
CATALOG_SHAPES = frozenset(
    {
        "CounterTop",
        "DiningTable",
        "Desk",
        "CoffeeTable",
        "SideTable",
        "ShelvingUnit",
        "Sofa",
        "ArmChair",
        "TVStand",
        "Bed",
        "Dresser",
        "Toilet",
        "Bathtub",
        "Chair",
        "Fridge",
        "Microwave",
        "Television",
        "Laptop",
        "FloorLamp",
        "DeskLamp",
        "GarbageCan",
        "CoffeeMachine",
        "Toaster",
        "Kettle",
        "AlarmClock",
        "Bowl",
        "Pot",
        "Pan",
        "Book",
        "CellPhone",
        "RemoteControl",
        "Plate",
        "LightSwitch",
        "StoveBurner",
        "Sink",
    }
)
#: Material roles of categories that the procedural catalog does not know (:data:`catalog.ROLES` covers the rest).
EXTRA_ROLES = {
    "Cabinet": ("painted",),
    "Drawer": ("painted",),
    "Shelf": ("wood",),
    "Window": ("lamp",),
    "Blinds": ("painted",),
    "Curtains": ("fabric",),
    "Mirror": ("screen",),
    "Painting": ("paper",),
    "Poster": ("paper",),
    "SinkBasin": ("metal",),
    "Faucet": ("metal",),
    "StoveKnob": ("plastic",),
    "Stool": ("wood",),
    "Pillow": ("bedding",),
    "Cloth": ("fabric",),
    "Towel": ("fabric",),
    "HandTowel": ("fabric",),
    "ShowerCurtain": ("fabric",),
    "ShowerDoor": ("lamp",),
    "ShowerGlass": ("lamp",),
    "BathtubBasin": ("ceramic",),
    "HousePlant": ("fabric",),
    "Box": ("paper",),
    "Newspaper": ("paper",),
    "Vase": ("ceramic",),
    "Statue": ("stone",),
    "Safe": ("metal",),
    "Ottoman": ("fabric",),
    "LaundryHamper": ("fabric",),
    "Stove": ("metal", "metal", "plastic"),
}
_FLOOR_TOL = 0.05
#: Version of the ``ithor-real`` rules (:func:`real_spec`); version 1 is the rules of worlds built before issue 24.
GENERATOR_VERSION = 2
VERSIONS = (1, 2)
#: The Floor object's box runs under the walls: from version 2 a wall lies at least this far inside its edge, m.
WALL_INSET = 0.1
#: Clearance kept between the agent's centre and walls or blocking boxes from version 2, metres: the capsule's
#: radius (:data:`~tsnav.world.navgrid.AGENT_RADIUS`) less 1 cm, as a capsule just touching a box is no hit and the
#: recorded boxes are rounded to the millimetre (real agents stand exactly 0.20 m from counters and walls).
CLEARANCE = 0.19
#: Clearance a MoveAhead's straight path keeps from version 2, metres: real agents move diagonally between any
#: two reachable neighbours (of the real blocked MoveAheads none leads to a position real agents stood on), so
#: the path only has to stay off the obstacles themselves, not a full capsule radius away from them.
SWEEP_CLEARANCE = 0.05
#: Upholstered seats, whose recorded boxes hold cushions and rounded arms beyond their colliders: real agents
#: stand 0.166-0.186 m from sofa and armchair boxes (FloorPlan222, 226, 330); from version 2 the agent keeps
#: :data:`SEAT_CLEARANCE` from them. (Beds are not among them: a real agent is blocked 0.182 m from one.)
UPHOLSTERED = frozenset({"Sofa", "ArmChair"})
SEAT_CLEARANCE = 0.16
#: Height of the bottom of the agent's capsule above the floor, metres: AI2-THOR reports the agent's centre 0.93 m
#: above the floor (``event_FloorPlan29_physics_reset.json``) and the capsule is :data:`AGENT_HEIGHT` high.
CAPSULE_BOTTOM = 0.03


def low_clearance(top: float, clearance: float = 0.19) -> float:
    """Clearance the capsule keeps from an object whose top is ``top`` metres above the floor (from version 2):
    the capsule's rounded bottom (a hemisphere of radius ``clearance`` from :data:`CAPSULE_BOTTOM` up) is
    narrower than ``clearance`` below ``CAPSULE_BOTTOM + clearance``; 0 when the object is lower than the
    capsule (a cloth lying flat). Objects at least that high keep ``clearance``."""
    h = top - CAPSULE_BOTTOM
    if h <= 0:
        return 0.0
    if h >= clearance:
        return clearance
    return math.sqrt(clearance**2 - (clearance - h) ** 2)


#: A toilet box wider than this across the direction it faces holds more than the toilet (the Toilet_2 asset of
#: FloorPlan421-430 records 1.12 x 1.17 m); from version 2 it is replaced by :data:`TOILET_SIZE`, metres.
TOILET_MAX_WIDTH = 0.8
#: ``(width, depth)`` of the toilet footprint used instead, its back on the recorded box's back face and
#: centred across on the toilet's pivot (its objectId), metres.
TOILET_SIZE = (0.53, 0.97)


# ------------------------------------------------------------------------------------------------ rules
def is_floor_id(object_id: str) -> bool:
    return object_id.split("|", 1)[0] == "Floor"


def blocks(
    o: LayoutObject, floor_y: float = 0.0, height: float = AGENT_HEIGHT, version: int = GENERATOR_VERSION
) -> bool:
    """Whether object ``o`` blocks the agent (AI2-THOR's reachability rule as the metadata tells it, see the
    module docstring): floor-standing or fixed, below the capsule's top, not a wall fixture. Version 1 let an
    object block when any of its receptacles was the Floor; from version 2 a pickupable object that also rests on
    another receptacle (a pillow on a sofa touching the floor, a towel on its holder) is on that receptacle (a
    desk whose receptacles are the floor and the chair touching it still blocks)."""
    if o.object_type == "Floor" or o.object_type in WALL_FIXTURES:
        return False
    if o.parents and not any(is_floor_id(p) for p in o.parents):
        return False  # on a receptacle: the receptacle blocks
    if version >= 2 and o.pickupable and any(not is_floor_id(p) for p in o.parents):
        return False  # a small thing resting on a receptacle that also touches the floor (a pillow on a sofa)
    if version >= 2 and o.aabb_max[1] - floor_y <= CAPSULE_BOTTOM:
        return False  # lower than the capsule's bottom: the agent passes over it
    return o.aabb_min[1] - floor_y < height


def floor_top(layout: Layout) -> float:
    """Height of the Floor object's top surface, metres (not 0 in every scene: 0.22 in FloorPlan3)."""
    return layout.floor.aabb_max[1]


def on_floor(layout: Layout) -> Layout:
    """``layout`` moved vertically so that the floor's top is at y = 0, where the renderer's camera height
    (1.5 m) and the agent's capsule are measured from; x and z (and the recorded objectIds) are unchanged."""
    dy = -floor_top(layout)
    if dy == 0:
        return layout

    def move(o: LayoutObject) -> LayoutObject:
        cx, cy, cz = o.aabb_center
        oobb = None if o.oobb is None else tuple((x, y + dy, z) for x, y, z in o.oobb)
        return replace(o, aabb_center=(cx, cy + dy, cz), oobb=oobb)

    return Layout(layout.scene, tuple(move(o) for o in layout.objects))


def oriented_box(o: LayoutObject) -> tuple[tuple[float, float], tuple[float, float], float]:
    """Footprint of ``o`` on the floor plane as ``((cx, cz), (size along local x, along local z), yaw)``.

    From the oriented box's corners when recorded (the smallest rectangle around their floor projection,
    turned by a multiple of 90 degrees so that its yaw is nearest the object's rotation, which keeps the
    model's front where AI2-THOR's is), otherwise from the axis-aligned box (yaw 0, or 90/180/270 when the
    object is turned by a right angle, with the sides swapped)."""
    ry = o.rotation[1] % 360
    if o.oobb is not None:
        pts = MultiPoint([(c[0], c[2]) for c in o.oobb])
        rect = pts.minimum_rotated_rectangle
        if isinstance(rect, Polygon) and rect.area > 1e-6:
            p = np.asarray(rect.exterior.coords)[:4]
            e0, e1 = p[1] - p[0], p[2] - p[1]
            a, b = float(np.hypot(*e0)), float(np.hypot(*e1))
            yaw0 = math.degrees(math.atan2(-e0[1], e0[0]))  # local +x = (cos yaw, -sin yaw) in (x, z)
            best = min(range(4), key=lambda k: abs((yaw0 + 90 * k - ry + 180) % 360 - 180))
            yaw = round((yaw0 + 90 * best) % 360, 3)
            sx, sz = (a, b) if best % 2 == 0 else (b, a)
            c = rect.centroid
            return (float(c.x), float(c.y)), (sx, sz), yaw
    cx, _, cz = o.aabb_center
    sx, _, sz = o.aabb_size
    k = round(ry / 90) % 4
    if abs(ry - 90 * round(ry / 90)) < 10 and k % 2 == 1:
        return (cx, cz), (sz, sx), 90.0 * k
    return (cx, cz), (sx, sz), (180.0 if k == 2 and abs(ry - 180) < 10 else 0.0)


def _bounds(o: LayoutObject) -> tuple[float, float, float, float]:
    (x0, _, z0), (x1, _, z1) = o.aabb_min, o.aabb_max
    return x0, z0, x1, z1


def outer_rect(layout: Layout, version: int = GENERATOR_VERSION) -> list[float]:
    """``[x0, z0, x1, z1]``: the room's outer walls (module docstring, "Outer walls"); from version 2 every
    wall lies at least :data:`WALL_INSET` inside the floor box's edge."""
    fx0, fz0, fx1, fz1 = _bounds(layout.floor)
    ext = [math.inf, math.inf, -math.inf, -math.inf]
    for o in layout.objects:
        if o.object_type == "Floor":
            continue
        if o.object_type == "Window":
            b = (o.aabb_center[0], o.aabb_center[2], o.aabb_center[0], o.aabb_center[2])
        else:
            b = _bounds(o)
        ext = [min(ext[0], b[0]), min(ext[1], b[1]), max(ext[2], b[2]), max(ext[3], b[3])]
    floor = (fx0, fz0, fx1, fz1)
    out = []
    for i, sign in enumerate((1, 1, -1, -1)):  # x0, z0 grow inwards (+); x1, z1 shrink (-)
        gap = (ext[i] - floor[i]) * sign
        used = gap if 0 < gap <= WALL_SNAP else 0.0
        out.append(floor[i] + sign * max(used, WALL_INSET if version >= 2 else 0.0))
    # From version 2 rounded to 0.1 mm like the alcove cuts, so that a cut flush with a wall leaves no sliver.
    return [round(v, 4) + 0.0 for v in out] if version >= 2 else out


def alcoves(layout: Layout, rect: list[float]) -> list[list[float]]:
    """Corner rectangles ``[x0, z0, x1, z1]`` cut from ``rect`` (module docstring, "L-shapes and alcoves")."""
    x0, z0, x1, z1 = rect
    obstacles = [_bounds(o) for o in layout.objects if o.object_type != "Floor" and o.object_type not in WALL_FIXTURES]
    cuts: list[list[float]] = []
    for f in layout.objects:
        if f.object_type not in WALL_FIXTURES:
            continue
        fx, _, fz = f.aabb_center
        if min(fx - x0, x1 - fx, fz - z0, z1 - fz) < 0.4:
            continue  # on an outer wall
        ry = math.radians(f.rotation[1])
        face = (math.sin(ry), math.cos(ry))  # the direction it faces (into the room)
        axis = 0 if abs(face[0]) > abs(face[1]) else 1  # wall plane: x = const (0) or z = const (1)
        if abs(face[axis]) < 0.9:
            continue  # not square to the grid
        back = -1.0 if face[axis] > 0 else 1.0  # the side behind the wall
        plane = (fx, fz)[axis] + back * f.aabb_size[0 if axis == 0 else 2] / 2
        lo, hi = (x0, x1) if axis == 0 else (z0, z1)
        outer = hi if back > 0 else lo
        a0, a1 = sorted((plane, outer))
        if a1 - a0 < MIN_ALCOVE or (hi - lo) - (a1 - a0) < MIN_ALCOVE:
            continue
        # Along the wall, from each end of the rectangle towards the fixture, until the first object.
        along = fz if axis == 0 else fx
        blo, bhi = (z0, z1) if axis == 0 else (x0, x1)
        for start, step in ((blo, 1), (bhi, -1)):
            stop = bhi if step > 0 else blo
            for ob in obstacles:
                oa0, oa1 = (ob[0], ob[2]) if axis == 0 else (ob[1], ob[3])
                ob0, ob1 = (ob[1], ob[3]) if axis == 0 else (ob[0], ob[2])
                if oa1 <= a0 + 1e-3 or oa0 >= a1 - 1e-3:
                    continue
                stop = min(stop, ob0) if step > 0 else max(stop, ob1)
            c0, c1 = sorted((start, stop))
            if c1 - c0 < MIN_ALCOVE or not (c0 < along < c1) or (bhi - blo) - (c1 - c0) < MIN_ALCOVE:
                continue
            cut = [a0, c0, a1, c1] if axis == 0 else [c0, a0, c1, a1]
            if all(not box(*cut).buffer(-1e-3).intersects(box(*c)) for c in cuts):
                cuts.append([round(v, 4) for v in cut])
    return cuts


def _local(x: float, z: float, yaw: float) -> tuple[float, float]:
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    return c * x - s * z, s * x + c * z  # inverse of (x = c lx + s lz, z = -s lx + c lz)


def counter_boxes(
    layout: Layout, counter: LayoutObject, version: int = GENERATOR_VERSION
) -> list[tuple[tuple[float, float], tuple[float, float], float]]:
    """Footprints ``((cx, cz), (sx, sz), yaw)`` of a counter whose recorded box (its top slab, without an
    oriented box) is much larger than a counter's depth: an L- or U-shaped run along the walls, or an island
    turned off the grid. Things standing on the counter and the fixed cabinets, drawers and sinks under it
    show where it is:

    * turned off the grid (e.g. 315 degrees): one rectangle at that yaw, centred in the box, whose depth
      spans the objects on it (at least 0.6 m) and whose length fills the box's diagonal extent;
    * axis-aligned: each object is assigned to the box side nearest its far edge; per side, one strip as deep
      as its deepest object, running over its objects' extent (to the box's end when within 0.35 m).

    Without such objects, or for a box at most :data:`COUNTER_MAX_DEPTH` deep, the recorded box is kept."""
    (cx, _, cz), (ax, _, az) = counter.aabb_center, counter.aabb_size
    top = counter.aabb_max[1]
    x0, z0, x1, z1 = _bounds(counter)
    plain = [((cx, cz), (ax, az), 0.0)]
    if counter.oobb is not None or min(ax, az) <= COUNTER_MAX_DEPTH:
        return plain
    sup = []
    for o in layout.objects:
        if o is counter or o.object_type in WALL_FIXTURES:
            continue
        ox, _, oz = o.aabb_center
        on = counter.object_id in o.parents
        under = (
            not o.parents
            and o.object_type in ("Cabinet", "Drawer", "Sink", "SinkBasin", "StoveBurner")
            and o.aabb_max[1] <= top + 0.05
        )
        if (on or under) and x0 <= ox <= x1 and z0 <= oz <= z1:
            sup.append(o)
    if not sup:
        return plain
    ry = counter.rotation[1] % 360
    if abs(ry - 90 * round(ry / 90)) > 5:  # an island turned off the grid
        loc = np.array([_local(*(np.array((o.aabb_center[0], o.aabb_center[2])) - (cx, cz)), ry) for o in sup])
        diag = (ax + az) / 2 * math.sqrt(2)  # length + depth of a rectangle turned by 45 degrees
        # Version 1 took the depth along the local z axis; from version 2 along the axis the objects on it
        # spread less over (they stand along its length).
        axis = 1 if version < 2 or np.ptp(loc[:, 1]) <= np.ptp(loc[:, 0]) else 0
        depth = min(max(0.6, 2 * float(np.abs(loc[:, axis]).max()) + 0.15), diag / 2)
        return [((cx, cz), (diag - depth, depth) if axis == 1 else (depth, diag - depth), ry)]
    runs: dict[int, list[float]] = {}  # side -> [along0, along1, depth]
    for o in sup:
        bx0, bz0, bx1, bz1 = _bounds(o)
        far = {0: bx1 - x0, 1: bz1 - z0, 2: x1 - bx0, 3: z1 - bz0}  # sides x0, z0, x1, z1
        side = min(far, key=far.get)
        a0, a1 = (bz0, bz1) if side in (0, 2) else (bx0, bx1)
        r = runs.setdefault(side, [a0, a1, 0.0])
        r[0], r[1], r[2] = min(r[0], a0), max(r[1], a1), max(r[2], min(far[side], COUNTER_MAX_DEPTH))
    out = []
    for side, (a0, a1, depth) in sorted(runs.items()):
        lo, hi = (z0, z1) if side in (0, 2) else (x0, x1)
        a0, a1 = (lo if a0 - lo < 0.35 else max(a0, lo)), (hi if hi - a1 < 0.35 else min(a1, hi))
        depth = max(depth, 0.5)
        if side == 0:
            out.append(((x0 + depth / 2, (a0 + a1) / 2), (depth, a1 - a0), 0.0))
        elif side == 2:
            out.append(((x1 - depth / 2, (a0 + a1) / 2), (depth, a1 - a0), 0.0))
        elif side == 1:
            out.append((((a0 + a1) / 2, z0 + depth / 2), (a1 - a0, depth), 0.0))
        else:
            out.append((((a0 + a1) / 2, z1 - depth / 2), (a1 - a0, depth), 0.0))
    return out


def room_polygon(layout: Layout, version: int = GENERATOR_VERSION) -> Polygon:
    """The room's floor: :func:`outer_rect` minus :func:`alcoves`. From version 2, version 1's outline clipped
    to version 2's (inset) outer walls: the inset moves the outer walls and changes no alcove. (Version 1's
    outline keeps a quirk: a cut whose edge is flush with the rectangle's only up to rounding, as in FloorPlan18,
    223, 324 and 404, becomes a hole that the floor (the exterior) ignores. No dev scene tells whether those cuts are right, so version 2 keeps
    the outlines as they were.)"""
    if version >= 2:  # version 1's floor is its polygon's exterior (a cut left as a hole changed nothing)
        poly = Polygon(room_polygon(layout, 1).exterior).intersection(box(*outer_rect(layout, version)))
        if not isinstance(poly, Polygon):
            poly = max(poly.geoms, key=lambda g: g.area)
        return orient(poly.simplify(0), sign=1.0)
    rect = outer_rect(layout, version)
    poly = box(*rect)
    for c in alcoves(layout, rect):
        poly = poly.difference(box(*c))
    if not isinstance(poly, Polygon):  # cuts never split the rectangle in practice; keep the largest piece
        poly = max(poly.geoms, key=lambda g: g.area)
    return orient(poly.simplify(0), sign=1.0)


# ------------------------------------------------------------------------------------------------ scene
def _category_mats(category: str) -> dict:
    # Materials by category, the same in every scene, so RGB frames tell categories apart.
    rng = np.random.default_rng(zlib.crc32(f"tsnav-ithor-real|{category}".encode()))
    return materials_for(category, rng, EXTRA_ROLES.get(category))


def pivot(o: LayoutObject) -> tuple[float, float]:
    """The object's pivot ``(x, z)`` as its objectId records it (``Toilet|-01.84|+00.00|+02.50``), else the
    centre of its box."""
    parts = o.object_id.split("|")
    try:
        return float(parts[1]), float(parts[3])
    except (IndexError, ValueError):
        return o.aabb_center[0], o.aabb_center[2]


def toilet_box(o: LayoutObject) -> tuple[tuple[float, float], tuple[float, float], float] | None:
    """The footprint ``((cx, cz), (sx, sz), yaw)`` of a toilet whose recorded box is wider than
    :data:`TOILET_MAX_WIDTH` across the direction it faces (turned by a right angle; None otherwise): a
    :data:`TOILET_SIZE` box with its back on the recorded box's back face, centred across on the pivot."""
    ry = o.rotation[1] % 360
    k = round(ry / 90) % 4
    if abs(ry - 90 * round(ry / 90)) > 5:
        return None
    fx, fz = ((0, 1), (1, 0), (0, -1), (-1, 0))[k]  # the direction it faces: rotation 0 faces +z, 90 faces +x
    across = o.aabb_size[2] if fx else o.aabb_size[0]
    if across <= TOILET_MAX_WIDTH:
        return None
    w, d = TOILET_SIZE
    px, pz = pivot(o)
    if fx:  # back face at the box's x side opposite the facing direction
        back = o.aabb_min[0] if fx > 0 else o.aabb_max[0]
        return (back + fx * d / 2, pz), (w, d), 90.0 * k
    back = o.aabb_min[2] if fz > 0 else o.aabb_max[2]
    return (px, back + fz * d / 2), (w, d), 90.0 * k


def footprints(
    layout: Layout, o: LayoutObject, version: int = GENERATOR_VERSION
) -> list[tuple[tuple[float, float], tuple[float, float], float]]:
    """Floor-plane boxes ``((cx, cz), (sx, sz), yaw)`` of object ``o``: :func:`oriented_box`, or for a
    large counter :func:`counter_boxes`, or (from version 2) for an oversized toilet box :func:`toilet_box`."""
    if o.object_type == "CounterTop":
        return counter_boxes(layout, o, version)
    if o.object_type == "Toilet" and version >= 2:
        t = toilet_box(o)
        if t is not None:
            return [t]
    return [oriented_box(o)]


def sink_top(layout: Layout, o: LayoutObject) -> float:
    """Height at which a sink's rim is drawn: the top of its box, or of the counter around it when higher
    (the counter's body is drawn solid, so a sink below its top would be hidden)."""
    x, _, z = o.aabb_center
    tops = [
        c.aabb_max[1]
        for c in layout.objects
        if c.object_type == "CounterTop" and c.aabb_min[0] <= x <= c.aabb_max[0] and c.aabb_min[2] <= z <= c.aabb_max[2]
    ]
    return max([o.aabb_max[1], *tops]) + 0.003


def _parts_for(o: LayoutObject, fp, inst: int, fy: float, layout: Layout) -> list[Part]:
    (cx, cz), (sx, sz), yaw = fp
    y0, y1 = o.aabb_min[1], o.aabb_max[1]
    if o.object_type == "CounterTop":  # the record is the top slab; the counter's body stands on the floor
        y0 = fy
    mats = _category_mats(o.object_type)
    if o.object_type == "Sink":  # the record spans the cabinet under the sink: its body, the catalog's sink on top
        col, col2, pat, scale = mats["accent"]
        body = Part(
            (cx, (y0 + y1) / 2, cz),
            (max(sx, 0.01), max(y1 - y0, 0.01), max(sz, 0.01)),
            yaw,
            col,
            col2,
            pat,
            scale,
            inst,
        )
        top = sink_top(layout, o)
        return [body] + build_parts("Sink", (cx, top, cz), (sx, 0.25, sz), yaw, inst, np.random.default_rng(0), mats)
    size = (max(sx, 0.01), max(y1 - y0, 0.01), max(sz, 0.01))
    if o.object_type in CATALOG_SHAPES:
        return build_parts(o.object_type, (cx, y0, cz), size, yaw, inst, np.random.default_rng(0), mats)
    col, col2, pat, scale = mats["main"]
    return [Part((cx, y0 + size[1] / 2, cz), size, yaw, col, col2, pat, scale, inst)]


def _walls(spec: SceneSpec, poly: Polygon, inst: int, material) -> None:
    """Wall slabs along every edge of ``poly`` (outside it, so the interior is exactly the polygon)."""
    col, col2, pat, scale = material
    H = spec.wall_height
    pts = list(poly.exterior.coords)
    for (ax, az), (bx, bz) in zip(pts[:-1], pts[1:]):
        length = math.hypot(bx - ax, bz - az)
        if length < 1e-6:
            continue
        nx, nz = (bz - az) / length, -(bx - ax) / length  # right-hand normal: outwards for a CCW polygon
        mx, mz = (ax + bx) / 2 + nx * WALL_T / 2, (az + bz) / 2 + nz * WALL_T / 2
        yaw = math.degrees(math.atan2(-(bz - az), bx - ax))  # local +x along the edge
        spec.parts.append(Part((mx, H / 2, mz), (length + 2 * WALL_T, H, WALL_T), yaw, col, col2, pat, scale, inst))


def check_version(version: int | None) -> int:
    """``version`` of the ``ithor-real`` rules (None: the newest, :data:`GENERATOR_VERSION`); ValueError when unknown."""
    if version is None:
        return GENERATOR_VERSION
    if version not in VERSIONS:
        raise ValueError(f"unknown ithor-real version {version!r} (choose from {', '.join(map(str, VERSIONS))})")
    return int(version)


def real_spec(name: str, version: int | None = None) -> SceneSpec:
    """The :class:`SceneSpec` of real iTHOR scene ``name`` (``FloorPlan1``-``430``) from its packaged layout, by
    the rules of ``version`` (:data:`VERSIONS`; None: the newest)."""
    version = check_version(version)
    room_type, split = scene_info(name)
    if room_type == "apartment":
        raise ValueError(f"the ithor-real world has the 120 iTHOR single rooms, not {name!r}")
    return spec_from_layout(load_layout(name), room_type, split, version)


def spec_from_layout(layout: Layout, room_type: str, split: str, version: int | None = None) -> SceneSpec:
    """The :class:`SceneSpec` of one recorded layout: room outline, walls, and every object as parts of its
    recorded size, pose and category; objects of the 22 target classes keep their recorded objectId. The spec
    records the rules' version and (from version 2) the agent's clearance, :data:`CLEARANCE`."""
    version = check_version(version)
    name = layout.scene
    layout = on_floor(layout)
    fy = 0.0
    poly = room_polygon(layout, version)
    x0, z0, x1, z1 = poly.bounds
    top = max(o.aabb_max[1] for o in layout.objects if o.object_type != "Floor")
    spec = SceneSpec(
        name=name,
        room_type=room_type,
        split=split,
        seed=0,
        rooms=[{"type": room_type, "rect": [round(v, 4) for v in (x0, z0, x1, z1)]}],
        floor=[[[round(x, 4), round(z, 4)] for x, z in list(poly.exterior.coords)[:-1]]],
        wall_height=round(max(2.6, top + 0.1), 3),
        generator={"world": "ithor-real", "version": version},
        navigation={"clearance": CLEARANCE, "sweep_clearance": SWEEP_CLEARANCE} if version >= 2 else None,
    )
    spec.light = {"direction": [0.35, -2.5, 0.2], "ambient": 0.55, "diffuse": 0.42, "tint": [1.0, 0.98, 0.95]}
    rng = np.random.default_rng(zlib.crc32(f"tsnav-ithor-real|{name}".encode()))
    floor_inst, wall_inst, ceil_inst = spec.new_inst("Floor"), spec.new_inst("Wall"), spec.new_inst("Ceiling")
    floor_material = jitter(rng, *FLOORS[int(rng.integers(len(FLOORS)))])
    spec.parts += floor_and_ceiling((x0, z0, x1, z1), spec.wall_height, floor_material, floor_inst, ceil_inst)
    _walls(spec, poly, wall_inst, jitter(rng, *WALLS[int(rng.integers(len(WALLS)))]))
    own: dict[str, float] = {}
    for o in layout.objects:
        if o.object_type == "Floor":
            continue
        inst = spec.new_inst(o.object_id)
        block = blocks(o, fy, version=version)
        if block and version >= 2:
            c = min(
                low_clearance(o.aabb_max[1] - fy, CLEARANCE),
                SEAT_CLEARANCE if o.object_type in UPHOLSTERED else CLEARANCE,
            )
            if c < CLEARANCE:
                own[o.object_id] = round(c, 4)
        for (ox, oz), (sx, sz), yaw in footprints(layout, o, version):
            size = (round(sx, 4), round(o.aabb_size[1], 4), round(sz, 4))
            center = (round(ox, 4), round(o.aabb_min[1], 4), round(oz, 4))
            if o.object_type in TARGET_CATEGORIES:
                support = (
                    "floor" if block else ("wall" if o.object_type in WALL_FIXTURES or not o.parents else o.parents[0])
                )
                spec.objects.append(ObjectInstance(o.object_id, o.object_type, center, size, yaw, support, inst))
            else:  # a counter made of several runs gives several entries with its one id
                spec.furniture.append(Furniture(o.object_id, o.object_type, center, size, yaw, block, None, inst))
            spec.parts += _parts_for(o, ((ox, oz), (sx, sz), yaw), inst, fy, layout)
    if own:
        spec.navigation["clearances"] = own
    stove = stove_body(layout, version)
    if stove is not None:  # not a recorded object: its id says so
        (ox, oz), (sx, sz), yaw, top = stove
        sid = f"Stove|inferred|{ox:+.2f}|{oz:+.2f}"
        inst = spec.new_inst(sid)
        spec.furniture.append(
            Furniture(
                sid,
                "Stove",
                (round(ox, 4), 0.0, round(oz, 4)),
                (round(sx, 4), round(top, 4), round(sz, 4)),
                yaw,
                True,
                None,
                inst,
            )
        )
        spec.parts += build_parts(
            "Cabinet", (ox, 0.0, oz), (sx, top, sz), yaw, inst, np.random.default_rng(0), _category_mats("Stove")
        )
    return spec


def stove_body(layout: Layout, version: int = GENERATOR_VERSION):
    """The body under the stove burners, which the records lack (the burners float at counter height in
    26 of 30 kitchens): ``((cx, cz), (width, depth), yaw, height)`` of a box from the floor to the burners,
    over the burners and knobs not standing on a counter run, its front towards the knobs; None without them."""
    counters = [
        Polygon(box_footprint((c[0], 0, c[1]), (sz[0], 0, sz[1]), y))
        for o in layout.objects
        if o.object_type == "CounterTop"
        for c, sz, y in footprints(layout, o, version)
    ]

    def free(o: LayoutObject) -> bool:
        return not any(p.contains(Point(o.aabb_center[0], o.aabb_center[2])) for p in counters)

    burners = [o for o in layout.objects if o.object_type == "StoveBurner" and free(o)]
    if not burners:
        return None
    knobs = [o for o in layout.objects if o.object_type == "StoveKnob" and free(o)]
    parts = burners + knobs
    x0, z0 = min(o.aabb_min[0] for o in parts), min(o.aabb_min[2] for o in parts)
    x1, z1 = max(o.aabb_max[0] for o in parts), max(o.aabb_max[2] for o in parts)
    bx, bz = np.mean([o.aabb_center[0] for o in burners]), np.mean([o.aabb_center[2] for o in burners])
    kx, kz = (
        (np.mean([o.aabb_center[0] for o in knobs]), np.mean([o.aabb_center[2] for o in knobs]))
        if knobs
        else (bx, bz - 1)
    )
    yaw = (round(math.degrees(math.atan2(kx - bx, kz - bz)) / 90) * 90) % 360  # front (local +z) to the knobs
    w, d = (x1 - x0 + 0.1, z1 - z0 + 0.1) if yaw % 180 == 0 else (z1 - z0 + 0.1, x1 - x0 + 0.1)
    top = min(o.aabb_min[1] for o in burners)
    return ((x0 + x1) / 2, (z0 + z1) / 2), (w, d), float(yaw), top


__all__ = [
    "AGENT_HEIGHT",
    "WALL_FIXTURES",
    "alcoves",
    "blocks",
    "oriented_box",
    "outer_rect",
    "real_spec",
    "room_polygon",
]
