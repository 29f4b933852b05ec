"""The ``robothor-real`` world: RoboTHOR's 75 apartments rebuilt from their real records (issue 46).

Records (``data/robothor/``, copied unchanged from the sources its ``NOTICE`` names): a calibrated top-down plan
of every scene (``plans/``), the object metadata of the 60 train scenes (``train_objects.json.gz``, ai2thor
2.7.2 at reset) and the RoboTHOR ObjectNav 2021 challenge's val episodes (``challenge_episodes/val/``). No record
holds walls or the val scenes' objects; they are inferred, and every scene says what was inferred from what
(``scene.json`` ``generator``: ``walls`` and ``provenance``; inferred ids carry ``|inferred|``).

* **Walls and outline** (:mod:`tsnav.world.plans`): voted over the five plans of the apartment, the same for
  its five scenes. Outer walls bound the floor rectangle; interior walls are slabs :data:`WALL_THICKNESS` thick
  on the plan's line, as high as the outer walls.
* **Train scenes**: every recorded object, as ``ithor-real`` builds iTHOR's (:mod:`tsnav.world.real`: footprints
  from the oriented boxes, AI2-THOR's blocking rule, the same clearances).
* **Val scenes**: furniture footprints are the plan's non-floor blobs (:func:`~tsnav.world.plans.furniture_blobs`)
  cut into :data:`BAND`-pixel row bands, blocking, :data:`FURNITURE_HEIGHT` high (lower under an inferred object
  standing on them). Each of the 12 challenge target types present in the scene's val episodes is placed where
  its episodes' shortest paths end: rules version 2 (the default) fits its footprint, the type's median width and
  depth (:func:`type_extents`) at yaw 0 or 90, :data:`END_DISTANCE` from the ends (:func:`place_footprint`), and keeps
  a floor-standing target off the episodes' starts and ends; version 1 fitted its centre :data:`SUCCESS_RADIUS` from
  them (:func:`place_target`) at yaw 0 with the per-axis median size. It takes the median height above the floor of
  that type's records in the train scenes, and stands on the floor (blocking) when most of them do. Version 2 builds
  the train scenes exactly as version 1.
"""

from __future__ import annotations

import gzip
import json
import math
import zlib
from dataclasses import replace
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage
from shapely.geometry import box as shapely_box
from shapely.geometry.polygon import orient

from ..constants import ROBOTHOR12, TARGET_CATEGORIES
from ..data.names import scene_info
from . import plans as P
from .catalog import FLOORS, WALLS, build_parts, jitter
from .house import floor_and_ceiling
from .layouts import Layout, LayoutObject
from .real import (
    CATALOG_SHAPES,
    SEAT_CLEARANCE,
    SWEEP_CLEARANCE,
    UPHOLSTERED,
    WALL_FIXTURES,
    _category_mats,
    _parts_for,
    _walls,
    blocks,
    footprints,
    low_clearance,
)
from .spec import Furniture, ObjectInstance, Part, SceneSpec

#: The RoboTHOR ObjectNav challenge's 12 target types (the ``robothor12`` class set every scene of this world declares).
ROBOTHOR_TARGETS = ROBOTHOR12.categories
#: Object types kept as objects (visibility statistics, the visible object map): iTHOR's 22 and RoboTHOR's 12.
OBJECT_TYPES = frozenset(TARGET_CATEGORIES) | frozenset(ROBOTHOR_TARGETS)
#: Version of the ``robothor-real`` rules; each version's constants are in :data:`RULES`.
GENERATOR_VERSION = 2
VERSIONS = (1, 2)
WALL_THICKNESS = 0.02  #: interior walls and the outer walls' inset (half of it), metres
#: Clearance kept between the agent's centre and walls or blocking footprints, metres (the challenge's LoCoBot
#: agent is narrower than iTHOR's default agent: fitted to the train scenes' start positions, see docs/WORLD.md)
CLEARANCE = 0.14
WALL_HEIGHT = 2.5  #: walls' height, metres
FURNITURE_HEIGHT = 0.75  #: height of an inferred furniture blob, metres
#: Clearance kept from an inferred furniture blob, metres: the plan's furniture mask runs over the furniture's soft
#: edges and shadows (fitted on the train scenes rebuilt as val scenes are: 98.3 % of the starts kept at 0.14 m,
#: 98.7 % at 0.10 m, the path ratios unchanged)
INFERRED_CLEARANCE = 0.10
BAND = 3  #: rows of plan pixels per footprint box of an inferred furniture blob
#: Challenge train episodes a train scene rebuilt the val way (``tsnav world --infer-train-objects``) infers its
#: targets from: as many as a val scene has (1,800 val episodes over 15 scenes)
INFER_EPISODES = 120
SUCCESS_RADIUS = 1.0  #: the challenge's success distance: its shortest paths end this far from the target, m
FLOOR_COST = 0.25  #: placement cost of a candidate on open floor (no furniture blob) in the plan, metres^2
NEAR_COST = 1.0  #: placement cost of a target with all its paths' earlier points within the success radius, m^2
OFF_GRID = 5.0  #: degrees off a right angle beyond which a recorded object without oriented box is measured
MIN_TURNED_PX = 10  #: fewest plan pixels to measure a turned object's footprint from
#: Version 2: how far the challenge's shortest paths end from their target's box (horizontal distance to the box),
#: metres: the median over the train scenes' episodes and recorded objects (0.87; the ends lie between 0.75 and 1.0 m
#: of the box, the first grid position within the success radius). A val target's footprint is fitted to it.
END_DISTANCE = 0.87
#: Version 2: the yaws a val target's footprint is fitted at (its width along x, or along z)
FIT_YAWS = (0.0, 90.0)
RULES = {
    1: {
        "clearance": CLEARANCE,
        "inferred_clearance": INFERRED_CLEARANCE,
        "wall_thickness": WALL_THICKNESS,
        "wall_height": WALL_HEIGHT,
        "furniture_height": FURNITURE_HEIGHT,
        "band": BAND,
        "success_radius": SUCCESS_RADIUS,
        "floor_cost": FLOOR_COST,
        "near_cost": NEAR_COST,
        "off_grid": OFF_GRID,
        "min_turned_px": MIN_TURNED_PX,
        "plans": P.RULES[P.PLAN_VERSION],
    }
}
#: Version 2 changes the val scenes' targets only (the train scenes are built as in version 1): each is fitted by
#: its footprint (the type's median width and depth, at the better of :data:`FIT_YAWS`) so that its episodes' paths
#: end :data:`END_DISTANCE` from the footprint and come no closer than the success radius before, and a target that
#: stands on the floor (and blocks) keeps clear of every start and path end of the scene's episodes (version 1 fitted
#: its centre at the success radius and took the per-axis median size at yaw 0).
RULES[2] = {
    **RULES[1],
    "placement": "footprint",
    "end_distance": END_DISTANCE,
    "fit_yaws": list(FIT_YAWS),
    "blocking_targets_keep_clear": "the episodes' starts and path ends",
}
RECORDS = "train_objects.json.gz (ai2thor 2.7.2 metadata at reset)"


