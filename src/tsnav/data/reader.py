"""Read a scene folder (lineage layout, DESIGN.md "The offline dataset") into integer arrays.

The read side never loops over states in Python: keys are parsed with numpy string operations, edges are
mapped to state ids with ``searchsorted``, and each edge's action is derived from the geometry of its two
keys (edges carry no action label in the lineage's ``graph.json``).

Files read (per scene folder):
    graph.json                      networkx node-link directed graph over state keys
    grid.json                       reachable positions [{"x","y","z"}]
    visible_object_map_1.5.json     objectId -> state keys from which it is visible within 1.5 m
    scene.json                      this project's scene description (floor polygons, objects, furniture)
    states.hdf5                     this project's per-state, per-object tables (pixels, boxes, distances)
    images.hdf5 / depth.hdf5        optional observations keyed by state key
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from ..constants import (
    DONE,
    GRID_SIZE,
    ITHOR22,
    LOOK_DOWN,
    LOOK_UP,
    MOVE_AHEAD,
    NUM_ACTIONS,
    ROTATE_LEFT,
    ROTATE_RIGHT,
    ROTATE_STEP,
    SUCCESS_DISTANCE,
    ClassSet,
    class_set_of,
    parse_state_keys,
)
from ..errors import read_json
from ..protocol import DEFAULT_PROTOCOL, PAPER, check_protocol

COMPLETE_MARKER = "COMPLETE"

#: Suffix of a mirrored scene's name and of the caches written for it (``features_<name>-mirror.hdf5``,
#: ``detections_<name>-mirror.hdf5``): :meth:`Scene.mirrored`.
MIRROR_SUFFIX = "-mirror"
#: Action ids as seen in the mirror image: RotateLeft and RotateRight trade places, the rest keep theirs.
MIRROR_ACTIONS = np.array([MOVE_AHEAD, ROTATE_RIGHT, ROTATE_LEFT, LOOK_UP, LOOK_DOWN, DONE], dtype=np.int64)


class SceneFormatError(ValueError):
    """A scene folder is missing a file or holds malformed content."""


@dataclass
class Scene:
    """A scene as arrays. ``S`` states, ``O`` objects (targets and other objects of ``scene.json``).

    Attributes:
        name: scene name, e.g. ``FloorPlan1``.
        path: the scene folder.
        keys: ``(S,)`` state keys, sorted; state id = index.
        x, z: ``(S,)`` float32 position, metres. rotation, horizon: ``(S,)`` int16 degrees.
        next_state: ``(S, 6)`` int32 state reached by each action of ``constants.ACTIONS``; the state itself
            when the action fails (a MoveAhead collision, or a look past horizons 0 / 30) and for Done.
        object_ids: ``(O,)`` AI2-THOR-style object ids; object_category: ``(O,)`` index into
            ``class_set.categories`` (-1 for non-target objects).
        visible: ``(S, O)`` bool, from ``visible_object_map_1.5.json`` (in view and within 1.5 m).
        distance: ``(S, O)`` float32 metres on the floor plane from the agent position to the nearest point of
            the object's footprint (the success distance of paper III-A),
            (NaN when unknown, e.g. imported data without metadata).
        pixels: ``(S, O)`` int32 visible pixel count in the rendered frame (-1 when unknown).
        boxes: ``(S, O, 4)`` int16 ``[x0, y0, x1, y1]`` pixel box of the visible part (-1 when not visible).
        floor: list of floor polygons, each ``(N, 2)`` float array of (x, z) metres.
        image_size: side of the square frames the tables refer to, pixels.
        meta: the parsed ``scene.json`` (empty dict when absent).
        mirror: the scene is the mirror image of its folder's room (:meth:`mirrored`).
        class_set: the target classes (:class:`~tsnav.constants.ClassSet`) that ``scene.json`` declares
            (``"class_set"``; absent: ``ithor22``); ``C`` below is its size (22 or 12).
    """

    name: str
    path: Path
    keys: np.ndarray
    x: np.ndarray
    z: np.ndarray
    rotation: np.ndarray
    horizon: np.ndarray
    next_state: np.ndarray
    object_ids: np.ndarray
    object_category: np.ndarray
    visible: np.ndarray
    distance: np.ndarray
    pixels: np.ndarray
    boxes: np.ndarray
    floor: list = field(default_factory=list)
    image_size: int = 0
    meta: dict = field(default_factory=dict)
    mirror: bool = False
    class_set: ClassSet = ITHOR22

    @property
    def num_categories(self) -> int:
        """``C``: columns of the per-category tables (the class set's size)."""
        return self.class_set.size

    @property
    def num_states(self) -> int:
        return len(self.keys)

    def index(self, key: str) -> int:
        """State id of ``key``; ``KeyError`` naming the key when it is not a state of this scene."""
        i = int(np.searchsorted(self.keys, key))
        if i >= len(self.keys) or self.keys[i] != key:
            raise KeyError(f"state {key!r} is not in scene {self.name}")
        return i

    def indices(self, keys) -> np.ndarray:
        """Vectorised :meth:`index`; raises ``KeyError`` naming the first unknown key."""
        keys = np.asarray(keys, dtype=self.keys.dtype)
        idx = np.searchsorted(self.keys, keys)
        idx_c = np.minimum(idx, len(self.keys) - 1)
        bad = self.keys[idx_c] != keys
        if bad.any():
            raise KeyError(f"state {str(keys[bad][0])!r} is not in scene {self.name}")
        return idx_c.astype(np.int64)

    def category_visible_within(self, distance: float = SUCCESS_DISTANCE) -> np.ndarray:
        """``(S, C)`` bool: some instance of the category is in view and within ``distance`` metres.

        This is the success condition of the paper (section III-A) with ``distance`` = 1.0 m. When the
        scene has no distances (imported without metadata) it falls back to the 1.5 m visibility map.
        """
        if np.isnan(self.distance).all():
            obj_ok = self.visible
        else:
            obj_ok = self.visible_at_any_range() & (self.distance <= distance)
        return self._per_category(obj_ok)

    def success_table(self, protocol: str = DEFAULT_PROTOCOL, distance: float = SUCCESS_DISTANCE) -> np.ndarray:
        """``(S, C)`` bool: Done in a state succeeds for the category under the success ``protocol``
        (:mod:`tsnav.protocol`) - the one place that turns a protocol into a success mask.

        ``paper``: :meth:`category_visible_within` ``(distance)`` (1.0 m, paper III-A). ``lineage``: some object id
        of the category lists the state in ``visible_object_map_1.5.json`` (``visible``), as the lineage's
        ``basic_episode.judge`` asks it; ``distance`` is not used. Slow reference:
        :func:`tsnav.data.lineage.visibility_map_success_reference`.
        """
        if check_protocol(protocol) == PAPER:
            return self.category_visible_within(distance)
        return self._per_category(self.visible)

    def _per_category(self, obj_ok: np.ndarray) -> np.ndarray:
        """``(S, O)`` per-object flags -> ``(S, C)``: any object of the category."""
        out = np.zeros((self.num_states, self.num_categories), dtype=bool)
        tgt = self.object_category >= 0
        if tgt.any():
            cats = self.object_category[tgt]
            # Scatter-or over objects of the same category: one column per object, reduced per category.
            onehot = np.zeros((tgt.sum(), self.num_categories), dtype=np.int32)
            onehot[np.arange(tgt.sum()), cats] = 1
            out = (obj_ok[:, tgt].astype(np.int32) @ onehot) > 0
        return out

    def visible_at_any_range(self) -> np.ndarray:
        """``(S, O)`` bool: the object shows enough pixels to count as seen (visibility rule of the writer)."""
        min_px = int(self.meta.get("visibility", {}).get("min_pixels", 1))
        return self.pixels >= min_px if (self.pixels >= 0).any() else self.visible

    def category_in_frame(self) -> np.ndarray:
        """``(S, C)`` bool: some instance of the category shows in the frame at any range (:meth:`visible_at_any_range`)."""
        return self._per_category(self.visible_at_any_range())

    def success_mask(self, category: str | int, distance: float = SUCCESS_DISTANCE) -> np.ndarray:
        """``(S,)`` bool: Done in this state succeeds for ``category`` (name or index)."""
        c = self.class_set.index[category] if isinstance(category, str) else int(category)
        return self.category_visible_within(distance)[:, c]

    def categories_present(self) -> list[int]:
        """Indices of target categories with at least one instance in the scene."""
        return sorted(set(int(c) for c in self.object_category if c >= 0))

    def mirrored(self) -> "Scene":
        """The mirror image of the room across the z axis (a deviation from the paper: training-data augmentation).

        The same states, ids and keys; each state is the mirror of the state of the same id: position ``(-x, z)``,
        rotation ``-r`` (mod 360), the same horizon, so every heading and MoveAhead stays consistent with
        :data:`~tsnav.constants.ROTATIONS`' convention. RotateLeft and RotateRight trade their successors
        (:data:`MIRROR_ACTIONS`); MoveAhead, the looks and Done keep theirs, so path lengths, visibility, distances
        and success are those of the room. Boxes and floor polygons are mirrored; ``meta`` is the room's (its
        object poses are not mirrored; ``meta["mirror"]`` says so). The frames of the mirrored scene are its
        folder's frames flipped left to right: caches made from them carry :data:`MIRROR_SUFFIX`
        (:meth:`cache_name`). Mirroring twice gives the room back.
        """
        boxes = self.boxes.copy()
        seen = boxes[..., 0] >= 0
        w = self.image_size - 1
        x0, x1 = boxes[..., 0].copy(), boxes[..., 2].copy()
        boxes[..., 0] = np.where(seen, w - x1, x0)
        boxes[..., 2] = np.where(seen, w - x0, x1)
        name = self.name[: -len(MIRROR_SUFFIX)] if self.mirror else self.name + MIRROR_SUFFIX
        meta = {k: v for k, v in self.meta.items() if k != "mirror"}
        if not self.mirror:
            meta["mirror"] = True
        return Scene(
            name=name,
            path=self.path,
            keys=self.keys,
            x=(-self.x).astype(self.x.dtype) + 0.0,
            z=self.z,
            rotation=((360 - self.rotation.astype(np.int64)) % 360).astype(self.rotation.dtype),
            horizon=self.horizon,
            next_state=self.next_state[:, MIRROR_ACTIONS].copy(),
            object_ids=self.object_ids,
            object_category=self.object_category,
            visible=self.visible,
            distance=self.distance,
            pixels=self.pixels,
            boxes=boxes,
            floor=[np.stack([-p[:, 0], p[:, 1]], axis=1) + 0.0 for p in self.floor],
            image_size=self.image_size,
            meta=meta,
            mirror=not self.mirror,
            class_set=self.class_set,
        )

    def cache_name(self, name: str) -> str:
        """The name under which this scene's caches ``name`` are stored: ``name`` + :data:`MIRROR_SUFFIX` for a
        mirrored scene (features and detections of the flipped frames), else ``name``."""
        return name + MIRROR_SUFFIX if self.mirror else name

    @property
    def room_type(self) -> str:
        return str(self.meta.get("room_type", "unknown"))

    def images_path(self) -> Path | None:
        p = self.path / "images.hdf5"
        return p if p.exists() else None

    def depth_path(self) -> Path | None:
        p = self.path / "depth.hdf5"
        return p if p.exists() else None


def _load_json(path: Path):
    return read_json(path, SceneFormatError, missing="missing file")


def edge_actions(x0, z0, r0, h0, x1, z1, r1, h1) -> np.ndarray:
    """Action id of each edge from the geometry of its two states; -1 where no single action fits."""
    dx = np.round((x1 - x0) / GRID_SIZE).astype(np.int64)
    dz = np.round((z1 - z0) / GRID_SIZE).astype(np.int64)
    dr = (r1.astype(np.int64) - r0.astype(np.int64)) % 360
    dh = h1.astype(np.int64) - h0.astype(np.int64)
    same_pos = (dx == 0) & (dz == 0)
    act = np.full(len(dx), -1, dtype=np.int64)
    act[same_pos & (dh == 0) & (dr == ROTATE_STEP)] = ROTATE_RIGHT
    act[same_pos & (dh == 0) & (dr == 360 - ROTATE_STEP)] = ROTATE_LEFT
    act[same_pos & (dr == 0) & (dh > 0)] = LOOK_DOWN
    act[same_pos & (dr == 0) & (dh < 0)] = LOOK_UP
    # MoveAhead: one grid step along the heading (diagonal headings move one step in both x and z).
    rad = np.deg2rad(r0.astype(np.float64))
    ex = np.round(np.sin(rad)).astype(np.int64)
    ez = np.round(np.cos(rad)).astype(np.int64)
    act[(~same_pos) & (dr == 0) & (dh == 0) & (dx == ex) & (dz == ez)] = MOVE_AHEAD
    return act


def load_scene(path: str | Path) -> Scene:
    """Load a scene folder into a :class:`Scene`. Raises :class:`SceneFormatError` with a one-line reason."""
    path = Path(path)
    if not path.is_dir():
        raise SceneFormatError(f"{path}: not a scene folder")
    graph = _load_json(path / "graph.json")
    try:
        node_keys = [n["id"] for n in graph["nodes"]]
        link_key = "links" if "links" in graph else "edges"
        src_keys = [e["source"] for e in graph[link_key]]
        dst_keys = [e["target"] for e in graph[link_key]]
    except (KeyError, TypeError):
        raise SceneFormatError(f"{path / 'graph.json'}: not a networkx node-link graph") from None
    keys = np.array(sorted(node_keys))
    if len(keys) == 0:
        raise SceneFormatError(f"{path / 'graph.json'}: the graph has no states")
    try:
        x, z, rot, hor = parse_state_keys(keys)
    except ValueError as e:
        raise SceneFormatError(f"{path / 'graph.json'}: {e}") from None
    n = len(keys)

    def ids(k, what, file="graph.json"):
        k = np.asarray(k, dtype=keys.dtype)
        i = np.minimum(np.searchsorted(keys, k), n - 1)
        bad = keys[i] != k
        if bad.any():
            of = "" if file == "graph.json" else " of graph.json"
            raise SceneFormatError(f"{path / file}: {what} {str(k[bad][0])!r} is not a node{of}")
        return i

    src = ids(src_keys, "edge source")
    dst = ids(dst_keys, "edge target")
    act = edge_actions(x[src], z[src], rot[src], hor[src], x[dst], z[dst], rot[dst], hor[dst])
    if (act < 0).any():
        j = int(np.flatnonzero(act < 0)[0])
        raise SceneFormatError(f"{path / 'graph.json'}: edge {keys[src[j]]} -> {keys[dst[j]]} is not a single action")
    next_state = np.repeat(np.arange(n, dtype=np.int32)[:, None], NUM_ACTIONS, axis=1)
    next_state[src, act] = dst
    assert DONE == NUM_ACTIONS - 1

    meta = _load_json(path / "scene.json") if (path / "scene.json").exists() else {}
    vis_map = (
        _load_json(path / "visible_object_map_1.5.json") if (path / "visible_object_map_1.5.json").exists() else {}
    )

    objs = meta.get("objects", [])
    object_ids = [o["objectId"] for o in objs]
    seen = set(object_ids)
    object_ids += sorted(k for k in vis_map if k not in seen)
    object_ids = np.array(object_ids, dtype=str) if object_ids else np.zeros(0, dtype="<U1")
    try:
        classes = class_set_of(meta)
    except ValueError as e:
        raise SceneFormatError(f"{path / 'scene.json'}: {e}") from None
    cat = object_categories(object_ids, classes)

    visible = np.zeros((n, len(object_ids)), dtype=bool)
    col = {o: j for j, o in enumerate(object_ids.tolist())}
    for oid, state_list in vis_map.items():
        if state_list:
            visible[ids(state_list, f"visible state of {oid}", "visible_object_map_1.5.json"), col[oid]] = True

    distance = np.full((n, len(object_ids)), np.nan, dtype=np.float32)
    pixels = np.full((n, len(object_ids)), -1, dtype=np.int32)
    boxes = np.full((n, len(object_ids), 4), -1, dtype=np.int16)
    image_size = int(meta.get("image_size", 0))
    if (path / "states.hdf5").exists():
        image_size = _read_object_states(path / "states.hdf5", ids, col, distance, pixels, boxes, image_size)

    floor = [np.asarray(p, dtype=np.float64) for p in meta.get("floor", [])]
    return Scene(
        name=str(meta.get("name", path.name)),
        path=path,
        keys=keys,
        x=x,
        z=z,
        rotation=rot,
        horizon=hor,
        next_state=next_state,
        object_ids=object_ids,
        object_category=cat,
        visible=visible,
        distance=distance,
        pixels=pixels,
        boxes=boxes,
        floor=floor,
        image_size=image_size,
        meta=meta,
        class_set=classes,
    )


def object_categories(object_ids, classes: ClassSet) -> np.ndarray:
    """``(O,)`` int16 column in ``classes`` of each object, from the type its id starts with (``Mug|+01.00|...``,
    as AI2-THOR forms ids); -1 for a non-target object."""
    idx = classes.index
    return np.array([idx.get(str(o).split("|")[0], -1) for o in object_ids], dtype=np.int16)


def _read_object_states(
    st_path: Path, ids, col: dict, distance: np.ndarray, pixels: np.ndarray, boxes: np.ndarray, image_size: int
) -> int:
    """Fill the per state and object ``distance``, ``pixels`` and ``boxes`` from ``states.hdf5`` (``ids``: state
    keys to rows, ``col``: object id to column); returns the image size it records (else ``image_size``)."""
    try:
        with h5py.File(st_path, "r") as f:
            st_keys = f["keys"][()].astype(str)
            st_objs = f["object_ids"][()].astype(str)
            rows = ids(st_keys, "key", "states.hdf5")
            cols = np.array([col[o] for o in st_objs], dtype=np.int64)
            distance[np.ix_(rows, cols)] = f["distance"][()]
            pixels[np.ix_(rows, cols)] = f["pixels"][()]
            boxes[rows[:, None], cols[None, :]] = f["boxes"][()]
            return int(f.attrs.get("image_size", image_size))
    except (OSError, KeyError) as e:
        raise SceneFormatError(f"{st_path}: unreadable ({e})") from None


def is_complete(path: str | Path) -> bool:
    """True when ``path`` is a scene folder that the writer finished."""
    return (Path(path) / COMPLETE_MARKER).exists()


def list_scenes(root: str | Path, split: str | None = None) -> list[Path]:
    """Complete scene folders under a dataset root, optionally only those of ``split`` (train/val/test).

    The split comes from the dataset's ``index.json`` when present, else from each ``scene.json``.
    """
    root = Path(root)
    if not root.is_dir():
        raise SceneFormatError(f"{root}: no such dataset folder")
    out = []
    for p in sorted(root.iterdir()):
        if not p.is_dir() or not is_complete(p):
            continue
        if split is not None:
            meta = _load_json(p / "scene.json") if (p / "scene.json").exists() else {}
            if meta.get("split") != split:
                continue
        out.append(p)
    return out


def read_stack(f: h5py.File, keys) -> np.ndarray:
    """The datasets ``keys`` of the open HDF5 file ``f`` stacked in that order: ``(len(keys), *shape)`` in the
    first dataset's dtype (every frame file of a scene folder: one dataset per state key).

    Reads through h5py's low-level calls, about 7x less overhead a dataset than ``f[key][()]`` (the reference,
    :func:`read_stack_reference`), which pays for itself on gzip-compressed frames (the writers' default). A
    missing key raises ``KeyError`` naming it; datasets of different shapes raise :class:`SceneFormatError`.
    """
    keys = [str(k) for k in keys]
    if not keys:
        raise ValueError("read_stack needs at least one key")
    out = None
    for i, k in enumerate(keys):
        try:
            d = h5py.h5d.open(f.id, k.encode())
        except KeyError:
            raise KeyError(f"{f.filename}: no dataset {k!r}") from None
        if out is None:
            out = np.empty((len(keys),) + tuple(d.shape), dtype=d.dtype)
        elif tuple(d.shape) != out.shape[1:]:
            raise SceneFormatError(f"{f.filename}: dataset {k!r} has shape {d.shape}, the first has {out.shape[1:]}")
        d.read(h5py.h5s.ALL, h5py.h5s.ALL, out[i])
    return out


def read_stack_reference(f: h5py.File, keys) -> np.ndarray:
    """Reference of :func:`read_stack`: ``np.stack([f[k][()] for k in keys])``."""
    return np.stack([f[str(k)][()] for k in keys])
