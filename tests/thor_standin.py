"""Stand-ins for AI2-THOR in tests: a live controller backed by a tsnav scene, and the lineage's offline folder.

:class:`StandInController` follows the documented interface of ``ai2thor.controller.Controller`` that
:func:`tsnav.data.thor_live.export_live` uses: ``reset(scene)``, ``step(action=..., **kwargs)`` (or
``step(dict(action=...))``) returning an event with ``metadata`` (``lastActionSuccess``, ``errorMessage``,
``actionReturn``, ``agent`` {``position``, ``rotation``, ``cameraHorizon``}, ``cameraPosition``,
``objects`` [{``objectId``, ``objectType``, ``position``, ``axisAlignedBoundingBox``, ``visible``,
``distance``}], ``sceneBounds``, ``screenWidth``/``screenHeight``), ``frame`` (uint8 H x W x 3),
``depth_frame`` (float32 metres), ``instance_segmentation_frame`` (uint8 colours) and ``instance_masks``
(objectId -> bool mask). The metadata replays the shape of a real ai2thor 5 event
(``fixtures/ai2thor/event_FloorPlan29_physics_reset.json``): every top-level key, every ``agent`` key and
every field of an object record are there, with this scene's values where the export reads them (agent pose,
objects' ids, types, positions, boxes, ``visible``, ``distance``, ``sceneBounds``) and the real event's
values elsewhere. Frames come from tsnav's renderer (``tsnav.world.show.render_views``) of the
scene's own states (rendered once, up front); actions are answered from the scene's state graph:

* ``GetReachablePositions``: the scene's ``grid.json`` with a little float noise, as Unity reports them.
* ``Teleport``: succeeds at a reachable position (1 mm), a rotation of the 45 degree set, horizon 0 or 30.
* ``MoveAhead`` (``moveMagnitude``, default ``gridSize``): moves along the heading; succeeds when the
  landing point is the graph's MoveAhead successor (so 0.25 * sqrt(2) m at diagonal headings).
* ``RotateLeft`` / ``RotateRight`` / ``LookUp`` / ``LookDown``: the graph's successor, failing where it has none.

Objects are the scene's target objects and its furniture (as AI2-THOR, the metadata lists every object);
their ``axisAlignedBoundingBox`` bounds the rotated box of ``scene.json``.

:func:`write_lineage_scene` writes a tsnav scene in the exact layout of ``AI2Thor_offline_data_2.0.2``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import h5py
import networkx as nx
import numpy as np

from tsnav.constants import (
    CAMERA_HEIGHT,
    object_id,
    GRID_SIZE,
    LOOK_DOWN,
    LOOK_UP,
    MOVE_AHEAD,
    NUM_CATEGORIES,
    ROTATE_LEFT,
    ROTATE_RIGHT,
)
from tsnav.data.reader import load_scene

GRID_Y = 0.9009995
#: A real ai2thor 5 event (``Event.metadata`` after reset of FloorPlan29_physics); see fixtures/ai2thor/README.md.
REAL_EVENT = Path(__file__).parent / "fixtures" / "ai2thor" / "event_FloorPlan29_physics_reset.json"


def real_event_metadata() -> dict:
    """The real event's metadata dict (a fresh copy)."""
    return json.loads(REAL_EVENT.read_text())


def aabb(center, size, yaw):
    """Axis-aligned box {center, size} (AI2-THOR's dicts) around a tsnav box (base centre, size, yaw)."""
    c, s = abs(math.cos(math.radians(yaw))), abs(math.sin(math.radians(yaw)))
    hx, hz = size[0] / 2, size[2] / 2
    ex, ez = c * hx + s * hz, s * hx + c * hz
    cy = center[1] + size[1] / 2
    return {
        "center": {"x": center[0], "y": cy, "z": center[2]},
        "size": {"x": 2 * ex, "y": size[1], "z": 2 * ez},
        "cornerPoints": [
            [center[0] + a * ex, cy + b * size[1] / 2, center[2] + d * ez]
            for a in (-1, 1)
            for b in (-1, 1)
            for d in (-1, 1)
        ],
    }