def _data():
    return resources.files("tsnav.world") / "data" / "robothor"


def apartment(name: str) -> str:
    """``FloorPlan_Train3_2`` -> ``Train3``."""
    return name.split("_")[1]


@lru_cache(maxsize=80)
def load_plan(name: str) -> np.ndarray:
    """The ``(300, 300, 3)`` uint8 plan of scene ``name``."""
    ref = _data() / "plans" / f"{name}.png"
    with ref.open("rb") as f:
        return np.asarray(Image.open(f).convert("RGB"))


@lru_cache(maxsize=16)
def apartment_walls(apt: str) -> P.WallPlan:
    """The walls of apartment ``apt`` (``Train3``), voted over its five plans."""
    return P.infer_walls([load_plan(f"FloorPlan_{apt}_{k}") for k in range(1, 6)])


@lru_cache(maxsize=16)
def apartment_static(apt: str) -> np.ndarray:
    """Pixels that look the same in the five plans of apartment ``apt`` (:func:`~tsnav.world.plans.static_mask`)."""
    return P.static_mask([load_plan(f"FloorPlan_{apt}_{k}") for k in range(1, 6)])


@lru_cache(maxsize=1)
def train_records() -> dict:
    """``{scene: {objectType: {index: object dict}}}`` of the 60 train scenes."""
    with (_data() / "train_objects.json.gz").open("rb") as f:
        return json.loads(gzip.decompress(f.read()))


@lru_cache(maxsize=16)
def val_episodes(name: str) -> list[dict]:
    """The challenge's val episodes of scene ``name``."""
    with (_data() / "challenge_episodes" / "val" / f"{name}.json.gz").open("rb") as f:
        return json.loads(gzip.decompress(f.read()))


def layout_object(o: dict) -> LayoutObject:
    """One record of ``train_objects.json.gz`` as a :class:`~tsnav.world.layouts.LayoutObject`."""
    a = o["axisAlignedBoundingBox"]
    c, s = a["center"], a["size"]
    oobb = (o.get("objectOrientedBoundingBox") or {}).get("cornerPoints")
    r = o.get("rotation") or {"x": 0, "y": 0, "z": 0}
    return LayoutObject(
        o["objectId"],
        o["objectType"],
        (c["x"], c["y"], c["z"]),
        (s["x"], s["y"], s["z"]),
        None if not oobb else tuple(tuple(map(float, p)) for p in oobb),
        (r["x"], r["y"], r["z"]),
        tuple(o.get("parentReceptacles") or ()),
        bool(o.get("receptacle")),
        bool(o.get("pickupable")),
        bool(o.get("moveable")),
        bool(o.get("openable")),
        bool(o.get("isOpen")),
        bool(o.get("visible")),
    )


def scene_layout(name: str) -> Layout:
    """The recorded objects of train scene ``name`` (sorted by objectId)."""
    recs = train_records().get(name)
    if recs is None:
        raise ValueError(f"no recorded objects for {name!r} (only the 60 train scenes have them)")
    objs = [layout_object(o) for per in recs.values() for o in per.values()]
    return Layout(name, tuple(sorted(objs, key=lambda o: o.object_id)))


