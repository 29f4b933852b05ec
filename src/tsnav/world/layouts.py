"""The recorded object layouts of the 120 real iTHOR scenes: reader, validator and package-data file.

Source files (``FloorPlan*.json``, one per scene, see ``NOTICE`` next to the packed file) hold every object of
a scene as ai2thor 5 reports it at reset: ``{"scene": NAME, "objects": [{objectId, objectType, position,
rotation, aabb, oobbCorners, parentReceptacles, receptacle, pickupable, moveable, openable, isOpen, visible,
...}]}``. :func:`read_layout_file` checks one such file and turns it into a :class:`Layout`; a malformed file
raises :class:`LayoutError` with one line naming the file, the object and the problem.

The package ships all 120 layouts in one gzipped JSON file (``data/ithor_layouts.json.gz``), the fields the
world builder needs rounded to the millimetre; :func:`pack_layouts` writes it from a folder of source files
(``python -m tsnav.world.layouts SRC_DIR``) and :func:`load_layout` reads one scene from it. No network.
"""

from __future__ import annotations

import argparse
import gzip
import json
import math
import re
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path

from ..atomic import atomic_write_bytes
from ..data.names import scene_base_name
from ..errors import read_json

#: Package-data file of the packed layouts (inside ``tsnav/world/data``).
PACKED_NAME = "ithor_layouts.json.gz"
PACKED_FORMAT = "tsnav-ithor-layouts"
#: Flags kept per object, in this order (bit i of ``flags``).
FLAGS = ("receptacle", "pickupable", "moveable", "openable", "isOpen", "visible")
_NAME = re.compile(r"FloorPlan\d+")


class LayoutError(ValueError):
    """A layout file (or the packed layouts) is malformed; the message is one line naming the problem."""


@dataclass(frozen=True)
class LayoutObject:
    """One recorded object. Boxes in metres, world frame, y up; ``rotation`` Euler degrees (x, y, z)."""

    object_id: str
    object_type: str
    aabb_center: tuple[float, float, float]
    aabb_size: tuple[float, float, float]
    oobb: tuple[tuple[float, float, float], ...] | None  #: the 8 corners of the oriented box, or None
    rotation: tuple[float, float, float]
    parents: tuple[str, ...]  #: objectIds of the receptacles it stands on/in (empty: fixed structure)
    receptacle: bool = False
    pickupable: bool = False
    moveable: bool = False
    openable: bool = False
    is_open: bool = False
    visible: bool = False

    @property
    def aabb_min(self) -> tuple[float, float, float]:
        return tuple(c - s / 2 for c, s in zip(self.aabb_center, self.aabb_size))

    @property
    def aabb_max(self) -> tuple[float, float, float]:
        return tuple(c + s / 2 for c, s in zip(self.aabb_center, self.aabb_size))


@dataclass(frozen=True)
class Layout:
    """All objects of one scene; ``floor`` is its single ``Floor`` object."""

    scene: str
    objects: tuple[LayoutObject, ...]

    @property
    def floor(self) -> LayoutObject:
        return next(o for o in self.objects if o.object_type == "Floor")


# ------------------------------------------------------------------------------------------ validation
def _vec(v, what: str, n: int = 3) -> tuple[float, ...]:
    if isinstance(v, dict):
        try:
            v = [v["x"], v["y"], v["z"]]
        except KeyError as e:
            raise LayoutError(f"{what}: missing coordinate {e.args[0]!r}") from None
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise LayoutError(f"{what}: expected {n} numbers")
    out = []
    for x in v:
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            raise LayoutError(f"{what}: {x!r} is not a finite number")
        out.append(float(x))
    return tuple(out)