class StandInEvent:
    def __init__(self, metadata, frame, depth_frame, instance_segmentation_frame, instance_masks):
        self.metadata = metadata
        self.frame = frame
        self.depth_frame = depth_frame
        self.instance_segmentation_frame = instance_segmentation_frame
        self.instance_masks = instance_masks
        self.screen_width = metadata["screenWidth"]
        self.screen_height = metadata["screenHeight"]

    def __bool__(self):
        return bool(self.metadata["lastActionSuccess"])


class StandInController:
    """See the module docstring. ``scene_dir``: a rendered tsnav scene folder (with ``parts``)."""

    def __init__(
        self,
        scene_dir,
        width: int = 64,
        height: int | None = None,
        gridSize: float = GRID_SIZE,
        renderDepthImage: bool = True,
        renderInstanceSegmentation: bool = True,
        noise: float = 2e-6,
        **settings,
    ):
        from tsnav.world.show import render_views

        self.scene = load_scene(scene_dir)
        self.size = int(width)
        assert height in (None, width), "the stand-in renders square frames"
        self.grid_size = gridSize
        self.depth_on, self.seg_on = renderDepthImage, renderInstanceSegmentation
        self.settings = settings
        s = self.scene
        poses = np.stack([s.x, s.z, s.rotation, s.horizon], 1).astype(np.float64)
        self.rgb, self.depth, self.ids = render_views(s, poses, self.size)
        self.grid = json.loads((Path(scene_dir) / "grid.json").read_text())
        self.noise = noise
        self.steps: dict[str, int] = {}
        objs = []
        for o in s.meta["objects"]:
            b = o["bbox"]
            objs.append(
                (o["objectId"], o["objectType"], o["inst"], aabb(b["center"], b["size"], b["yaw"]), o["position"])
            )
        for f in s.meta["furniture"]:
            cx, cy, cz = f["center"]
            oid = object_id(f["category"], cx, cy, cz)
            objs.append(
                (oid, f["category"], f["inst"], aabb(f["center"], f["size"], f["yaw"]), {"x": cx, "y": cy, "z": cz})
            )
        self.objects = objs
        rng = np.random.default_rng(0)
        self.colors = {o[2]: rng.integers(0, 256, 3).astype(np.uint8) for o in objs}
        self.state = 0
        self.scene_name = s.name
        self.template = real_event_metadata()
        self.object_template = self.template["objects"][0]

    # ------------------------------------------------------------------ ai2thor Controller interface
    def reset(self, scene=None, **init_params):
        if scene is not None and scene != self.scene_name:
            raise ValueError(f"Scene '{scene}' not contained in build")
        self.state = int(self.scene.index(f"{self.grid[0]['x']:.2f}|{self.grid[0]['z']:.2f}|0|0"))
        return self._event("Reset", True)

    def stop(self):
        pass

    def step(self, action=None, **kwargs):
        if isinstance(action, dict):
            kwargs = {**action, **kwargs}
            action = kwargs.pop("action")
        self.steps[action] = self.steps.get(action, 0) + 1
        s = self.scene
        ns = s.next_state
        if action == "GetReachablePositions":
            ret = [
                {"x": p["x"] - self.noise, "y": GRID_Y, "z": p["z"] - self.noise} for p in self.grid
            ]  # Unity float noise
            return self._event(action, True, ret)
        if action in ("Teleport", "TeleportFull"):
            p = kwargs.get("position", {})
            rot = kwargs.get("rotation", s.rotation[self.state])
            rot = rot["y"] if isinstance(rot, dict) else rot
            hor = kwargs.get("horizon", s.horizon[self.state])
            near = (np.abs(s.x - p.get("x", np.inf)) < 1e-3) & (np.abs(s.z - p.get("z", np.inf)) < 1e-3)
            ok = near & (s.rotation == int(round(rot)) % 360) & (s.horizon == int(round(hor)))
            if abs(rot - round(rot)) > 1e-3 or not ok.any():
                return self._event(action, False, error="stand-in: no such pose on the scene's grid")
            self.state = int(np.flatnonzero(ok)[0])
            return self._event(action, True)
        if action == "MoveAhead":
            mag = float(kwargs.get("moveMagnitude", self.grid_size))
            t = int(ns[self.state, MOVE_AHEAD])
            r = math.radians(float(s.rotation[self.state]))
            tx, tz = s.x[self.state] + mag * math.sin(r), s.z[self.state] + mag * math.cos(r)
            if t != self.state and abs(tx - s.x[t]) < 1e-3 and abs(tz - s.z[t]) < 1e-3:
                self.state = t
                return self._event(action, True)
            return self._event(action, False, error="stand-in: blocked or off the grid")
        simple = {"RotateLeft": ROTATE_LEFT, "RotateRight": ROTATE_RIGHT, "LookUp": LOOK_UP, "LookDown": LOOK_DOWN}
        if action in simple:
            t = int(ns[self.state, simple[action]])
            ok = t != self.state
            self.state = t
            return self._event(action, ok)
        return self._event(action, False, error=f"stand-in: unsupported action {action}")

    # ------------------------------------------------------------------ events
    def _event(self, action, ok, ret=None, error=""):
        s, v = self.scene, self.state
        x, z = float(s.x[v]), float(s.z[v])
        cam = np.array([x, CAMERA_HEIGHT, z])
        ids = self.ids[v]
        objects, masks = [], {}
        seg = np.zeros(ids.shape + (3,), np.uint8)
        for oid, otype, inst, box, pos in self.objects:
            m = ids == inst
            c = np.array([box["center"][a] for a in "xz"])
            h = np.array([box["size"][a] for a in "xz"]) / 2
            d = float(np.linalg.norm(np.maximum(np.abs(np.array([x, z]) - c) - h, 0)))  # floor plane
            if m.any() and self.seg_on:
                masks[oid] = m
                seg[m] = self.colors[inst]
            # every field of a real object record; identity, geometry and visibility are this scene's
            objects.append(
                {
                    **self.object_template,
                    "name": oid.split("|")[0] + f"_{inst}",
                    "objectId": oid,
                    "objectType": otype,
                    "assetId": otype,
                    "position": dict(pos),
                    "rotation": {"x": 0.0, "y": 0.0, "z": 0.0},
                    "visible": bool(m.any() and d <= 1.5),
                    "axisAlignedBoundingBox": box,
                    "objectOrientedBoundingBox": {"cornerPoints": box["cornerPoints"]},
                    "parentReceptacles": None,
                    "receptacleObjectIds": None,
                    "distance": float(np.linalg.norm(cam - np.array([pos["x"], pos["y"], pos["z"]]))),
                }
            )
        fl = np.concatenate([np.asarray(p) for p in s.floor])
        bounds = aabb(
            [float(fl[:, 0].mean()), 0.0, float(fl[:, 1].mean())],
            [float(np.ptp(fl[:, 0])), 2.6, float(np.ptp(fl[:, 1]))],
            0.0,
        )
        t = self.template  # the real event's top-level keys; the state's values where the export reads them
        meta = {
            **t,
            "lastAction": action,
            "lastActionSuccess": bool(ok),
            "errorMessage": error,
            "actionReturn": ret,
            "sceneName": self.scene_name,
            "screenWidth": self.size,
            "screenHeight": self.size,
            "agent": {
                **t["agent"],
                "position": {"x": x, "y": GRID_Y, "z": z},
                "rotation": {"x": 0.0, "y": float(s.rotation[v]), "z": 0.0},
                "cameraHorizon": float(s.horizon[v]),
            },
            "cameraPosition": {"x": x, "y": CAMERA_HEIGHT, "z": z},
            "objects": objects,
            "sceneBounds": {"cornerPoints": bounds["cornerPoints"], "center": bounds["center"], "size": bounds["size"]},
        }
        return StandInEvent(
            meta,
            self.rgb[v].copy(),
            self.depth[v].astype(np.float32) if self.depth_on else None,
            seg if self.seg_on else None,
            masks if self.seg_on else {},
        )


