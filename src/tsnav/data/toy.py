"""A small analytic scene for unit tests: a rectangular room, no rendering.

Visibility is decided geometrically (object centre inside the 90-degree horizontal field of view, within
range, no occlusion), so that tests of the simulator, rewards and metrics can run on a scene whose every
number can be worked out by hand, without the renderer.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..constants import (
    GRID_SIZE,
    HORIZONS,
    LOOK_DOWN,
    LOOK_UP,
    MOVE_AHEAD,
    NUM_ACTIONS,
    ROTATE_LEFT,
    ROTATE_RIGHT,
    ROTATIONS,
    VISIBILITY_DISTANCE,
    ClassSet,
    class_set as get_class_set,
    state_key,
)
from .reader import Scene, object_categories


def toy_scene(
    width: float = 2.0,
    depth: float = 1.5,
    objects: dict[str, tuple[float, float]] | None = None,
    blocked: list[tuple[float, float]] | None = None,
    name: str = "Toy",
    class_set: str | ClassSet | None = None,
) -> Scene:
    """A ``width`` x ``depth`` metre room with positions every 0.25 m from (0, 0).

    ``objects`` maps an object id (``Category|n``) to its (x, z) centre; ``blocked`` lists grid positions
    that are not reachable. Distances are horizontal from the agent to the object centre. ``class_set`` names
    the scene's target classes (default ``ithor22``; ``robothor12`` for RoboTHOR's), recorded in its meta as
    ``scene.json`` records it.
    """
    classes = get_class_set(class_set)
    objects = {"Bowl|1": (width, depth)} if objects is None else objects
    blocked = set() if blocked is None else {(round(x, 2), round(z, 2)) for x, z in blocked}
    nx, nz = int(round(width / GRID_SIZE)) + 1, int(round(depth / GRID_SIZE)) + 1
    pos = [(round(i * GRID_SIZE, 2), round(j * GRID_SIZE, 2)) for i in range(nx) for j in range(nz)]
    pos = [p for p in pos if p not in blocked]
    keys = sorted(state_key(px, pz, r, h) for px, pz in pos for r in ROTATIONS for h in HORIZONS)
    keys = np.array(keys)
    index = {k: i for i, k in enumerate(keys.tolist())}
    n = len(keys)
    parts = np.array([k.split("|") for k in keys.tolist()], dtype=float)
    x, z, rot, hor = parts[:, 0], parts[:, 1], parts[:, 2].astype(int), parts[:, 3].astype(int)
    nxt = np.repeat(np.arange(n, dtype=np.int32)[:, None], NUM_ACTIONS, axis=1)
    for i in range(n):
        r, h = rot[i], hor[i]
        nxt[i, ROTATE_LEFT] = index[state_key(x[i], z[i], (r - 45) % 360, h)]
        nxt[i, ROTATE_RIGHT] = index[state_key(x[i], z[i], (r + 45) % 360, h)]
        if h == 0:
            nxt[i, LOOK_DOWN] = index[state_key(x[i], z[i], r, 30)]
        else:
            nxt[i, LOOK_UP] = index[state_key(x[i], z[i], r, 0)]
        ex, ez = round(np.sin(np.deg2rad(r))), round(np.cos(np.deg2rad(r)))
        k = state_key(x[i] + ex * GRID_SIZE, z[i] + ez * GRID_SIZE, r, h)
        if k in index:
            nxt[i, MOVE_AHEAD] = index[k]
    oids = np.array(list(objects), dtype=str)
    cat = object_categories(oids, classes)
    centers = np.array([objects[o] for o in oids], dtype=np.float64).reshape(-1, 2)
    dx = centers[None, :, 0] - x[:, None]
    dz = centers[None, :, 1] - z[:, None]
    dist = np.hypot(dx, dz)
    bearing = np.degrees(np.arctan2(dx, dz))  # 0 = +z, 90 = +x, as AI2-THOR
    rel = (bearing - rot[:, None] + 180) % 360 - 180
    in_view = (np.abs(rel) <= 45) | (dist < 1e-6)
    visible = in_view & (dist <= VISIBILITY_DISTANCE)
    pixels = np.where(in_view, 100, 0).astype(np.int32)
    boxes = np.where(in_view[..., None], np.array([10, 10, 20, 20], dtype=np.int16), -1).astype(np.int16)
    floor = [
        np.array([[-0.125, -0.125], [width + 0.125, -0.125], [width + 0.125, depth + 0.125], [-0.125, depth + 0.125]])
    ]
    meta = {
        "name": name,
        "room_type": "toy",
        "split": "train",
        "visibility": {"min_pixels": 1},
        "objects": [
            {"objectId": o, "objectType": o.split("|")[0], "position": {"x": float(c[0]), "y": 0.5, "z": float(c[1])}}
            for o, c in zip(oids, centers)
        ],
    }
    if class_set is not None:
        meta["class_set"] = classes.name
    return Scene(
        name=name,
        path=Path("."),
        keys=keys,
        x=x.astype(np.float32),
        z=z.astype(np.float32),
        rotation=rot.astype(np.int16),
        horizon=hor.astype(np.int16),
        next_state=nxt,
        object_ids=oids,
        object_category=cat,
        visible=visible,
        distance=dist.astype(np.float32),
        pixels=pixels,
        boxes=boxes,
        floor=floor,
        image_size=64,
        meta=meta,
        class_set=classes,
    )
