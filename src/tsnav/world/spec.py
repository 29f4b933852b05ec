"""The scene description written to ``scene.json``: rooms, floor, furniture, objects, render parts.

Everything the renderer draws is an oriented box (:class:`Part`) with a procedural material; walls,
floors, furniture and objects are made of parts. Each part carries an instance id: 0 is empty space,
structure (walls, floor, ceiling) and furniture have their own ids, target objects theirs, so that the
renderer's id buffer tells which object covers each pixel.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

#: Procedural patterns understood by the fragment shader.
PLAIN, STRIPES, CHECKER, WOOD, TILES, SPECKLE = range(6)


@dataclass
class Part:
    """One box: centre and size in metres (x, y, z; y up), yaw in degrees about +y (0 keeps axes),
    two colours (RGB in 0..1), a pattern id with its scale in metres, and the instance id."""

    center: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw: float
    color: tuple[float, float, float]
    color2: tuple[float, float, float]
    pattern: int = PLAIN
    scale: float = 0.25
    inst: int = 0

    def row(self) -> list[float]:
        return [
            *map(float, self.center),
            *map(float, self.size),
            float(self.yaw),
            *map(float, self.color),
            *map(float, self.color2),
            float(self.pattern),
            float(self.scale),
            float(self.inst),
        ]


@dataclass
class Furniture:
    """A piece of furniture: oriented footprint on the floor, height, and whether it blocks the agent."""

    id: str
    category: str
    center: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw: float
    blocks: bool = True
    surface: float | None = None  # height of the top surface that holds small objects, metres
    inst: int = 0

    def footprint(self, pad: float = 0.0) -> list[list[float]]:
        """Corners (x, z) of the footprint rectangle, grown by ``pad`` metres on every side."""
        return box_footprint(self.center, self.size, self.yaw, pad)


@dataclass
class ObjectInstance:
    """A target-category object with an AI2-THOR-style id (``Category|+x|+y|+z``)."""

    objectId: str
    objectType: str
    center: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw: float
    support: str  # id of the furniture it stands on, "floor" or "wall"
    inst: int = 0

    def to_json(self) -> dict:
        x, y, z = self.center
        return {
            "objectId": self.objectId,
            "objectType": self.objectType,
            "position": {"x": x, "y": y, "z": z},
            "bbox": {"center": list(self.center), "size": list(self.size), "yaw": self.yaw},
            "support": self.support,
            "inst": self.inst,
        }


@dataclass
class SceneSpec:
    """A whole scene. ``rooms``: list of {"type", "rect": [x0, z0, x1, z1]}; ``floor``: polygons (x, z)."""

    name: str
    room_type: str
    split: str
    seed: int
    rooms: list[dict]
    floor: list[list[list[float]]]
    doors: list[dict] = field(default_factory=list)
    furniture: list[Furniture] = field(default_factory=list)
    objects: list[ObjectInstance] = field(default_factory=list)
    parts: list[Part] = field(default_factory=list)
    instances: list[str] = field(default_factory=lambda: [""])
    light: dict = field(default_factory=dict)
    wall_height: float = 2.6
    #: where the scene comes from (e.g. ``{"world": "ithor-real", "version": 2}``); None for procedural scenes
    generator: dict | None = None
    #: reachability rule of the navgrid (None: its defaults): ``clearance``, the distance kept between the agent's
    #: centre and walls or blocking footprints, and ``sweep_clearance``, the one a MoveAhead's path keeps, metres
    navigation: dict | None = None
    #: the target classes the scene's tables have one column each for (:data:`tsnav.constants.CLASS_SETS`; None:
    #: ``ithor22``, written as no key, so iTHOR scenes are byte for byte as before)
    class_set: str | None = None

    def new_inst(self, name: str) -> int:
        self.instances.append(name)
        return len(self.instances) - 1

    def to_json(self) -> dict:
        return {
            "format": "tsnav-scene",
            "version": 1,
            "name": self.name,
            "room_type": self.room_type,
            "split": self.split,
            "seed": self.seed,
            "rooms": self.rooms,
            "floor": self.floor,
            "doors": self.doors,
            "wall_height": self.wall_height,
            "light": self.light,
            "furniture": [dict(asdict(f), footprint=f.footprint()) for f in self.furniture],
            "objects": [o.to_json() for o in self.objects],
            "instances": self.instances,
            "parts_columns": [
                "cx",
                "cy",
                "cz",
                "sx",
                "sy",
                "sz",
                "yaw",
                "r",
                "g",
                "b",
                "r2",
                "g2",
                "b2",
                "pattern",
                "scale",
                "inst",
            ],
            "parts": [[round(v, 5) for v in p.row()] for p in self.parts],
            **({"generator": self.generator} if self.generator is not None else {}),
            **({"navigation": self.navigation} if self.navigation is not None else {}),
            **({"class_set": self.class_set} if self.class_set is not None else {}),
        }

    @classmethod
    def from_json(cls, meta: dict) -> "SceneSpec":
        """The spec a ``scene.json`` (:meth:`to_json`, plus the writer's extra keys, which are ignored) describes:
        enough to lay the scene out again (:mod:`~tsnav.world.navgrid`), e.g. for a what-if without one object.
        The parts come back rounded to 10 micrometres, as written."""
        furniture = [
            Furniture(
                f["id"],
                f["category"],
                tuple(f["center"]),
                tuple(f["size"]),
                f["yaw"],
                bool(f.get("blocks", True)),
                f.get("surface"),
                int(f.get("inst", 0)),
            )
            for f in meta.get("furniture", [])
        ]
        objects = [
            ObjectInstance(
                o["objectId"],
                o["objectType"],
                tuple(o["bbox"]["center"]),
                tuple(o["bbox"]["size"]),
                o["bbox"].get("yaw", 0.0),
                o["support"],
                int(o.get("inst", 0)),
            )
            for o in meta.get("objects", [])
        ]
        parts = [
            Part(tuple(r[0:3]), tuple(r[3:6]), r[6], tuple(r[7:10]), tuple(r[10:13]), int(r[13]), r[14], int(r[15]))
            for r in meta.get("parts", [])
        ]
        return cls(
            name=meta["name"],
            room_type=meta["room_type"],
            split=meta["split"],
            seed=meta.get("seed", 0),
            rooms=meta.get("rooms", []),
            floor=meta.get("floor", []),
            doors=meta.get("doors", []),
            furniture=furniture,
            objects=objects,
            parts=parts,
            instances=list(meta.get("instances", [""])),
            light=meta.get("light", {}),
            wall_height=meta.get("wall_height", 2.6),
            generator=meta.get("generator"),
            navigation=meta.get("navigation"),
            class_set=meta.get("class_set"),
        )


def box_footprint(center, size, yaw: float, pad: float = 0.0) -> list[list[float]]:
    cx, _, cz = center
    hx, hz = size[0] / 2 + pad, size[2] / 2 + pad
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    out = []
    for lx, lz in ((-hx, -hz), (hx, -hz), (hx, hz), (-hx, hz)):
        # yaw rotates local +z (the front) towards +x, as AI2-THOR's rotation.
        out.append([round(cx + c * lx + s * lz, 5), round(cz - s * lx + c * lz, 5)])
    return out