@lru_cache(maxsize=1)
def type_stats() -> dict[str, dict]:
    """Per object type, over the train scenes' records: median box size (x, y, z), median bottom height above
    the floor of those not on the floor, share on the floor, and the record count (what an inferred object of the
    type takes)."""
    acc: dict[str, list] = {}
    for scene in train_records().values():
        for t, per in scene.items():
            for o in per.values():
                acc.setdefault(t, []).append(layout_object(o))
    out = {}
    for t, objs in acc.items():
        size = np.median([o.aabb_size for o in objs], axis=0)
        floor = [not o.parents for o in objs]
        raised = [o.aabb_min[1] for o in objs if o.parents]
        out[t] = {
            "size": [round(float(v), 3) for v in size],
            "floor_share": round(float(np.mean(floor)), 3),
            "bottom": round(float(np.median(raised)), 3) if raised else 0.0,
            "records": len(objs),
        }
    return out


@lru_cache(maxsize=1)
def type_extents() -> dict[str, tuple[float, float]]:
    """Per object type, the median ``(width, depth)`` of the train scenes' records: the larger and the smaller of the
    box's horizontal sides (a television 1.16 x 0.33 m whichever way it faces; :func:`type_stats` takes the median of
    x and of z, which mixes the two for a type that stands either way)."""
    acc: dict[str, list] = {}
    for scene in train_records().values():
        for t, per in scene.items():
            for o in per.values():
                sx, sz = o["axisAlignedBoundingBox"]["size"]["x"], o["axisAlignedBoundingBox"]["size"]["z"]
                acc.setdefault(t, []).append((max(sx, sz), min(sx, sz)))
    return {
        t: (round(float(np.median([w for w, _ in v])), 3), round(float(np.median([d for _, d in v])), 3))
        for t, v in acc.items()
    }


# ------------------------------------------------------------------------------------------- walls
def _wall_box(seg: P.Segment) -> tuple[float, float, float, float]:
    """``(cx, cz, sx, sz)`` of an interior wall slab on segment ``seg``."""
    if seg.axis == 0:
        x0, z = P.pixel_to_world(seg.line, seg.a0 - 0.5)
        x1, _ = P.pixel_to_world(seg.line, seg.a1 + 0.5)
        return (x0 + x1) / 2, z, x1 - x0, WALL_THICKNESS
    x, z0 = P.pixel_to_world(seg.a1 + 0.5, seg.line)
    _, z1 = P.pixel_to_world(seg.a0 - 0.5, seg.line)
    return x, (z0 + z1) / 2, WALL_THICKNESS, z1 - z0


def floor_rect(walls: P.WallPlan) -> tuple[float, float, float, float]:
    """``(x0, z0, x1, z1)`` of the floor: the outer walls' centre lines moved in by half a wall."""
    top, left, bottom, right = walls.outline
    x0, z1 = P.pixel_to_world(top, left)
    x1, z0 = P.pixel_to_world(bottom, right)
    h = WALL_THICKNESS / 2
    return round(x0 + h, 4), round(z0 + h, 4), round(x1 - h, 4), round(z1 - h, 4)


# ------------------------------------------------------------------------------------------- val inference
def blob_boxes(blob: tuple[int, int, int, int, int], mask: np.ndarray) -> list[tuple[float, float, float, float]]:
    """World boxes ``(x0, z0, x1, z1)`` of one furniture blob: its pixels of ``mask`` in its bounding box, cut into
    :data:`BAND`-row bands, each band one box per run of columns it covers (a hole, such as the place of a
    floor-standing target cut out of its blob, stays open)."""
    r0, c0, r1, c1, _ = blob
    out = []
    for a in range(r0, r1 + 1, BAND):
        b = min(a + BAND - 1, r1)
        for s0, s1 in P.runs_1d(mask[a : b + 1, c0 : c1 + 1].any(axis=0), max_gap=0, min_run=1):
            xa, zb = P.pixel_to_world(b + 0.5, c0 + s0 - 0.5)
            xb, za = P.pixel_to_world(a - 0.5, c0 + s1 + 0.5)
            out.append((xa, zb, xb, za))
    return out


def path_samples(path: list[dict], step: float = 0.1, stop_before: float = 0.15) -> np.ndarray:
    """``(n, 2)`` points every ``step`` m along a challenge shortest path (its corner points ``{x, y, z}``), up to
    ``stop_before`` m before its end: where the path had not yet come within the success radius of its target."""
    pts = np.array([[p["x"], p["z"]] for p in path], dtype=np.float64).reshape(-1, 2)
    if len(pts) < 2:
        return np.zeros((0, 2))
    seg = np.hypot(*np.diff(pts, axis=0).T)
    cum = np.r_[0.0, np.cumsum(seg)]
    at = np.arange(0.0, cum[-1] - stop_before, step)
    if len(at) == 0:
        return np.zeros((0, 2))
    return np.stack([np.interp(at, cum, pts[:, 0]), np.interp(at, cum, pts[:, 1])], axis=1)