def parse_object(raw, where: str) -> LayoutObject:
    """One object dict of a source file -> :class:`LayoutObject`; ``where`` prefixes error messages."""
    if not isinstance(raw, dict):
        raise LayoutError(f"{where}: expected an object dict, got {type(raw).__name__}")
    for key in ("objectId", "objectType", "aabb"):
        if key not in raw:
            raise LayoutError(f"{where}: missing field {key!r}")
    oid, otype = raw["objectId"], raw["objectType"]
    if not isinstance(oid, str) or not oid or not isinstance(otype, str) or not otype:
        raise LayoutError(f"{where}: objectId and objectType must be non-empty strings")
    where = f"{where} ({oid})"
    aabb = raw["aabb"]
    if not isinstance(aabb, dict) or "center" not in aabb or "size" not in aabb:
        raise LayoutError(f"{where}: aabb needs 'center' and 'size'")
    center, size = _vec(aabb["center"], f"{where}: aabb.center"), _vec(aabb["size"], f"{where}: aabb.size")
    if min(size) < 0:
        raise LayoutError(f"{where}: aabb.size has a negative side {size}")
    corners = raw.get("oobbCorners")
    oobb = None
    if corners is not None:
        if not isinstance(corners, list) or len(corners) != 8:
            raise LayoutError(f"{where}: oobbCorners must be 8 corners or null")
        oobb = tuple(_vec(c, f"{where}: oobbCorners[{i}]") for i, c in enumerate(corners))
    rot = _vec(raw.get("rotation", {"x": 0, "y": 0, "z": 0}), f"{where}: rotation")
    parents = raw.get("parentReceptacles") or []
    if not isinstance(parents, list) or not all(isinstance(p, str) for p in parents):
        raise LayoutError(f"{where}: parentReceptacles must be a list of objectIds or null")
    flags = {}
    for f in FLAGS:
        v = raw.get(f, False)
        if not isinstance(v, bool):
            raise LayoutError(f"{where}: {f} must be true or false, got {v!r}")
        flags[f] = v
    return LayoutObject(
        oid,
        otype,
        center,
        size,
        oobb,
        rot,
        tuple(parents),
        flags["receptacle"],
        flags["pickupable"],
        flags["moveable"],
        flags["openable"],
        flags["isOpen"],
        flags["visible"],
    )


def parse_layout(data, where: str, expect_scene: str | None = None) -> Layout:
    """A decoded source file -> :class:`Layout` (checks the scene name, one Floor, unique ids)."""
    if not isinstance(data, dict) or not isinstance(data.get("objects"), list):
        raise LayoutError(f"{where}: expected {{'scene': NAME, 'objects': [...]}}")
    scene = data.get("scene")
    if not isinstance(scene, str) or not _NAME.fullmatch(scene_base_name(scene)):
        raise LayoutError(f"{where}: 'scene' must be an iTHOR scene name like FloorPlan1, got {scene!r}")
    scene = scene_base_name(scene)
    if expect_scene is not None and scene != expect_scene:
        raise LayoutError(f"{where}: holds scene {scene!r}, expected {expect_scene!r}")
    objects = tuple(parse_object(o, f"{where}: object {i}") for i, o in enumerate(data["objects"]))
    floors = [o for o in objects if o.object_type == "Floor"]
    if len(floors) != 1:
        raise LayoutError(f"{where}: expected exactly one Floor object, found {len(floors)}")
    seen: set[str] = set()
    for o in objects:
        if o.object_id in seen:
            raise LayoutError(f"{where}: duplicate objectId {o.object_id!r}")
        seen.add(o.object_id)
    return Layout(scene, objects)


def read_layout_file(path: str | Path) -> Layout:
    """Read and check one source layout file (``FloorPlanN.json`` or ``FloorPlanN_physics.json``)."""
    path = Path(path)
    data = read_json(path, LayoutError, missing="no such layout file")
    stem = scene_base_name(path.name.split(".")[0])
    return parse_layout(data, str(path), stem if _NAME.fullmatch(stem) else None)


# ------------------------------------------------------------------------------------------- packing
def _r(v: float) -> float:
    return round(v, 3) + 0.0  # + 0.0 turns -0.0 into 0.0