# ---------------------------------------------------------------------------- lineage offline folder
def detections_22x264(scene, box_size: int = 300, seed: int = 0):
    """Hand-built lineage detection rows (S, 22, 264) for ``scene``: per category the instance with the most
    pixels (score = min(1, pixels / 50)), box scaled to ``box_size``, label c + 1 (23 = no object), random
    float16-exact features. Columns written one by one, independently of tsnav.data.lineage."""
    rng = np.random.default_rng(seed)
    S = scene.num_states
    rows = np.zeros((S, NUM_CATEGORIES, 264), np.float32)
    rows[:, :, :256] = rng.standard_normal((S, NUM_CATEGORIES, 256)).astype(np.float16).astype(np.float32)
    rows[:, :, 257] = 23
    scale = box_size / scene.image_size
    for c in range(NUM_CATEGORIES):
        cols = np.flatnonzero(scene.object_category == c)
        if len(cols) == 0:
            continue
        px = scene.pixels[:, cols]
        best = np.argmax(px, axis=1)
        bpx = px[np.arange(S), best]
        seen = bpx > 0
        rows[seen, c, 256] = np.minimum(1.0, bpx[seen] / 50.0)
        rows[seen, c, 257] = c + 1
        rows[seen, c, 260:264] = scene.boxes[np.flatnonzero(seen), cols[best[seen]]].astype(np.float32) * scale
    return rows