def place_target(
    ends: np.ndarray, before: np.ndarray, furniture: np.ndarray, inside: np.ndarray
) -> tuple[float, float, float]:
    """Where a target stands, from the challenge's episodes of its type in one scene: the plan pixel that best
    fits ``ends`` ((n, 2) x, z where the shortest paths end, about :data:`SUCCESS_RADIUS` from the target):
    cost = mean squared difference of the end distances from :data:`SUCCESS_RADIUS`, + :data:`FLOOR_COST` on a
    pixel that is not furniture (``furniture``, (H, W) bool), + :data:`NEAR_COST` times the share of ``before``
    (points of the paths before their ends, :func:`path_samples`) within the radius; candidates are the ``inside``
    pixels. Returns ``(x, z, cost)``."""
    rr, cc = np.nonzero(inside)
    xs, zs = P.pixel_to_world(rr.astype(float), cc.astype(float))
    d = np.hypot(xs[:, None] - ends[None, :, 0], zs[:, None] - ends[None, :, 1])
    cost = ((d - SUCCESS_RADIUS) ** 2).mean(axis=1)
    cost += FLOOR_COST * ~furniture[rr, cc]
    if len(before):
        near = np.zeros(len(xs))
        for a in range(0, len(before), 256):  # chunks keep the (pixels, samples) table small
            b = before[a : a + 256]
            near += (np.hypot(xs[:, None] - b[None, :, 0], zs[:, None] - b[None, :, 1]) < SUCCESS_RADIUS - 0.05).sum(1)
        cost += NEAR_COST * near / len(before)
    k = int(np.argmin(cost))
    return float(xs[k]), float(zs[k]), float(cost[k])


def box_distance_2d(xs: np.ndarray, zs: np.ndarray, px: np.ndarray, pz: np.ndarray, hx: float, hz: float) -> np.ndarray:
    """``(len(xs), len(px))``: horizontal distance from the points ``(px, pz)`` to the axis-aligned rectangles of half
    sides ``hx, hz`` centred on ``(xs, zs)`` (0 inside)."""
    dx = np.maximum(np.abs(xs[:, None] - px[None, :]) - hx, 0.0)
    dz = np.maximum(np.abs(zs[:, None] - pz[None, :]) - hz, 0.0)
    return np.hypot(dx, dz)


def place_footprint(
    ends: np.ndarray,
    before: np.ndarray,
    furniture: np.ndarray,
    inside: np.ndarray,
    extent: tuple[float, float],
    keep_clear: np.ndarray | None = None,
) -> tuple[float, float, float, float]:
    """Version 2 of :func:`place_target`: where a target of horizontal ``extent`` (width, depth) stands, fitted by
    its footprint. For each of :data:`FIT_YAWS` (yaw 0: the width along x) and each ``inside`` pixel: cost = mean
    squared difference of the ends' distances to the footprint from :data:`END_DISTANCE`, + :data:`FLOOR_COST` on a
    pixel that is not ``furniture``, + :data:`NEAR_COST` times the share of ``before`` within the success radius of
    the footprint (a path that came within it earlier would have ended there). ``keep_clear`` ((n, 2) x, z, for a
    target that blocks): places whose footprint, grown by :data:`CLEARANCE`, holds one of these points are ruled
    out (they are positions the challenge's agent stood on). Returns ``(x, z, yaw, cost)`` of the cheapest (the first
    yaw on a tie)."""
    rr, cc = np.nonzero(inside)
    xs, zs = P.pixel_to_world(rr.astype(float), cc.astype(float))
    w, d = extent
    best = None
    for yaw in FIT_YAWS:
        hx, hz = (w / 2, d / 2) if yaw % 180 == 0 else (d / 2, w / 2)
        cost = ((box_distance_2d(xs, zs, ends[:, 0], ends[:, 1], hx, hz) - END_DISTANCE) ** 2).mean(axis=1)
        cost += FLOOR_COST * ~furniture[rr, cc]
        if len(before):
            near = np.zeros(len(xs))
            for a in range(0, len(before), 256):  # chunks keep the (pixels, samples) table small
                b = before[a : a + 256]
                near += (box_distance_2d(xs, zs, b[:, 0], b[:, 1], hx, hz) < SUCCESS_RADIUS - 0.05).sum(1)
            cost += NEAR_COST * near / len(before)
        if keep_clear is not None and len(keep_clear):
            blocked = np.zeros(len(xs), bool)
            for a in range(0, len(keep_clear), 256):
                b = keep_clear[a : a + 256]
                blocked |= (box_distance_2d(xs, zs, b[:, 0], b[:, 1], hx + CLEARANCE, hz + CLEARANCE) <= 0).any(1)
            if not blocked.all():
                cost[blocked] = np.inf
        k = int(np.argmin(cost))
        if best is None or cost[k] < best[3]:
            best = (float(xs[k]), float(zs[k]), float(yaw), float(cost[k]))
    return best


def _inside_mask(walls: P.WallPlan, shape) -> np.ndarray:
    t, l, b, r = (int(round(v)) for v in walls.outline)
    m = np.zeros(shape, bool)
    m[t + 2 : b - 1, l + 2 : r - 1] = True
    return m & ~P.wall_mask(shape, walls, pad=1)


