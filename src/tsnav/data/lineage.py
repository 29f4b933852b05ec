"""What the SAVN / VTNet / DOA / IOM / DAT code expects of an ``AI2Thor_offline_data_2.0.2`` scene folder.

The lineage's offline data is one folder per scene (``FloorPlan1`` ... or ``FloorPlan1_physics``) holding:

=================================  ======================================================================
``graph.json``                     networkx ``node_link_data`` of a ``DiGraph``: ``{"directed": true,
                                   "multigraph": false, "graph": {}, "nodes": [{"id": key}], "links":
                                   [{"source": key, "target": key}]}``; one edge per successful action
``grid.json``                      reachable positions ``[{"x": float, "y": float, "z": float}]``
``visible_object_map_1.5.json``    ``{objectId: [state key, ...]}`` (SAVN calls it ``visible_object_map.json``)
``metadata.json`` (older sets)     ``{state key: event.metadata}`` (the raw AI2-THOR metadata of each state)
``images.hdf5``                    one dataset per state key: RGB ``uint8 (H, W, 3)`` (300 x 300 in the lineage)
``depth.hdf5`` (optional)          one dataset per state key: depth ``(H, W)`` float, metres
``resnet18_featuremap.hdf5``       one dataset per state key: ``float32 (1, 512, 7, 7)`` (ResNet18's last
                                   feature map of the 224 x 224 frame, with the batch axis: IOM's model
                                   concatenates it with 4-d tensors)
``detr_features_22cls.hdf5`` /     one dataset per state key: ``float32 (R, 264)``, R = 22: columns 0-255 the
``det_feature_categories.hdf5``    DETR decoder feature, 256 the score, 257 the label (category index + 1;
                                   0 = padding, 23 = no object), 258-259 unused, 260-263 the box
                                   ``[x0, y0, x1, y1]`` in pixels of the 300 x 300 frame
``optimal_action.json``            ``{state key: {target type: action id}}``: a first action of a shortest
                                   path to the target (5 = Done where the state already succeeds)
``../test_val_split/``             the episode lists ``{room}_{test,val}_22.pkl`` (:mod:`lineage_splits`)
=================================  ======================================================================

State keys are ``"{x:.2f}|{z:.2f}|{rotation:d}|{horizon:d}"`` (``constants.state_key``); object ids
are AI2-THOR's ``Type|x|y|z`` (e.g. ``Fridge|-02.10|+00.00|+01.07``).

This module holds that format knowledge and the pieces shared by import and export: the floor polygon
derived from the reachable grid, and the conversion between the lineage's 22 x 264 detection table and
the detect stage's per-category table (:class:`tsnav.data.detections.Detections`).
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import h5py
import numpy as np
import shapely

from ..atomic import atomic_path
from ..constants import DEFAULT_CLASS_SET, GRID_SIZE, NUM_CATEGORIES
from .detections import Detections
from .reader import SceneFormatError


GRAPH_FILE = "graph.json"
GRID_FILE = "grid.json"
VISIBLE_MAP_FILE = "visible_object_map_1.5.json"
#: SAVN's name of the same map (the later papers renamed it after the 1.5 m visibility distance).
VISIBLE_MAP_FILE_SAVN = "visible_object_map.json"
METADATA_FILE = "metadata.json"
IMAGES_FILE = "images.hdf5"
DEPTH_FILE = "depth.hdf5"
RESNET_FILE = "resnet18_featuremap.hdf5"
#: Shape of one ResNet feature dataset (batch axis, channels, 7 x 7 grid) and the frame side it is made from.
RESNET_SHAPE = (1, 512, 7, 7)
RESNET_INPUT_SIZE = 224
OPTIMAL_ACTION_FILE = "optimal_action.json"
#: Folder of the episode lists, beside the scene folders.
SPLIT_DIR = "test_val_split"
#: Names under which the lineage stores the 22-class DETR table (DOA/IOM/DAT, then VTNet/HOZ).
DETECTION_FILES = ("detr_features_22cls.hdf5", "det_feature_categories.hdf5")
#: Name of the imported table in the detect stage's layout (``detections_<name>.hdf5``, tsnav.data.detections).
DETECTIONS_LINEAGE_NAME = "lineage"
DETECTIONS_LINEAGE_FILE = f"detections_{DETECTIONS_LINEAGE_NAME}.hdf5"
#: Other per-state files of the lineage that the import carries over unchanged.
EXTRA_FILES = (RESNET_FILE, OPTIMAL_ACTION_FILE)

#: Columns of the lineage's detection table.
FEATURE_DIM = 256
SCORE_COL = 256
LABEL_COL = 257
BOX_COLS = slice(260, 264)
TABLE_WIDTH = 264
#: Label of DETR's "no object" class in the table (labels 1..22 are the target categories).
NO_OBJECT_LABEL = NUM_CATEGORIES + 1
#: Label of the lineage's zero padding rows (never a target; tsnav never writes it, see table_to_22x264).
EMPTY_LABEL = 0
#: Attributes tsnav writes into a 22 x 264 file: rows in category order (row c = category c, "no object"
#: rows keep the class's score and feature), and the size of the feature before zero padding to 256.
OWN_ROWS_ATTR = "tsnav_category_rows"
FEATURE_DIM_ATTR = "tsnav_feature_dim"
#: Frame size the lineage's boxes refer to, pixels.
LINEAGE_IMAGE_SIZE = 300

#: A state key written by ``ThorAgentState.__str__``: two decimals for x and z, integer degrees.
KEY_PATTERN = re.compile(r"^-?\d+\.\d\d\|-?\d+\.\d\d\|\d+\|-?\d+$")


def visible_object_map(object_ids, keys, visible) -> dict[str, list[str]]:
    """The lineage's ``visible_object_map_1.5.json`` content: objectId -> the state keys (in ``keys`` order) where
    ``visible[:, j]`` is set. Objects visible from no state are left out, as the lineage's maps (built from
    AI2-THOR's visibility) never list one: IOM's planner returns no path for an empty list."""
    keys = np.asarray(keys, dtype=str)
    visible = np.asarray(visible, dtype=bool)
    return {str(oid): keys[visible[:, j]].tolist() for j, oid in enumerate(object_ids) if visible[:, j].any()}


def visibility_map_success_reference(folder: str | Path, keys) -> np.ndarray:
    """Slow, obviously-correct reference of ``Scene.success_table("lineage")``: ``(len(keys), 22)`` bool.

    Reads ``visible_object_map_1.5.json`` of the scene folder itself and, per state key and target category,
    does what the lineage's ``episodes/basic_episode.py::judge`` does on Done: loop over the object ids whose
    type (the id's first ``|`` field) is the category and succeed when the state key is listed for one.
    """
    import json

    from ..constants import TARGET_CATEGORIES

    with open(Path(folder) / VISIBLE_MAP_FILE) as f:
        vis_map = json.load(f)
    by_type: dict[str, list[set]] = {}
    for oid, states in vis_map.items():
        by_type.setdefault(str(oid).split("|")[0], []).append(set(states))
    out = np.zeros((len(keys), NUM_CATEGORIES), dtype=bool)
    for i, key in enumerate(keys):
        for c, name in enumerate(TARGET_CATEGORIES):
            for listed in by_type.get(name, []):
                if str(key) in listed:
                    out[i, c] = True
                    break
    return out


def parse_object_id(object_id: str) -> tuple[str, np.ndarray | None]:
    """``(objectType, position)`` of an AI2-THOR object id ``Type|x|y|z``; position ``(3,)`` metres or ``None``
    when the id carries none (e.g. ids of sliced objects with a fifth part keep the parent's position)."""
    parts = str(object_id).split("|")
    if len(parts) < 4:
        return parts[0], None
    try:
        return parts[0], np.array([float(parts[1]), float(parts[2]), float(parts[3])])
    except ValueError:
        return parts[0], None


# ------------------------------------------------------------------------------------------- floor
def derive_floor(grid_positions, cell: float = GRID_SIZE) -> list[np.ndarray]:
    """Floor polygons from reachable positions: the union of ``cell`` x ``cell`` squares centred on them.

    ``grid_positions``: ``(P, 2)`` array of (x, z) metres, or ``grid.json``'s list of ``{"x", "y", "z"}``.
    Returns a list of ``(N, 2)`` (x, z) exterior rings (closed: last vertex = first), one per connected
    part, largest first. Holes (where furniture stands) are filled: the floor continues under furniture and
    the searched area of TSRM (paper section III-B) counts floor seen around it. Every reachable position
    is the centre of its square, so the floor covers it with a margin of ``cell / 2``.
    """
    if isinstance(grid_positions, (list, tuple)) and grid_positions and isinstance(grid_positions[0], dict):
        pts = np.array([[p["x"], p["z"]] for p in grid_positions], dtype=np.float64)
    else:
        pts = np.asarray(grid_positions, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        raise ValueError("no reachable positions to derive a floor from")
    h = cell / 2
    cells = shapely.box(pts[:, 0] - h, pts[:, 1] - h, pts[:, 0] + h, pts[:, 1] + h)
    union = shapely.union_all(cells, grid_size=1e-6)
    parts = list(union.geoms) if hasattr(union, "geoms") else [union]
    parts = sorted((p for p in parts if p.area > 0), key=lambda p: -p.area)
    return [np.round(np.asarray(p.exterior.coords, dtype=np.float64), 6) for p in parts]


# ------------------------------------------------------------------------------- detection tables
def table_to_22x264(det, box_size: int | None = LINEAGE_IMAGE_SIZE) -> np.ndarray:
    """The lineage's ``(S, 22, 264)`` float32 rows from a tsnav detection table (row ``c`` = category ``c``).

    ``det``: a :class:`tsnav.data.detections.Detections`. Its ``F``-d features fill columns ``0..F-1``; when
    ``F < 256`` (tsnav's own detectors give 64-d) columns ``F..255`` are zero (zero padding: the lineage's
    linear layers over the 256 columns then see tsnav's vector unchanged, and the reader drops the padding
    again, :data:`FEATURE_DIM_ATTR`); ``F > 256`` raises ``ValueError``.

    A row with a kept detection (``labels[s, c] == c``): label ``c + 1``, the score, the box rescaled from
    ``det.image_size`` to ``box_size`` pixels (kept as it is when ``box_size`` is None). A row without one
    (label -1) reads like the lineage's DETR rows whose class is "no object": label :data:`NO_OBJECT_LABEL`
    (23), box ``[0, 0, 0, 0]`` (a box inside the frame, never tsnav's -1 marker), and the class's score and
    feature as tsnav's detector gave them (the lineage's agents zero such rows entirely with their
    ``detr_padding`` option). Label 0 is never written: the lineage's readers that gather rows with
    ``for cate_id in range(23): table[cate_id - 1] = ...`` would file a label-0 row under the last class.
    """
    if getattr(det, "class_set", DEFAULT_CLASS_SET) != DEFAULT_CLASS_SET:
        raise ValueError(
            f"the lineage's table holds iTHOR's 22 classes; this detection table is of class set {det.class_set}"
        )
    feats = np.asarray(det.features)
    F = feats.shape[2]
    if F > FEATURE_DIM:
        raise ValueError(
            f"the lineage's table holds {FEATURE_DIM}-d features; this detection table has {F}-d "
            f"(more than fit; only smaller features are zero-padded)"
        )
    labels = np.asarray(det.labels).astype(np.int64)
    kept = labels >= 0
    out = np.zeros((len(det.keys), NUM_CATEGORIES, TABLE_WIDTH), np.float32)
    out[:, :, :F] = feats.astype(np.float32)
    out[:, :, SCORE_COL] = np.asarray(det.scores, np.float32)
    out[:, :, LABEL_COL] = np.where(kept, labels + 1, NO_OBJECT_LABEL)
    boxes = np.asarray(det.boxes, np.float64)
    if box_size is not None and det.image_size and int(box_size) != int(det.image_size):
        boxes = boxes * (float(box_size) / float(det.image_size))
    out[:, :, BOX_COLS] = np.where(kept[:, :, None], boxes, 0.0).astype(np.float32)
    return out


def table_from_22x264(
    keys,
    rows: np.ndarray,
    image_size: int = LINEAGE_IMAGE_SIZE,
    out_size: int | None = None,
    source: str = "",
    own_rows: bool = False,
    feature_dim: int = FEATURE_DIM,
):
    """The best detection per category from the lineage's ``(S, R, 264)`` rows, as a
    :class:`tsnav.data.detections.Detections` (the inverse of :func:`table_to_22x264`).

    For each state and category ``c`` the row labelled ``c + 1`` with the highest score is taken (how the
    lineage's agents read DETR's table). Where no row carries that label the category has no detection:
    score 0, box -1, feature 0, label -1 (rows of DETR's "no object" class, 23, and of the zero padding, 0,
    never count as a detection). ``own_rows`` (a 22-row table written by :func:`table_to_22x264`, whose row
    ``c`` belongs to category ``c``): an undetected category keeps the score and feature of its own "no
    object" row, so such a table reads back exactly. ``feature_dim``: columns of the feature kept (tsnav's
    padded features read back at their own size). Boxes are rescaled from ``image_size`` to ``out_size``
    pixels when ``out_size`` is given.
    """
    rows = np.asarray(rows, dtype=np.float32)
    if rows.ndim != 3 or rows.shape[2] != TABLE_WIDTH:
        raise ValueError(f"expected (S, R, {TABLE_WIDTH}) detection rows, got shape {rows.shape}")
    if not 1 <= int(feature_dim) <= FEATURE_DIM:
        raise ValueError(f"feature_dim must be in 1..{FEATURE_DIM}, got {feature_dim}")
    S, R, _ = rows.shape
    cats = np.arange(NUM_CATEGORIES)
    lab = np.round(rows[:, :, LABEL_COL]).astype(np.int64)  # (S, R)
    match = lab[:, :, None] == (cats + 1)[None, None, :]  # (S, R, 22)
    best = np.argmax(np.where(match, rows[:, :, SCORE_COL][:, :, None], -np.inf), axis=1)  # (S, 22)
    found = match.any(axis=1)
    own = np.zeros_like(found)
    if own_rows and R == NUM_CATEGORIES:
        own = ~found & (lab == NO_OBJECT_LABEL)  # row c, "no object": its score and feature stay with c
    pick = np.where(found, best, np.minimum(cats, R - 1)[None, :])  # row c only matters when R == 22
    sel = np.take_along_axis(rows, pick[:, :, None], axis=1)  # (S, 22, 264)
    keep = found | own
    boxes = np.where(found[:, :, None], sel[:, :, BOX_COLS].astype(np.float64), -1.0)
    size = int(image_size)
    if out_size is not None and int(out_size) != size:
        boxes = np.where(found[:, :, None], boxes * (float(out_size) / float(size)), -1.0)
        size = int(out_size)
    return Detections(
        keys=np.asarray(keys, dtype=str),
        scores=np.where(keep, sel[:, :, SCORE_COL], 0).astype(np.float32),
        labels=np.where(found, cats[None, :], -1).astype(np.int16),
        boxes=boxes.astype(np.float32),
        features=np.where(keep[:, :, None], sel[:, :, : int(feature_dim)], 0).astype(np.float16),
        detector="lineage",
        config={"source": source, "box_frame": size},
        fingerprint=_rows_fingerprint(rows),
        image_size=size,
    )


def _rows_fingerprint(rows: np.ndarray) -> str:
    return "lineage-" + hashlib.sha256(np.ascontiguousarray(rows).tobytes()).hexdigest()[:16]


def read_detections_22x264(path: str | Path, image_size: int = LINEAGE_IMAGE_SIZE, keys=None):
    """Read a lineage detection file (one ``(R, 264)`` dataset per state key) as
    :class:`tsnav.data.detections.Detections`.

    ``keys``: the states to read, in order (default: every dataset of the file, sorted); a key the file lacks
    gets an empty row (score 0, label -1, box -1). Boxes stay in pixels of the ``image_size`` frame they
    were computed on (300 in the lineage). :class:`SceneFormatError` naming the file and the problem for a
    missing or truncated file or a dataset of the wrong shape.
    """
    path = Path(path)
    if not path.exists():
        raise SceneFormatError(f"{path}: missing file")
    try:
        with h5py.File(path, "r") as f:
            names = sorted(f.keys()) if keys is None else [str(k) for k in keys]
            if not names:
                raise SceneFormatError(f"{path}: no state datasets")
            stack, present = [], []
            for k in names:
                if k not in f:
                    stack.append(None)
                    continue
                d = f[k]
                if not isinstance(d, h5py.Dataset) or d.ndim != 2 or d.shape[1] != TABLE_WIDTH:
                    shape = getattr(d, "shape", "a group")
                    raise SceneFormatError(f"{path}: state {k!r} holds {shape}, expected an (R, {TABLE_WIDTH}) table")
                stack.append(d[()])
                present.append(len(stack) - 1)
            counts = {stack[i].shape[0] for i in present}
            if len(counts) > 1:
                raise SceneFormatError(f"{path}: states hold tables with different row counts {sorted(counts)}")
            if not present:
                raise SceneFormatError(f"{path}: none of the requested states is in the file")
            own_rows = bool(f.attrs.get(OWN_ROWS_ATTR, False))
            fdim = int(f.attrs.get(FEATURE_DIM_ATTR, FEATURE_DIM))
    except OSError as e:
        raise SceneFormatError(f"{path}: unreadable HDF5 ({' '.join(str(e).split())})") from None
    R = counts.pop()
    empty = np.zeros((R, TABLE_WIDTH), np.float32)
    empty[:, LABEL_COL] = NO_OBJECT_LABEL
    rows = np.stack([empty if a is None else a for a in stack]).astype(np.float32)
    try:
        return table_from_22x264(
            names, rows, image_size=image_size, source=path.name, own_rows=own_rows, feature_dim=fdim
        )
    except ValueError as e:
        raise SceneFormatError(f"{path}: {e}") from None


def write_detections_22x264(path: str | Path, det, box_size: int | None = LINEAGE_IMAGE_SIZE) -> Path:
    """Write the lineage's file from a :class:`tsnav.data.detections.Detections`: one float32 ``(22, 264)``
    dataset per state key (rows of :func:`table_to_22x264`; atomic: a temporary file renamed when complete).
    File attributes :data:`OWN_ROWS_ATTR` and :data:`FEATURE_DIM_ATTR` let :func:`read_detections_22x264`
    read it back exactly; the lineage's code ignores them."""
    path = Path(path)
    rows = table_to_22x264(det, box_size)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        for k, r in zip(np.asarray(det.keys, dtype=str).tolist(), rows):
            f.create_dataset(k, data=r, track_times=False)
        f.attrs["box_frame"] = int(box_size if box_size is not None else det.image_size)
        f.attrs[OWN_ROWS_ATTR] = True
        f.attrs[FEATURE_DIM_ATTR] = int(np.asarray(det.features).shape[2])
    return path