def write_lineage_scene(
    scene_dir, out: Path, metadata: bool = False, detections: bool = True, savn_names: bool = False
) -> Path:
    """Write tsnav scene ``scene_dir`` in the lineage's layout at ``out`` (graph.json with networkx's
    ``node_link_data``, grid.json, visible_object_map_1.5.json, images.hdf5, det_feature_categories.hdf5,
    optionally the raw ``metadata.json``; ``savn_names`` writes SAVN's ``visible_object_map.json`` instead)."""
    scene = load_scene(scene_dir)
    src = Path(scene_dir)
    out.mkdir(parents=True)
    g = nx.DiGraph()
    g.add_nodes_from(scene.keys.tolist())
    a, act = np.nonzero(scene.next_state != np.arange(scene.num_states)[:, None])
    g.add_edges_from(zip(scene.keys[a].tolist(), scene.keys[scene.next_state[a, act]].tolist()))
    with open(out / "graph.json", "w") as f:
        json.dump(nx.node_link_data(g, edges="links"), f)
    grid = json.loads((src / "grid.json").read_text())
    with open(out / "grid.json", "w") as f:
        json.dump([{"x": p["x"], "y": GRID_Y, "z": p["z"]} for p in grid], f)
    vis = json.loads((src / "visible_object_map_1.5.json").read_text())
    with open(out / ("visible_object_map.json" if savn_names else "visible_object_map_1.5.json"), "w") as f:
        json.dump(vis, f)
    with h5py.File(src / "images.hdf5", "r") as fi, h5py.File(out / "images.hdf5", "w") as fo:
        for k in scene.keys.tolist():
            fo.create_dataset(k, data=fi[k][()])
    if detections:
        rows = detections_22x264(scene)
        with h5py.File(out / "det_feature_categories.hdf5", "w") as f:
            for k, r in zip(scene.keys.tolist(), rows):
                f.create_dataset(k, data=r)
    if metadata:
        raw = {}
        objs = scene.meta["objects"]
        boxes = [aabb(o["bbox"]["center"], o["bbox"]["size"], o["bbox"]["yaw"]) for o in objs]
        col = {o: j for j, o in enumerate(scene.object_ids.tolist())}
        for v, k in enumerate(scene.keys.tolist()):
            raw[k] = {
                "agent": {
                    "position": {"x": float(scene.x[v]), "y": GRID_Y, "z": float(scene.z[v])},
                    "rotation": {"x": 0.0, "y": float(scene.rotation[v]), "z": 0.0},
                    "cameraHorizon": float(scene.horizon[v]),
                },
                "cameraPosition": {"x": float(scene.x[v]), "y": CAMERA_HEIGHT, "z": float(scene.z[v])},
                "objects": [
                    {
                        "objectId": o["objectId"],
                        "objectType": o["objectType"],
                        "position": o["position"],
                        "axisAlignedBoundingBox": b,
                        "visible": bool(scene.visible[v, col[o["objectId"]]]),
                    }
                    for o, b in zip(objs, boxes)
                ],
            }
        with open(out / "metadata.json", "w") as f:
            json.dump(raw, f)
    return out


__all__ = [
    "REAL_EVENT",
    "StandInController",
    "StandInEvent",
    "aabb",
    "detections_22x264",
    "real_event_metadata",
    "write_lineage_scene",
]