# ------------------------------------------------------------------------------------------- scene
def check_version(version: int | None) -> int:
    """``version`` of the ``robothor-real`` rules (None: the newest); ValueError when unknown."""
    if version is None:
        return GENERATOR_VERSION
    if version not in VERSIONS:
        raise ValueError(f"unknown robothor-real version {version!r} (choose from {', '.join(map(str, VERSIONS))})")
    return int(version)


def train_episodes_file(challenge: str | Path, name: str) -> Path:
    """Where the challenge's episode folder ``challenge`` holds the train episodes of scene ``name``."""
    return Path(challenge) / "train" / f"{name}.json.gz"


def missing_train_episodes(challenge: str | Path, names) -> str | None:
    """Why the train scenes among ``names`` cannot be rebuilt the val way from the challenge's episode folder
    ``challenge`` (no ``train/`` folder, or a scene without its episode file), in one line; None when they can."""
    from ..data.names import scene_info

    if not (Path(challenge) / "train").is_dir():
        return "no train/ folder of challenge episodes"
    for n in names:
        f = train_episodes_file(challenge, n)
        if scene_info(n)[1] == "train" and not f.is_file():
            return f"no challenge train episodes of {n} ({f})"
    return None


def inferred_train_episodes(challenge: str | Path, name: str, n: int = INFER_EPISODES) -> list[dict]:
    """The challenge's train episodes a train scene rebuilt the val way infers its targets from: ``n`` of those of
    scene ``name`` in ``challenge/train/NAME.json.gz`` (the first after a shuffle seeded by the name; all when
    fewer). ``ValueError`` naming the file when it is missing or unreadable."""
    path = train_episodes_file(challenge, name)
    try:
        eps = json.loads(gzip.decompress(path.read_bytes()))
    except (OSError, ValueError, EOFError) as e:
        raise ValueError(f"{path}: cannot read the challenge's train episodes of {name} ({e})") from None
    order = np.random.default_rng(zlib.crc32(name.encode())).permutation(len(eps))
    return [eps[i] for i in order[:n]]


def surface_seed(name: str, seed: int = 0) -> int:
    """The seed scene ``name`` draws its floor and wall materials with: ``seed`` for a train apartment, 0 for a val
    one (the val apartments are the benchmark: their surfaces never change)."""
    if seed < 0:
        raise ValueError(f"the surface seed must be 0 or more, got {seed}")
    return seed if scene_info(name)[1] == "train" else 0


def surface_rng(name: str, seed: int = 0) -> np.random.Generator:
    """The generator that draws scene ``name``'s floor and wall materials (``seed``: :func:`surface_seed`'s). Seed 0
    is the benchmark's draw: one per apartment, so its five variants share their surfaces. Any other seed draws them
    per scene (the variants then differ): more surfaces for a detector to learn than the twelve train apartments'
    draws, which a detector otherwise learns as part of what a target is."""
    key = f"tsnav-robothor-real|{apartment(name)}" if seed == 0 else f"tsnav-robothor-real|{name}|surfaces {seed}"
    return np.random.default_rng(zlib.crc32(key.encode()))


def robothor_spec(
    name: str, version: int | None = None, infer_train: str | Path | None = None, seed: int = 0
) -> SceneSpec:
    """The :class:`SceneSpec` of RoboTHOR scene ``name`` (``FloorPlan_Train1_1`` ... ``FloorPlan_Val3_5``) by the
    rules of ``version`` (module docstring). ``infer_train``: the challenge's episode folder; a train scene is then
    rebuilt the way the val ones are (furniture from the plan, targets inferred from :data:`INFER_EPISODES` of its
    challenge train episodes, :func:`inferred_train_episodes`), its object records left out. ``seed``: the draw of
    a train apartment's floor and wall materials (:func:`surface_seed`; the val apartments keep 0's, the benchmark's);
    nothing else depends on it."""
    version = check_version(version)
    room_type, split = scene_info(name)
    if room_type != "apartment":
        raise ValueError(f"the robothor-real world has the 75 RoboTHOR apartments, not {name!r}")
    walls = apartment_walls(apartment(name))
    x0, z0, x1, z1 = floor_rect(walls)
    poly = orient(shapely_box(x0, z0, x1, z1), sign=1.0)
    wall_src = (
        f"inferred from the 5 plans of {apartment(name)} (plans/FloorPlan_{apartment(name)}_1..5.png; "
        f"tsnav.world.plans rules v{P.PLAN_VERSION})"
    )
    spec = SceneSpec(
        name=name,
        room_type=room_type,
        split=split,
        seed=0,
        rooms=[{"type": room_type, "rect": [x0, z0, x1, z1]}],
        floor=[[[round(x, 4), round(z, 4)] for x, z in list(poly.exterior.coords)[:-1]]],
        wall_height=WALL_HEIGHT,
        generator={
            "world": "robothor-real",
            "version": version,
            "walls": {
                "source": wall_src,
                **walls.to_json(),
                "thickness": WALL_THICKNESS,
                "interior_walls": len(walls.interior),
            },
        },
        navigation={"clearance": CLEARANCE, "sweep_clearance": SWEEP_CLEARANCE},
        class_set=ROBOTHOR12.name,
    )
    spec.light = {"direction": [0.35, -2.5, 0.2], "ambient": 0.55, "diffuse": 0.42, "tint": [1.0, 0.98, 0.95]}
    seed = surface_seed(name, seed)
    rng = surface_rng(name, seed)
    if seed:
        spec.generator["surface_seed"] = int(seed)
    floor_inst, wall_inst, ceil_inst = spec.new_inst("Floor"), spec.new_inst("Wall"), spec.new_inst("Ceiling")
    spec.parts += floor_and_ceiling(
        (x0, z0, x1, z1), spec.wall_height, jitter(rng, *FLOORS[int(rng.integers(len(FLOORS)))]), floor_inst, ceil_inst
    )
    wall_mat = jitter(rng, *WALLS[int(rng.integers(len(WALLS)))])
    _walls(spec, poly, wall_inst, wall_mat)
    col, col2, pat, scale = wall_mat
    for seg in walls.interior:
        cx, cz, sx, sz = _wall_box(seg)
        spec.parts.append(Part((cx, WALL_HEIGHT / 2, cz), (sx, WALL_HEIGHT, sz), 0.0, col, col2, pat, scale, wall_inst))
    if split == "train" and infer_train is not None:
        provenance = _inferred_objects(
            spec, name, walls, inferred_train_episodes(infer_train, name), version, source="train"
        )
        spec.generator["train_objects"] = "inferred"
    elif split == "train":
        provenance = _recorded_objects(spec, scene_layout(name), P.furniture_mask(load_plan(name), walls))
    else:
        provenance = _inferred_objects(spec, name, walls, val_episodes(name), version)
    spec.generator["provenance"] = provenance
    return spec


