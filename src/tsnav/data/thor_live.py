"""Export a scene from a live AI2-THOR controller as a tsnav scene folder (optional extra ``tsnav[thor]``).

``ai2thor`` is imported only by :func:`make_controller`; :func:`export_live` needs nothing but an object
with AI2-THOR's documented ``Controller`` interface (``reset(scene)``, ``step(action=..., **kwargs)``
returning an ``Event`` with ``metadata``, ``frame``, ``depth_frame``, ``instance_masks``).

What the export does, in the lineage's way (SAVN's ``ExhaustiveBFSController``) but with real collision
checks:

1. ``GetReachablePositions``; positions are kept with two decimals (the state key's precision).
2. Walk the action graph: teleport to every (position, rotation) at horizon 0 and try ``MoveAhead``
   (``moveMagnitude`` 0.25 m, 0.25 * sqrt(2) m at diagonal headings, so that a diagonal move lands on the
   grid point one step along x and z, the lineage's convention); the edge exists when the action succeeds
   (``lastActionSuccess``) and the agent lands on that reachable position. Rotate +-45 and LookUp/LookDown
   (horizons 0 and 30) edges join the states of one position. Only the largest strongly connected set of
   states is kept.
3. Render every kept state: teleport to (position, rotation, horizon) and read ``event.frame``,
   ``event.depth_frame``, ``event.instance_masks`` and ``metadata['objects']``.
4. Write the scene folder through :mod:`tsnav.data.writer` (atomic, ``COMPLETE`` last): ``images.hdf5``,
   ``depth.hdf5``, ``graph.json``, ``grid.json``, ``visible_object_map_1.5.json`` (the object shows at
   least ``min_pixels`` pixels of its instance mask and the footprint of its axis-aligned box is within
   1.5 m of the agent on the floor plane, tsnav's distance of ``writer.box_distance``),
   ``scene.json`` (floor derived from the reachable grid, objects with their boxes, ``sceneBounds``) and
   ``states.hdf5`` (pixels, boxes, distances, and AI2-THOR's own ``visible`` flag as ``thor_visible``).

This path is tested against a stand-in controller backed by a tsnav scene (``tests/thor_standin.py``),
not against a real Unity build (none can be downloaded where tsnav is developed).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import networkx as nx
import numpy as np

from ..constants import (
    FIELD_OF_VIEW,
    GRID_SIZE,
    HORIZONS,
    ROTATE_STEP,
    ROTATIONS,
    TARGET_CATEGORIES,
    VISIBILITY_DISTANCE,
    state_key,
)
from .lineage import derive_floor, visible_object_map
from .names import lineage_scene_info
from .reader import COMPLETE_MARKER, SceneFormatError, load_scene
from .writer import (
    MIN_PIXEL_FRACTION,
    FrameWriter,
    box_distance,
    min_pixels,
    object_stats,
    scene_folder,
    write_graph,
    write_json,
    write_states,
)

INSTALL_HINT = (
    "ai2thor is not installed: pip install 'tsnav[thor]' (AI2-THOR then downloads its Unity build "
    "on first use and needs a display or Vulkan)"
)


class ThorUnavailable(RuntimeError):
    """ai2thor cannot be imported (the optional extra ``tsnav[thor]`` is not installed)."""


class LiveExportError(RuntimeError):
    """The controller did not behave as the export needs (settings, failed teleports)."""


@dataclass
class LiveConfig:
    """Settings of :func:`export_live`; the controller itself is made with :func:`controller_settings`."""

    size: int = 300
    """Frame side, pixels (the lineage's offline data uses 300)."""
    visibility_distance: float = VISIBILITY_DISTANCE
    """An object counts as visible within this many metres (``visible_object_map_1.5.json``)."""
    min_pixel_fraction: float = MIN_PIXEL_FRACTION
    """Share of the frame an instance mask must cover to count as seen (at least 2 pixels)."""
    depth_dtype: str = "float16"
    """dtype of ``depth.hdf5`` (metres)."""
    targets_only: bool = True
    """Keep only objects of the 22 target categories in the object table (``states.hdf5`` stays small)."""
    chunk: int = 64
    """States per batch of the pixel / box computation."""

    def min_pixels(self) -> int:
        return min_pixels(self.size, self.min_pixel_fraction)


@dataclass
class LiveStats:
    name: str
    states: int = 0
    positions: int = 0
    objects: int = 0
    dropped: int = 0
    steps: int = 0
    seconds: float = 0.0
    skipped: bool = False
    warnings: list = field(default_factory=list)


def controller_settings(size: int = 300) -> dict:
    """Keyword arguments for ``ai2thor.controller.Controller`` matching the lineage and the paper: 0.25 m
    grid, 45 degree rotations, 90 degree field of view, depth and instance segmentation on."""
    return dict(
        gridSize=GRID_SIZE,
        rotateStepDegrees=ROTATE_STEP,
        fieldOfView=FIELD_OF_VIEW,
        width=size,
        height=size,
        renderDepthImage=True,
        renderInstanceSegmentation=True,
        visibilityDistance=VISIBILITY_DISTANCE,
        snapToGrid=True,
    )


def make_controller(size: int = 300, **overrides):
    """An ``ai2thor.controller.Controller`` with :func:`controller_settings`; :class:`ThorUnavailable` with
    the install hint when ai2thor is missing."""
    try:
        from ai2thor.controller import Controller
    except ImportError:
        raise ThorUnavailable(INSTALL_HINT) from None
    try:
        return Controller(**{**controller_settings(size), **overrides})
    except Exception as e:  # download, display or Vulkan problems of the Unity build
        raise ThorUnavailable(f"AI2-THOR could not start: {' '.join(str(e).split()) or type(e).__name__}") from None


def _step(controller, stats: LiveStats, **action):
    stats.steps += 1
    return controller.step(**action)


def _ok(ev) -> bool:
    return bool(ev.metadata.get("lastActionSuccess", False))


def _cm(v) -> np.ndarray:
    return np.round(np.asarray(v, dtype=np.float64) * 100).astype(np.int64)


def agent_pose(metadata: dict) -> tuple[float, float, float, int, int] | None:
    """``(x, y, z, rotation, horizon)`` of ``metadata["agent"]``: position in metres, rotation (yaw, degrees)
    and camera horizon rounded to whole degrees (Unity reports 269.9999 for 270 and -0.0 for 0; rotation mod
    360); None when a field is missing."""
    a = metadata.get("agent")
    try:
        p, r = a["position"], a["rotation"]
        return (
            float(p["x"]),
            float(p["y"]),
            float(p["z"]),
            int(round(float(r["y"]))) % 360,
            int(round(float(a["cameraHorizon"]))) + 0,
        )
    except (TypeError, KeyError, ValueError):
        return None


def visible_object_ids(metadata: dict) -> set[str]:
    """objectIds that AI2-THOR flags ``visible`` in ``metadata["objects"]`` (in view and within its
    ``visibilityDistance``); kept in ``states.hdf5`` as ``thor_visible``."""
    return {
        o["objectId"]
        for o in metadata.get("objects", [])
        if isinstance(o, dict) and o.get("objectId") and o.get("visible")
    }


def scene_bounds(metadata: dict) -> dict | None:
    """``metadata["sceneBounds"]`` (``center`` and ``size`` {x, y, z} metres, ``cornerPoints``), as written to
    ``scene.json``; None when it is missing or lacks a numeric centre and size."""
    b = metadata.get("sceneBounds")
    try:
        [float(b[k][a]) for k in ("center", "size") for a in "xyz"]
    except (TypeError, KeyError, ValueError):
        return None
    return b


def _aabb(o: dict) -> tuple[list[float], list[float]] | None:
    """(base centre, size) of an object's ``axisAlignedBoundingBox``; its position as a point otherwise."""
    box = o.get("axisAlignedBoundingBox")
    if isinstance(box, dict) and isinstance(box.get("center"), dict) and isinstance(box.get("size"), dict):
        c = [float(box["center"][a]) for a in "xyz"]
        s = [float(box["size"][a]) for a in "xyz"]
        if any(v > 0 for v in s):
            return [c[0], c[1] - s[1] / 2, c[2]], s
    p = o.get("position")
    if isinstance(p, dict):
        return [float(p["x"]), float(p["y"]), float(p["z"])], [0.0, 0.0, 0.0]
    return None


def export_live(
    controller, scene_name: str, out_dir: str | Path, size: int | None = None, config: LiveConfig | None = None
) -> LiveStats:
    """Export ``scene_name`` from ``controller`` into the tsnav scene folder ``out_dir/scene_name``.

    The controller must have been made with :func:`controller_settings` (``size`` x ``size`` frames, depth
    and instance segmentation on). A complete folder is skipped (rerun to resume a dataset). Returns
    :class:`LiveStats`; raises :class:`LiveExportError` with one line when the controller misbehaves.
    """
    cfg = config or LiveConfig()
    if size is not None:
        cfg = LiveConfig(**{**cfg.__dict__, "size": int(size)})
    out_dir = Path(out_dir)
    final = out_dir / scene_name
    stats = LiveStats(scene_name)
    if (final / COMPLETE_MARKER).exists():
        stats.skipped = True
        return stats
    t0 = time.perf_counter()
    ev = controller.reset(scene_name)
    if ev is not None:  # fail before the walk when the settings are wrong
        _check_frames(ev, cfg.size, scene_name)
    agent = _Agent(controller, stats, _reachable_positions(controller, stats, scene_name))

    # --- 1. walk the action graph; keep its largest strongly connected set of states.
    valid, move_to = _walk(agent)
    states = _States.of(agent.raw, valid, move_to, scene_name)
    stats.dropped = states.dropped

    # --- 2. render every kept state; 3. distances, visibility map and the remaining files.
    with scene_folder(final) as tmp, FrameWriter(tmp, cfg.depth_dtype) as frames:
        objects, pixels, boxes, thor_visible, ev = _render(agent, states, frames, cfg, scene_name)
        frames.close()
        min_px = _write_tables(tmp, states, objects, pixels, boxes, thor_visible, cfg)
        write_json(tmp / "scene.json", _scene_meta(scene_name, controller, ev, states, objects, min_px, cfg))
        if load_scene(tmp).num_states != states.count:
            raise SceneFormatError(f"{final}: exported scene does not read back")
    stats.states, stats.positions, stats.objects = states.count, int(len(states.positions)), len(objects)
    stats.seconds = time.perf_counter() - t0
    return stats


def _reachable_positions(controller, stats: LiveStats, scene_name: str) -> np.ndarray:
    """``(P, 3)`` reachable positions (metres), one per 2-decimal (x, z): the state key's precision."""
    ev = _step(controller, stats, action="GetReachablePositions")
    reach = ev.metadata.get("actionReturn") if _ok(ev) else None
    if not reach:
        raise LiveExportError(f"{scene_name}: GetReachablePositions failed or returned no position")
    raw = np.array([[p["x"], p["y"], p["z"]] for p in reach], dtype=np.float64)
    codes = _cm(raw[:, 0]) * 1_000_003 + _cm(raw[:, 2])
    _, first = np.unique(codes, return_index=True)
    return raw[np.sort(first)]


class _Agent:
    """The controller's agent over the reachable positions ``raw``: teleports and the check of where it landed."""

    def __init__(self, controller, stats: LiveStats, raw: np.ndarray):
        self.controller, self.stats, self.raw = controller, stats, raw
        self.pcode = {(int(a), int(b)): i for i, (a, b) in enumerate(zip(_cm(raw[:, 0]), _cm(raw[:, 2])))}
        """Position index of each (x, z) in centimetres."""

    def step(self, **action):
        return _step(self.controller, self.stats, **action)

    def teleport(self, i: int, rot: int, hor: int):
        x, y, z = self.raw[i]
        return self.step(
            action="Teleport",
            position=dict(x=float(x), y=float(y), z=float(z)),
            rotation=dict(x=0.0, y=float(rot), z=0.0),
            horizon=float(hor),
            standing=True,
        )

    def pose_ok(self, ev, i: int, rot: int, hor: int) -> bool:
        """The action succeeded and the agent stands at position ``i`` with that rotation and horizon."""
        pose = agent_pose(ev.metadata)
        return (
            _ok(ev)
            and pose is not None
            and abs(pose[0] - self.raw[i, 0]) < 0.01
            and abs(pose[2] - self.raw[i, 2]) < 0.01
            and pose[3:] == (rot, hor)
        )


def _walk(agent: _Agent) -> tuple[np.ndarray, np.ndarray]:
    """Which (position, rotation) exist (``(P, R)`` bool: the teleport there succeeds) and where a MoveAhead from
    each lands (``(P, R)`` position index, -1: it fails or leaves the grid)."""
    raw = agent.raw
    P, R = len(raw), len(ROTATIONS)
    valid = np.zeros((P, R), dtype=bool)
    move_to = np.full((P, R), -1, dtype=np.int64)
    for i in range(P):
        for ri, rot in enumerate(ROTATIONS):
            if not agent.pose_ok(agent.teleport(i, rot, 0), i, rot, 0):
                continue
            valid[i, ri] = True
            diag = rot % 90 != 0
            ev = agent.step(action="MoveAhead", moveMagnitude=GRID_SIZE * (math.sqrt(2) if diag else 1.0))
            if not _ok(ev):
                continue
            ex, ez = int(round(math.sin(math.radians(rot)))), int(round(math.cos(math.radians(rot))))
            target = (int(_cm(raw[i, 0])) + 25 * ex, int(_cm(raw[i, 2])) + 25 * ez)
            p = ev.metadata.get("agent", {}).get("position", {})
            landed = (int(_cm(p.get("x", 1e9))), int(_cm(p.get("z", 1e9))))
            if target in agent.pcode and abs(landed[0] - target[0]) <= 1 and abs(landed[1] - target[1]) <= 1:
                move_to[i, ri] = agent.pcode[target]
    return valid, move_to


@dataclass
class _States:
    """The kept states: the largest strongly connected set of the walked action graph."""

    pos_i: np.ndarray
    """Position index of each kept state (in state-id order)."""
    rot_i: np.ndarray
    hor_i: np.ndarray
    keys: np.ndarray
    """State keys of the kept states (same order)."""
    edges: list
    """(key, key) edges among them."""
    kx: np.ndarray
    """x of every reachable position as the key writes it (two decimals, no negative zero)."""
    kz: np.ndarray
    y: np.ndarray
    """Height of every reachable position (metres)."""
    dropped: int
    """States outside the kept set."""

    @property
    def count(self) -> int:
        return int(len(self.keys))

    @property
    def positions(self) -> np.ndarray:
        """Indices of the positions with a kept state."""
        return np.unique(self.pos_i)

    @classmethod
    def of(cls, raw: np.ndarray, valid: np.ndarray, move_to: np.ndarray, scene_name: str) -> "_States":
        R, H = len(ROTATIONS), len(HORIZONS)
        # State ids: (position, rotation, horizon) -> i * R * H + ri * H + hi
        sid = lambda i, ri, hi: (i * R + ri) * H + hi  # noqa: E731
        edges = []
        for i, ri in zip(*np.nonzero(valid)):
            for hi in range(H):
                a = sid(i, ri, hi)
                for d in (1, -1):
                    rj = (ri + d) % R
                    if valid[i, rj]:
                        edges.append((a, sid(i, rj, hi)))
                if hi + 1 < H:
                    edges.append((a, sid(i, ri, hi + 1)))
                    edges.append((sid(i, ri, hi + 1), a))
                j = move_to[i, ri]
                if j >= 0 and valid[j, ri]:
                    edges.append((a, sid(j, ri, hi)))
        g = nx.DiGraph()
        g.add_nodes_from(sid(i, ri, hi) for i, ri in zip(*np.nonzero(valid)) for hi in range(H))
        g.add_edges_from(edges)
        if g.number_of_nodes() == 0:
            raise LiveExportError(f"{scene_name}: no teleport to a reachable position succeeded")
        keep = max(nx.strongly_connected_components(g), key=len)
        kept = np.array(sorted(keep), dtype=np.int64)
        pos_i, rot_i, hor_i = kept // (R * H), (kept // H) % R, kept % H
        # key positions: two decimals, no negative zero (Unity reports -1e-7 for 0; the key must read 0.00)
        kx, kz = np.round(raw[:, 0], 2) + 0.0, np.round(raw[:, 2], 2) + 0.0
        keys = np.array([state_key(kx[i], kz[i], ROTATIONS[r], HORIZONS[h]) for i, r, h in zip(pos_i, rot_i, hor_i)])
        key_of = dict(zip(kept.tolist(), keys.tolist()))
        kept_edges = [(key_of[a], key_of[b]) for a, b in g.subgraph(keep).edges()]
        return cls(pos_i, rot_i, hor_i, keys, kept_edges, kx, kz, raw[:, 1], g.number_of_nodes() - len(keep))


def _render(agent: _Agent, states: _States, frames: FrameWriter, cfg: LiveConfig, scene_name: str):
    """Teleport to every kept state and write its frames; returns the object table (from the first state's
    metadata), per state and object the visible pixels, boxes and AI2-THOR's ``visible`` flag, and the last
    event."""
    V = states.count
    objects: list[dict] | None = None
    lut_cols: dict[str, int] = {}
    thor_visible = None
    pixels = boxes = None
    ids_buf: list[np.ndarray] = []
    buf_start = 0

    def flush(upto: int):
        nonlocal buf_start, ids_buf
        if not ids_buf:
            return
        ids = np.stack(ids_buf)
        O = len(objects)
        lut = np.arange(O + 1, dtype=np.int64) - 1  # id map holds column + 1 (0 = no object)
        px, bx = (
            object_stats(ids, lut, O)
            if O
            else (np.zeros((len(ids), 0), np.int32), np.zeros((len(ids), 0, 4), np.int16))
        )
        pixels[buf_start:upto] = px
        boxes[buf_start:upto] = bx
        buf_start, ids_buf = upto, []

    ev = None
    for v in range(V):
        i, ri, hi = int(states.pos_i[v]), int(states.rot_i[v]), int(states.hor_i[v])
        key = states.keys[v]
        ev = agent.teleport(i, ROTATIONS[ri], HORIZONS[hi])
        if not agent.pose_ok(ev, i, ROTATIONS[ri], HORIZONS[hi]):
            raise LiveExportError(f"{scene_name}: teleport to state {key} failed while rendering")
        if objects is None:
            objects = _object_table(ev, cfg)
            lut_cols = {o["objectId"]: j for j, o in enumerate(objects)}
            O = len(objects)
            thor_visible = np.zeros((V, O), bool)
            pixels = np.zeros((V, O), np.int32)
            boxes = np.full((V, O, 4), -1, np.int16)
            _check_frames(ev, cfg.size, scene_name)
        frame, depth = np.asarray(ev.frame), np.asarray(ev.depth_frame)
        if frame.shape != (cfg.size, cfg.size, 3):
            raise LiveExportError(
                f"{scene_name}: frame of {key} is {frame.shape}, expected ({cfg.size}, {cfg.size}, 3)"
            )
        frames.add(key, frame.astype(np.uint8), depth)
        idmap = np.zeros(frame.shape[:2], np.int64)
        masks = ev.instance_masks
        for oid, j in lut_cols.items():
            m = masks.get(oid) if hasattr(masks, "get") else None
            if m is not None:
                idmap[np.asarray(m, dtype=bool)] = j + 1
        ids_buf.append(idmap)
        for oid in visible_object_ids(ev.metadata):
            j = lut_cols.get(oid)
            if j is not None:
                thor_visible[v, j] = True
        if len(ids_buf) >= cfg.chunk:
            flush(v + 1)
    flush(V)
    return objects, pixels, boxes, thor_visible, ev


def _write_tables(
    tmp: Path,
    states: _States,
    objects: list[dict],
    pixels: np.ndarray,
    boxes: np.ndarray,
    thor_visible: np.ndarray,
    cfg: LiveConfig,
) -> int:
    """Object distances, then ``visible_object_map_1.5.json``, ``grid.json``, ``graph.json`` and ``states.hdf5``
    (states in key order); returns the ``min_pixels`` used."""
    V, O = states.count, len(objects)
    kx, kz, pos_i, keys = states.kx, states.kz, states.pos_i, states.keys
    boxes3 = [_aabb(o) for o in objects]
    distance = np.full((V, O), np.nan, np.float32)
    has = np.array([b is not None for b in boxes3], bool)
    if has.any():
        bb = [b for b in boxes3 if b is not None]
        agent = np.stack([kx[pos_i], kz[pos_i]], 1)
        distance[:, has] = box_distance(
            agent, np.array([b[0] for b in bb]), np.array([b[1] for b in bb]), np.zeros(len(bb))
        )
    min_px = cfg.min_pixels()
    vis = (pixels >= min_px) & (distance <= cfg.visibility_distance)
    order = np.argsort(keys, kind="stable")
    keys_s = keys[order]
    vis_map = visible_object_map([o["objectId"] for o in objects], keys_s, vis[order])
    write_json(tmp / "visible_object_map_1.5.json", vis_map)
    write_json(
        tmp / "grid.json", [{"x": float(kx[i]), "y": float(states.y[i]), "z": float(kz[i])} for i in states.positions]
    )
    write_graph(tmp, keys_s.tolist(), sorted(states.edges))
    write_states(
        tmp,
        keys_s,
        [o["objectId"] for o in objects],
        pixels[order],
        boxes[order],
        distance[order],
        image_size=cfg.size,
        min_pixels=min_px,
        extra={"thor_visible": thor_visible[order]},
    )
    return min_px


def _scene_meta(
    scene_name: str, controller, ev, states: _States, objects: list[dict], min_px: int, cfg: LiveConfig
) -> dict:
    """``scene.json``: the objects with their boxes, the floor derived from the reachable grid, the scene bounds
    of the last event, the visibility rule and where the scene came from."""
    room_type, split = lineage_scene_info(scene_name)
    records = []
    for o in objects:
        b = _aabb(o)
        rec = {"objectId": o["objectId"], "objectType": o.get("objectType", o["objectId"].split("|")[0])}
        if isinstance(o.get("position"), dict):
            rec["position"] = {a: float(o["position"][a]) for a in "xyz"}
        if b is not None:
            rec["bbox"] = {"center": b[0], "size": b[1], "yaw": 0.0}
        if isinstance(o.get("axisAlignedBoundingBox"), dict):
            rec["axisAlignedBoundingBox"] = o["axisAlignedBoundingBox"]
        records.append(rec)
    positions = states.positions
    floor = derive_floor(np.stack([states.kx[positions], states.kz[positions]], 1))
    return {
        "format": "tsnav-scene",
        "version": 1,
        "name": scene_name,
        "room_type": room_type,
        "split": split,
        "rooms": [],
        "floor": [p.tolist() for p in floor],
        "furniture": [],
        "objects": records,
        "scene_bounds": scene_bounds(ev.metadata),
        "image_size": cfg.size,
        "visibility": {
            "min_pixels": min_px,
            "min_pixel_fraction": cfg.min_pixel_fraction,
            "distance": cfg.visibility_distance,
        },
        "num_states": states.count,
        "num_positions": int(len(positions)),
        "source": {
            "format": "ai2thor-live",
            "controller": type(controller).__name__,
            "settings": controller_settings(cfg.size),
            "config": asdict(cfg),
        },
        "derived": {
            "floor": "union of 0.25 m squares centred on the reachable positions, holes filled",
            "distance": "floor plane, agent position to the footprint of the object's axis-aligned box",
            "visible": "instance mask >= min_pixels and distance <= 1.5 m",
        },
    }


def _object_table(ev, cfg: LiveConfig) -> list[dict]:
    objs = [o for o in ev.metadata.get("objects", []) if isinstance(o, dict) and o.get("objectId")]
    if cfg.targets_only:
        objs = [o for o in objs if o.get("objectType", o["objectId"].split("|")[0]) in TARGET_CATEGORIES]
    return sorted(objs, key=lambda o: o["objectId"])


def _check_frames(ev, size: int, scene_name: str) -> None:
    if getattr(ev, "frame", None) is None:
        raise LiveExportError(f"{scene_name}: the controller returns no RGB frame")
    if getattr(ev, "depth_frame", None) is None:
        raise LiveExportError(f"{scene_name}: no depth frame; create the controller with renderDepthImage=True")
    if getattr(ev, "instance_segmentation_frame", None) is None or getattr(ev, "instance_masks", None) is None:
        raise LiveExportError(
            f"{scene_name}: no instance masks; create the controller with renderInstanceSegmentation=True"
        )
    shape = np.shape(ev.frame)
    if shape != (size, size, 3):
        raise LiveExportError(
            f"{scene_name}: the controller renders {shape} frames, expected ({size}, {size}, 3) "
            f"(create it with width=height={size})"
        )