def to_row(o: LayoutObject) -> list:
    """The packed row of one object: id, type, parents, flag bits, aabb (6), rotation (3), oobb (24 or null)."""
    bits = sum(1 << i for i, f in enumerate(FLAGS) if getattr(o, "is_open" if f == "isOpen" else f))
    oobb = None if o.oobb is None else [_r(v) for c in o.oobb for v in c]
    return [
        o.object_id,
        o.object_type,
        list(o.parents),
        bits,
        [_r(v) for v in (*o.aabb_center, *o.aabb_size)],
        [_r(v) for v in o.rotation],
        oobb,
    ]


def from_row(row, where: str) -> LayoutObject:
    try:
        oid, otype, parents, bits, box, rot, oobb = row
        return LayoutObject(
            str(oid),
            str(otype),
            tuple(map(float, box[:3])),
            tuple(map(float, box[3:6])),
            None if oobb is None else tuple(tuple(map(float, oobb[3 * i : 3 * i + 3])) for i in range(8)),
            tuple(map(float, rot)),
            tuple(parents),
            *(bool(int(bits) >> i & 1) for i in range(len(FLAGS))),
        )
    except (TypeError, ValueError, IndexError) as e:
        raise LayoutError(f"{where}: malformed packed row ({e})") from None


def pack_layouts(src_dir: str | Path, out: str | Path) -> int:
    """Read every ``FloorPlan*.json`` in ``src_dir`` (checked) and write the packed file ``out``; scene count."""
    files = sorted(Path(src_dir).glob("FloorPlan*.json"), key=lambda p: int(re.findall(r"\d+", p.name)[0]))
    if not files:
        raise LayoutError(f"{src_dir}: no FloorPlan*.json layout files")
    scenes = {}
    for f in files:
        lay = read_layout_file(f)
        scenes[lay.scene] = [to_row(o) for o in lay.objects]
    doc = {
        "format": PACKED_FORMAT,
        "version": 1,
        "columns": [
            "objectId",
            "objectType",
            "parentReceptacles",
            "flags:" + ",".join(FLAGS),
            "aabb:center+size",
            "rotation",
            "oobbCorners",
        ],
        "scenes": scenes,
    }
    text = json.dumps(doc, separators=(",", ":"))
    atomic_write_bytes(out, gzip.compress(text.encode(), compresslevel=9, mtime=0))
    return len(scenes)


@lru_cache(maxsize=1)
def _packed() -> dict:
    ref = resources.files("tsnav.world") / "data" / PACKED_NAME
    try:
        doc = json.loads(gzip.decompress(ref.read_bytes()))
    except (OSError, ValueError) as e:
        raise LayoutError(f"packaged iTHOR layouts {PACKED_NAME} unreadable: {e}") from None
    if doc.get("format") != PACKED_FORMAT or not isinstance(doc.get("scenes"), dict):
        raise LayoutError(f"packaged iTHOR layouts {PACKED_NAME}: not a {PACKED_FORMAT} file")
    return doc["scenes"]


def layout_names() -> list[str]:
    """Scene names available in the packaged layouts."""
    return list(_packed())


def load_layout(scene: str) -> Layout:
    """The packaged layout of ``scene`` (e.g. ``FloorPlan22``); ``LayoutError`` when there is none."""
    rows = _packed().get(scene)
    if rows is None:
        raise LayoutError(
            f"no recorded layout for scene {scene!r} (the ithor-real world has FloorPlan1-30, "
            f"201-230, 301-330, 401-430)"
        )
    return Layout(scene, tuple(from_row(r, f"{PACKED_NAME}: {scene}") for r in rows))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        allow_abbrev=False, description="Pack a folder of recorded iTHOR layouts into the package-data file."
    )
    p.add_argument("src", help="folder of FloorPlan*.json layout files")
    p.add_argument("--out", default=str(Path(__file__).parent / "data" / PACKED_NAME), help="packed file")
    a = p.parse_args(argv)
    n = pack_layouts(a.src, a.out)
    print(f"packed {n} scenes into {a.out} ({Path(a.out).stat().st_size / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