def turned_box(o: LayoutObject, furniture: np.ndarray):
    """The footprint ``((cx, cz), (sx, sz), yaw)`` of a recorded object turned off the grid (by more than
    :data:`OFF_GRID` degrees) that has no oriented box (ai2thor 2.7.2 records one for pickupable objects only), so
    its axis-aligned box holds much floor: the sizes along its own axes are the extents (2nd to 98th percentile)
    of the plan's furniture pixels (``furniture``) inside its box, centred on the box, at the recorded yaw, no
    larger than the box allows. None when the object is on the grid, has an oriented box, or the plan shows fewer
    than :data:`MIN_TURNED_PX` furniture pixels there."""
    ry = o.rotation[1] % 360
    if o.oobb is not None or abs(ry - 90 * round(ry / 90)) <= OFF_GRID:
        return None
    (x0, _, z0), (x1, _, z1) = o.aabb_min, o.aabb_max
    r_hi, c_lo = P.world_to_pixel(x0, z0)
    r_lo, c_hi = P.world_to_pixel(x1, z1)
    rr, cc = np.nonzero(
        furniture[
            max(int(np.ceil(r_lo)), 0) : int(np.floor(r_hi)) + 1, max(int(np.ceil(c_lo)), 0) : int(np.floor(c_hi)) + 1
        ]
    )
    if len(rr) < MIN_TURNED_PX:
        return None
    xs, zs = P.pixel_to_world(rr + max(int(np.ceil(r_lo)), 0), cc + max(int(np.ceil(c_lo)), 0))
    cx, cz = o.aabb_center[0], o.aabb_center[2]
    t = math.radians(ry)
    u = (xs - cx) * math.cos(t) - (zs - cz) * math.sin(t)  # local +x = (cos yaw, -sin yaw) in (x, z)
    v = (xs - cx) * math.sin(t) + (zs - cz) * math.cos(t)  # local +z = (sin yaw, cos yaw)
    w = 2 * max(abs(np.percentile(u, 2)), abs(np.percentile(u, 98))) + P.PIXEL
    d = 2 * max(abs(np.percentile(v, 2)), abs(np.percentile(v, 98))) + P.PIXEL
    c, s_ = abs(math.cos(t)), abs(math.sin(t))
    scale = min(1.0, o.aabb_size[0] / (w * c + d * s_), o.aabb_size[2] / (w * s_ + d * c))
    return (cx, cz), (w * scale, d * scale), round(ry, 3)


def surface_tops(layout: Layout) -> dict[str, float]:
    """Per receptacle objectId, the lowest bottom of the recorded objects resting on it (their first
    ``parentReceptacles``), metres, where that lies below the receptacle's box top: its box holds more than the
    surface (a table's rim, a lamp standing on it), and drawn solid to the box top it would hide what rests on it."""
    low: dict[str, float] = {}
    for o in layout.objects:
        if o.parents:
            low[o.parents[0]] = min(low.get(o.parents[0], math.inf), o.aabb_min[1])
    out = {}
    for o in layout.objects:
        b = low.get(o.object_id)
        if b is not None and o.aabb_min[1] + 0.05 < b < o.aabb_max[1] - 0.01:
            out[o.object_id] = round(b, 4)
    return out


def _drawn(o: LayoutObject, top: float | None) -> LayoutObject:
    """``o`` with its box cut at height ``top`` (None: as recorded), for drawing only."""
    if top is None:
        return o
    y0 = o.aabb_min[1]
    return replace(
        o,
        aabb_center=(o.aabb_center[0], (y0 + top) / 2, o.aabb_center[2]),
        aabb_size=(o.aabb_size[0], top - y0, o.aabb_size[2]),
    )


def _recorded_objects(spec: SceneSpec, layout: Layout, furniture: np.ndarray) -> dict:
    own: dict[str, float] = {}
    turned = []
    tops = surface_tops(layout)
    for o in layout.objects:
        inst = spec.new_inst(o.object_id)
        block = blocks(o, 0.0)
        if block:
            c = min(
                low_clearance(o.aabb_max[1], CLEARANCE), SEAT_CLEARANCE if o.object_type in UPHOLSTERED else CLEARANCE
            )
            if c < CLEARANCE:
                own[o.object_id] = round(c, 4)
        fps = footprints(layout, o)
        tb = turned_box(o, furniture)
        if tb is not None:
            fps = [tb]
            turned.append(o.object_id)
        for (ox, oz), (sx, sz), yaw in fps:
            size = (round(sx, 4), round(o.aabb_size[1], 4), round(sz, 4))
            center = (round(ox, 4), round(o.aabb_min[1], 4), round(oz, 4))
            if o.object_type in OBJECT_TYPES:
                support = (
                    "floor" if block else ("wall" if o.object_type in WALL_FIXTURES or not o.parents else o.parents[0])
                )
                spec.objects.append(ObjectInstance(o.object_id, o.object_type, center, size, yaw, support, inst))
            else:
                spec.furniture.append(Furniture(o.object_id, o.object_type, center, size, yaw, block, None, inst))
            spec.parts += _parts_for(_drawn(o, tops.get(o.object_id)), ((ox, oz), (sx, sz), yaw), inst, 0.0, layout)
    if own:
        spec.navigation["clearances"] = own
    return {
        "recorded": len(layout.objects),
        "inferred": 0,
        "objects": RECORDS,
        "inferred_objects": {},
        "drawn_to_surface": {i: f"drawn up to {t} m, the lowest object resting on it" for i, t in tops.items()},
        "footprints_from_plan": {
            i: "recorded box and yaw, sizes along its axes from the plan's furniture pixels (turned_box)"
            for i in turned
        },
    }


def _inferred_objects(
    spec: SceneSpec, name: str, walls: P.WallPlan, eps: list[dict], version: int, source: str = "val"
) -> dict:
    plan = load_plan(name)
    mask = P.furniture_mask(plan, walls)
    opened = ndimage.binary_opening(mask, structure=np.ones((3, 3), bool))
    inside = _inside_mask(walls, plan.shape[:2])
    stats = type_stats()
    inferred: dict[str, str] = {}
    # Targets first: furniture under them is drawn no higher than their bottom.
    # Targets in order of how well their episodes fix them (lowest fit cost first); a target is not put where it
    # would overlap one placed before it (its disc, the half diagonal of its size, off theirs).
    extents = type_extents()
    # Version 2: where the challenge's agent stood (every start and every path end of the scene's episodes): a target
    # that blocks is not put on them.
    stood = np.array(
        [[e["initial_position"]["x"], e["initial_position"]["z"]] for e in eps]
        + [[e["shortest_path"][-1]["x"], e["shortest_path"][-1]["z"]] for e in eps if e.get("shortest_path")]
    ).reshape(-1, 2)

    def fit(t: str, ends: np.ndarray, before: np.ndarray, where: np.ndarray) -> tuple[float, float, float, float]:
        """(x, z, yaw, cost) of type ``t``'s target by the rules of ``version``."""
        if version == 1:
            # yaw 0: the records give no hint (facing the paths' ends was tried: no closer paths)
            x, z, cost = place_target(ends, before, opened, where)
            return x, z, 0.0, cost
        on_floor = stats.get(t, {}).get("floor_share", 0.0) > 0.5
        return place_footprint(ends, before, opened, where, extents.get(t, (0.2, 0.2)), stood if on_floor else None)

    fits = []
    for t in sorted({e["object_type"] for e in eps}):
        mine = [e for e in eps if e["object_type"] == t]
        ends = np.array([[e["shortest_path"][-1]["x"], e["shortest_path"][-1]["z"]] for e in mine])
        before = np.concatenate([path_samples(e["shortest_path"]) for e in mine] + [np.zeros((0, 2))])
        fits.append((fit(t, ends, before, inside)[3], t, mine, ends, before))
    rr, cc = np.mgrid[0 : plan.shape[0], 0 : plan.shape[1]]
    px_x, px_z = P.pixel_to_world(rr.astype(float), cc.astype(float))
    placed: list[tuple[float, float, float]] = []  # x, z, half diagonal
    targets = []
    for _, t, mine, ends, before in sorted(fits, key=lambda f: (f[0], f[1])):
        st = stats.get(t, {"size": [0.2, 0.2, 0.2], "floor_share": 0.0, "bottom": 0.5, "records": 0})
        if version == 1:
            size = tuple(round(v, 4) for v in st["size"])
        else:  # width and depth in the object's own frame (type_extents), its yaw from the fit
            w, d = extents.get(t, (0.2, 0.2))
            size = (round(w, 4), round(st["size"][1], 4), round(d, 4))
        half = math.hypot(size[0], size[2]) / 2
        free = inside.copy()
        for px, pz, ph in placed:
            free &= np.hypot(px_x - px, px_z - pz) > ph + half
        x, z, yaw, cost = fit(t, ends, before, free if free.any() else inside)
        on_floor = st["floor_share"] > 0.5
        bottom = 0.0 if on_floor else st["bottom"]
        oid = f"{t}|inferred|{x:+.2f}|{z:+.2f}"
        targets.append((oid, t, x, z, bottom, size, on_floor, yaw))
        placed.append((x, z, half))
        ex, ez = (size[0], size[2]) if yaw % 180 == 0 else (size[2], size[0])
        if on_floor:  # the blob under a floor-standing target is the target itself: it is not furniture
            opened &= ~((np.abs(px_x - x) <= ex / 2 + P.PIXEL) & (np.abs(px_z - z) <= ez / 2 + P.PIXEL))
        if version == 1:
            inferred[oid] = (
                f"placed where the {len(mine)} challenge {source} episodes of {t} end {SUCCESS_RADIUS} m away "
                f"(fit cost {cost:.3f} m^2, off the targets placed before it); size and height: median of "
                f"{st['records']} train records of {t}{', on the floor' if on_floor else ''}"
            )
        else:
            inferred[oid] = (
                f"placed so that the {len(mine)} challenge {source} episodes of {t} end {END_DISTANCE} m from its "
                f"footprint, none earlier within {SUCCESS_RADIUS} m (yaw {yaw:.0f}, fit cost {cost:.3f} m^2, off the "
                f"targets placed before it); width, depth and height: median of {st['records']} train records of "
                f"{t}{', on the floor' if on_floor else ''}"
            )
    lab, n = ndimage.label(opened)
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    static = apartment_static(apartment(name))
    fixtures = 0
    for k, sl in enumerate(ndimage.find_objects(lab), start=1):
        if sl is None or sizes[k] < P.MIN_BLOB:
            continue
        if static[sl][lab[sl] == k].mean() >= P.STATIC_SHARE or P.is_lamp(
            int(sizes[k]), plan[sl][lab[sl] == k].mean(axis=0)
        ):
            fixtures += 1
            continue
        blob = (sl[0].start, sl[1].start, sl[0].stop - 1, sl[1].stop - 1, int(sizes[k]))
        boxes = blob_boxes(blob, lab == k)
        if not boxes:
            continue
        bx0, bz0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
        bx1, bz1 = max(b[2] for b in boxes), max(b[3] for b in boxes)
        height = FURNITURE_HEIGHT
        for _, _, x, z, bottom, _, on_floor, _ in targets:
            if not on_floor and bx0 <= x <= bx1 and bz0 <= z <= bz1:
                height = min(height, max(bottom, 0.05))
        fid = f"Furniture|inferred|{(bx0 + bx1) / 2:+.2f}|{(bz0 + bz1) / 2:+.2f}"
        inst = spec.new_inst(fid)
        col, col2, pat, scale = _category_mats("Furniture")["main"]
        for xa, za, xb, zb in boxes:
            c = (round((xa + xb) / 2, 4), 0.0, round((za + zb) / 2, 4))
            s = (round(xb - xa, 4), round(height, 4), round(zb - za, 4))
            spec.furniture.append(Furniture(fid, "Furniture", c, s, 0.0, True, round(height, 4), inst))
            spec.parts.append(Part((c[0], height / 2, c[2]), s, 0.0, col, col2, pat, scale, inst))
        spec.navigation.setdefault("clearances", {})[fid] = INFERRED_CLEARANCE
        inferred[fid] = (
            f"plan blob of {blob[4]} px (plans/{name}.png, tsnav.world.plans rules v{P.PLAN_VERSION}), "
            f"{len(boxes)} band boxes, height {height:.2f} m assumed"
        )
    for oid, t, x, z, bottom, size, on_floor, yaw in targets:
        inst = spec.new_inst(oid)
        center = (round(x, 4), round(bottom, 4), round(z, 4))
        spec.objects.append(
            ObjectInstance(oid, t, center, size, yaw, "floor" if on_floor else "inferred furniture", inst)
        )
        if t in CATALOG_SHAPES:
            spec.parts += build_parts(t, (x, bottom, z), size, yaw, inst, np.random.default_rng(0), _category_mats(t))
        else:
            col, col2, pat, scale = _category_mats(t)["main"]
            spec.parts.append(Part((x, bottom + size[1] / 2, z), size, yaw, col, col2, pat, scale, inst))
    return {
        "recorded": 0,
        "inferred": len(inferred),
        "objects": "inferred (val scenes have no object records)"
        if source == "val"
        else f"inferred as a val scene's are, from {len(eps)} challenge train episodes (the records left out)",
        "fixture_blobs_left_out": fixtures,
        "inferred_objects": inferred,
    }


__all__ = [
    "GENERATOR_VERSION",
    "OBJECT_TYPES",
    "ROBOTHOR_TARGETS",
    "VERSIONS",
    "apartment_walls",
    "check_version",
    "floor_rect",
    "place_footprint",
    "place_target",
    "robothor_spec",
    "type_extents",
    "type_stats",
]
