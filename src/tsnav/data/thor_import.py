"""Import the lineage's AI2-THOR offline data (``AI2Thor_offline_data_2.0.2``) as tsnav scene folders.

A lineage scene folder (layout in :mod:`tsnav.data.lineage`) already loads with
:func:`tsnav.data.reader.load_scene`: states, transitions and the visibility map come from ``graph.json``
and ``visible_object_map_1.5.json``. What it lacks is what tsnav derives here and writes next to the
lineage's files:

* **floor** (``scene.json``): :func:`tsnav.data.lineage.derive_floor` of ``grid.json`` (0.25 m squares
  around the reachable positions, holes filled); it covers every reachable position.
* **objects** (``scene.json``): every objectId of the visibility map (``Type|x|y|z`` gives type and
  position) and, when ``metadata.json`` is there, every object of its per-state metadata with its
  ``axisAlignedBoundingBox``.
* **distances** (``states.hdf5``, only with ``metadata.json``): on the floor plane, from the state's
  position to the nearest point of the footprint of the object's ``axisAlignedBoundingBox`` (to its
  position when it has no box), as tsnav's own scenes measure it (``writer.box_distance``). The paper's
  success rule then applies: visible (1.5 m map) and within 1.0 m. Without ``metadata.json`` no distance is known and success falls
  back to the lineage's rule, the visibility map alone (``Scene.category_visible_within``).
* **detections** (``detections_lineage.hdf5``): the 22 x 264 DETR table of ``detr_features_22cls.hdf5`` /
  ``det_feature_categories.hdf5`` in the detect stage's layout (:mod:`tsnav.data.detections`; best row per
  category, boxes in pixels of the lineage's 300 x 300 frames, empty rows for states the file lacks).

The lineage's own files are carried over (hard-linked when possible, else copied; ``copy_mode``), so the
imported folder still works with the lineage's code. Writing goes through :mod:`tsnav.data.writer`: a hidden
temporary folder, checked with ``load_scene`` and renamed when complete (``COMPLETE`` marker).
"""

from __future__ import annotations

import os
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import h5py
import numpy as np

from ..constants import GRID_SIZE, VISIBILITY_DISTANCE
from ..errors import read_json
from . import lineage as L
from .detections import write_detections
from .names import lineage_scene_info
from .reader import COMPLETE_MARKER, SceneFormatError, load_scene
from .writer import box_distance, scene_folder, write_json, write_states


@dataclass
class ImportConfig:
    """Settings of :func:`import_lineage_scene`."""

    copy_mode: str = "link"
    """How the lineage's large files (images, depth, features, metadata) reach the new folder: ``link``
    (hard link, copy when linking is impossible), ``copy``, or ``none`` (leave them out)."""
    detection_image_size: int = L.LINEAGE_IMAGE_SIZE
    """Frame size the lineage's detection boxes refer to, pixels (300 in ``AI2Thor_offline_data_2.0.2``)."""
    overwrite: bool = False
    """Replace a complete destination folder instead of skipping it."""


@dataclass
class ImportStats:
    """What one import did."""

    name: str
    states: int = 0
    positions: int = 0
    objects: int = 0
    distances: bool = False
    detections: bool = False
    image_size: int = 0
    skipped: bool = False
    files: list = field(default_factory=list)
    warnings: list = field(default_factory=list)


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())


def _load_json(path: Path):
    return read_json(path, SceneFormatError, missing="missing file")


def _read_grid(path: Path) -> np.ndarray:
    """``grid.json`` as a ``(P, 3)`` float64 array of x, y, z."""
    grid = _load_json(path)
    try:
        arr = np.array([[float(p["x"]), float(p.get("y", 0.0)), float(p["z"])] for p in grid], dtype=np.float64)
    except (TypeError, KeyError, ValueError, AttributeError):
        raise SceneFormatError(f'{path}: expected a list of reachable positions {{"x", "y", "z"}}') from None
    if len(arr) == 0:
        raise SceneFormatError(f"{path}: no reachable positions")
    return arr


def _is_raw_metadata(obj) -> bool:
    """The lineage's test: a ``metadata.json`` keyed by state keys (raw metadata) rather than by objectIds."""
    if not isinstance(obj, dict) or not obj:
        return False
    try:
        float(next(iter(obj)).split("|")[0])
        return True
    except ValueError:
        return False


def _check_visible_map(path: Path, vis) -> dict:
    if not isinstance(vis, dict) or not all(isinstance(v, list) for v in vis.values()):
        raise SceneFormatError(f"{path}: expected {{objectId: [state key, ...]}}")
    return vis


def _state_ids(scene, keys, what: str) -> np.ndarray:
    """State ids of ``keys``; :class:`SceneFormatError` naming ``what`` and the first key not in the graph."""
    k = np.asarray(list(keys), dtype=str)
    if k.size == 0:
        return np.zeros(0, np.int64)
    idx = np.minimum(np.searchsorted(scene.keys, k), scene.num_states - 1)
    bad = scene.keys[idx] != k
    if bad.any():
        raise SceneFormatError(f"{what}: state key {str(k[bad][0])!r} is not a state of graph.json")
    return idx.astype(np.int64)


def _objects_from_metadata(path: Path, raw: dict, scene):
    """Objects (objectId -> first record) and visible (state id, objectId) pairs from the lineage's raw
    ``metadata.json`` (state key -> AI2-THOR event metadata)."""
    objects: dict[str, dict] = {}
    rows, oids = [], []
    ids = _state_ids(scene, raw.keys(), str(path))
    for sid, (key, m) in zip(ids.tolist(), raw.items()):
        if not isinstance(m, dict) or not isinstance(m.get("objects"), list):
            raise SceneFormatError(f"{path}: state {key!r} has no 'objects' list")
        for o in m["objects"]:
            oid = o.get("objectId") if isinstance(o, dict) else None
            if not oid:
                raise SceneFormatError(f"{path}: state {key!r} holds an object without 'objectId'")
            if oid not in objects:
                objects[oid] = o
            if o.get("visible"):
                rows.append(sid)
                oids.append(oid)
    return objects, rows, oids


def _object_record(oid: str, o: dict | None) -> dict:
    """scene.json entry: id, type, position, and box (base centre, size, yaw 0) when known."""
    otype, pos = L.parse_object_id(oid)
    rec: dict = {"objectId": oid, "objectType": str((o or {}).get("objectType", otype))}
    box = (o or {}).get("axisAlignedBoundingBox")
    p = (o or {}).get("position")
    if isinstance(p, dict):
        pos = np.array([float(p["x"]), float(p["y"]), float(p["z"])])
    if isinstance(box, dict) and isinstance(box.get("center"), dict) and isinstance(box.get("size"), dict):
        c = [float(box["center"][a]) for a in "xyz"]
        s = [float(box["size"][a]) for a in "xyz"]
        rec["bbox"] = {"center": [c[0], c[1] - s[1] / 2, c[2]], "size": s, "yaw": 0.0}
        if pos is None:
            pos = np.array(c)
    elif pos is not None:
        rec["bbox"] = {"center": [float(v) for v in pos], "size": [0.0, 0.0, 0.0], "yaw": 0.0}
    if pos is not None:
        rec["position"] = {"x": float(pos[0]), "y": float(pos[1]), "z": float(pos[2])}
    return rec


def _place(src: Path, dst: Path, mode: str) -> None:
    if mode == "link":
        try:
            os.link(src, dst)
            return
        except OSError:
            pass
    shutil.copy2(src, dst)


def _check_images(path: Path, scene, what: str, channels: bool) -> tuple[int, list[str]]:
    """Open an image-like HDF5 file keyed by state; returns (frame size, warnings)."""
    try:
        with h5py.File(path, "r") as f:
            keys = sorted(f.keys())
            if not keys:
                raise SceneFormatError(f"{path}: no state datasets")
            _state_ids(scene, keys, str(path))
            d = f[keys[0]]
            if not isinstance(d, h5py.Dataset):
                raise SceneFormatError(f"{path}: state {keys[0]!r} is a group, expected a dataset")
            if channels and (d.dtype != np.uint8 or d.ndim != 3 or d.shape[2] != 3):
                raise SceneFormatError(f"{path}: state {keys[0]!r} holds {d.dtype} {d.shape}, expected uint8 (H, W, 3)")
            if not channels and (d.dtype.kind != "f" or d.ndim != 2):
                raise SceneFormatError(f"{path}: state {keys[0]!r} holds {d.dtype} {d.shape}, expected float (H, W)")
            size = int(d.shape[1])
    except OSError as e:
        raise SceneFormatError(f"{path}: unreadable HDF5 ({_one_line(e)})") from None
    warn = []
    missing = scene.num_states - len(keys)
    if missing > 0:
        warn.append(f"{what}: no frame for {missing} of {scene.num_states} states")
    return size, warn


def import_lineage_scene(src_dir: str | Path, dst_dir: str | Path, config: ImportConfig | None = None) -> ImportStats:
    """Import one lineage scene folder ``src_dir`` as the tsnav scene folder ``dst_dir`` (see the module doc).

    Skips a complete ``dst_dir`` unless ``config.overwrite``. Raises :class:`SceneFormatError` with a
    one-line reason naming the file for missing files, malformed JSON, keys that are not states of
    ``graph.json`` and unreadable HDF5 files.
    """
    cfg = config or ImportConfig()
    if cfg.copy_mode not in ("link", "copy", "none"):
        raise ValueError(f"copy_mode must be 'link', 'copy' or 'none', not {cfg.copy_mode!r}")
    src, dst = Path(src_dir), Path(dst_dir)
    stats = ImportStats(name=dst.name)
    if not src.is_dir():
        raise SceneFormatError(f"{src}: not a scene folder")
    if (dst / COMPLETE_MARKER).exists() and not cfg.overwrite:
        stats.skipped = True
        return stats
    vis_path, meta_path = _sources(src)

    # States and transitions exactly as the reader sees the lineage folder (validates graph.json).
    base = load_scene(src)
    S = base.num_states
    grid = _read_grid(src / L.GRID_FILE)
    _check_grid(src, base, grid)
    vis_path, vis, raw = _read_visibility(vis_path, meta_path)
    order, records, visible = _object_table(base, vis_path, vis, meta_path, raw)
    distance = None if raw is None else _distances(base, records)

    stats.states, stats.positions, stats.objects = S, len(grid), len(order)
    stats.distances = distance is not None
    with scene_folder(dst) as tmp:
        image_size, carried = _carried_files(src, base, raw, stats)
        _import_detections(src, tmp, base, cfg.detection_image_size, image_size, stats)
        if cfg.copy_mode != "none":
            for name in carried:
                _place(src / name, tmp / name, cfg.copy_mode)
        for name in (L.GRAPH_FILE, L.GRID_FILE):
            shutil.copy2(src / name, tmp / name)
        if vis_path is not None and vis_path.name == L.VISIBLE_MAP_FILE and all(vis.values()):
            shutil.copy2(vis_path, tmp / L.VISIBLE_MAP_FILE)
        else:  # SAVN's map under its new name, the raw metadata's visible flags, or a map listing unseen objects
            if vis is not None:
                vmap = {oid: keys for oid, keys in vis.items() if keys}
            else:
                vmap = L.visible_object_map(order, base.keys, visible)
            write_json(tmp / L.VISIBLE_MAP_FILE, vmap)
        if distance is not None:
            O = len(order)
            write_states(
                tmp,
                base.keys,
                order,
                np.full((S, O), -1, np.int32),
                np.full((S, O, 4), -1, np.int16),
                distance,
                image_size=image_size,
            )
        write_json(
            tmp / "scene.json",
            _scene_meta(
                src, dst, grid, records, image_size, S, raw is not None, distance is not None, carried, cfg, stats
            ),
        )
        check = load_scene(tmp)  # the result must read back as a tsnav scene
        if check.num_states != S or not check.floor:
            raise SceneFormatError(f"{dst}: imported scene does not read back")
    stats.image_size = image_size
    stats.files = sorted(p.name for p in dst.iterdir())
    return stats


def _sources(src: Path) -> tuple[Path | None, Path | None]:
    """The scene's visibility map (the lineage's or SAVN's name) and ``metadata.json``, each None when absent;
    :class:`SceneFormatError` when ``graph.json`` or ``grid.json`` is missing or neither of the two is there."""
    for name in (L.GRAPH_FILE, L.GRID_FILE):
        if not (src / name).exists():
            raise SceneFormatError(f"{src / name}: missing file")
    vis_path = next((src / n for n in (L.VISIBLE_MAP_FILE, L.VISIBLE_MAP_FILE_SAVN) if (src / n).exists()), None)
    meta_path = src / L.METADATA_FILE if (src / L.METADATA_FILE).exists() else None
    if vis_path is None and meta_path is None:
        raise SceneFormatError(f"{src}: no {L.VISIBLE_MAP_FILE}, {L.VISIBLE_MAP_FILE_SAVN} or {L.METADATA_FILE}")
    return vis_path, meta_path


def _check_grid(src: Path, base, grid: np.ndarray) -> None:
    """:class:`SceneFormatError` when the position of a state of ``graph.json`` is not in ``grid.json``."""

    def codes(x, z):  # integer centimetres -> one int64 per position
        return np.round(np.asarray(x, np.float64) * 100).astype(np.int64) * 1_000_003 + np.round(
            np.asarray(z, np.float64) * 100
        ).astype(np.int64)

    off = ~np.isin(codes(base.x, base.z), codes(grid[:, 0], grid[:, 2]))
    if off.any():
        i = int(np.flatnonzero(off)[0])
        raise SceneFormatError(f"{src / L.GRID_FILE}: position of state {base.keys[i]} (graph.json) is not in the grid")


def _read_visibility(vis_path: Path | None, meta_path: Path | None) -> tuple[Path | None, dict | None, dict | None]:
    """``(path, visibility map, raw metadata)``: the map (objectId -> state keys) and the lineage's raw per-state
    metadata, each None when the scene has none. A ``metadata.json`` that is not raw metadata is SAVN's
    swapped-in visibility map, used when there is no other."""
    vis = None
    if vis_path is not None:
        vis = _check_visible_map(vis_path, _load_json(vis_path))
    raw = None
    if meta_path is not None:
        m = _load_json(meta_path)
        if _is_raw_metadata(m):
            raw = m
        elif vis is None:
            vis_path, vis = meta_path, _check_visible_map(meta_path, m)  # SAVN's swapped-in visibility map
    return vis_path, vis, raw


def _object_table(
    base, vis_path: Path | None, vis: dict | None, meta_path: Path | None, raw: dict | None
) -> tuple[list[str], list[dict], np.ndarray]:
    """Object ids (metadata objects, then visibility-map ids not in the metadata), their ``scene.json`` records
    and the ``(S, O)`` visible flags (from the map, else from the raw metadata's ``visible``)."""
    meta_objects, mrows, moids = {}, [], []
    if raw is not None:
        meta_objects, mrows, moids = _objects_from_metadata(meta_path, raw, base)
    order = sorted(meta_objects)
    if vis is not None:
        seen = set(order)
        order += sorted(k for k in vis if k not in seen)
    records = [_object_record(oid, meta_objects.get(oid)) for oid in order]
    col = {oid: j for j, oid in enumerate(order)}
    visible = np.zeros((base.num_states, len(order)), dtype=bool)
    if vis is not None:
        for oid, keys in vis.items():
            if keys:
                visible[_state_ids(base, keys, f"{vis_path} (object {oid})"), col[oid]] = True
    elif raw is not None and mrows:
        visible[np.asarray(mrows), np.array([col[o] for o in moids])] = True
    return order, records, visible


def _distances(base, records: list[dict]) -> np.ndarray:
    """``(S, O)`` floor-plane distances (m) from each state's position to each object's box footprint (NaN for an
    object without a box)."""
    S, O = base.num_states, len(records)
    pos = np.stack([base.x, base.z], 1).astype(np.float64)
    has = np.array([("bbox" in r) for r in records], dtype=bool)
    distance = np.full((S, O), np.nan, dtype=np.float32)
    if has.any():
        b = [records[j]["bbox"] for j in np.flatnonzero(has)]
        distance[:, has] = box_distance(
            pos,
            np.array([x["center"] for x in b], np.float64),
            np.array([x["size"] for x in b], np.float64),
            np.zeros(len(b)),
        )
    return distance


def _carried_files(src: Path, base, raw: dict | None, stats: ImportStats) -> tuple[int, list[str]]:
    """The frame size of the lineage's images (0 without) and the names of its files to carry over; the images
    and depth files are checked against the states (warnings go to ``stats``)."""
    image_size = 0
    carried = []
    for name, channels in ((L.IMAGES_FILE, True), (L.DEPTH_FILE, False)):
        if (src / name).exists():
            size, warn = _check_images(src / name, base, name, channels)
            image_size = image_size or size
            stats.warnings += warn
            carried.append(name)
    for name in L.EXTRA_FILES + L.DETECTION_FILES:
        if (src / name).exists():
            carried.append(name)
    if raw is not None:
        carried.append(L.METADATA_FILE)
    return image_size, carried


def _import_detections(
    src: Path, tmp: Path, base, detection_image_size: int, image_size: int, stats: ImportStats
) -> None:
    """The lineage's 22 x 264 detection table (when the scene has one) as ``detections_lineage.hdf5``."""
    det_path = next((src / n for n in L.DETECTION_FILES if (src / n).exists()), None)
    if det_path is None:
        return
    S = base.num_states
    try:
        with h5py.File(det_path, "r") as f:
            det_keys = sorted(f.keys())
    except OSError as e:
        raise SceneFormatError(f"{det_path}: unreadable HDF5 ({_one_line(e)})") from None
    _state_ids(base, det_keys, str(det_path))
    det = L.read_detections_22x264(det_path, image_size=detection_image_size, keys=base.keys)
    write_detections(tmp, L.DETECTIONS_LINEAGE_NAME, det)
    if len(det_keys) < S:
        stats.warnings.append(f"{det_path.name}: no detections for {S - len(det_keys)} of {S} states")
    stats.detections = True


def _scene_meta(
    src: Path,
    dst: Path,
    grid: np.ndarray,
    records: list[dict],
    image_size: int,
    S: int,
    has_metadata: bool,
    has_distances: bool,
    carried: list[str],
    cfg: ImportConfig,
    stats: ImportStats,
) -> dict:
    """``scene.json`` of the imported scene: floor from the grid, objects, where it came from, what was derived."""
    floor = L.derive_floor(grid[:, [0, 2]], GRID_SIZE)
    room_type, split = lineage_scene_info(dst.name)
    return {
        "format": "tsnav-scene",
        "version": 1,
        "name": dst.name,
        "room_type": room_type,
        "split": split,
        "rooms": [],
        "floor": [p.tolist() for p in floor],
        "furniture": [],
        "objects": records,
        "image_size": image_size,
        "num_states": S,
        "num_positions": int(len(grid)),
        "visibility": {
            "distance": VISIBILITY_DISTANCE,
            "rule": "AI2-THOR's visible flag (in view, within 1.5 m) from the lineage's data",
        },
        "source": {
            "format": "ai2thor-offline-data",
            "path": str(src.resolve()),
            "files": sorted(carried),
            "config": asdict(cfg),
        },
        "derived": {
            "floor": "union of 0.25 m squares centred on grid.json positions, holes filled",
            "objects": "visible_object_map ids (Type|x|y|z)" + (" and metadata.json objects" if has_metadata else ""),
            "distance": (
                "floor plane, state position to the footprint of the object's axis-aligned box"
                if has_distances
                else "unknown: success uses the visibility map alone"
            ),
            "detections": L.DETECTIONS_LINEAGE_FILE if stats.detections else None,
        },
        "warnings": stats.warnings,
    }


def find_lineage_scenes(src: str | Path) -> list[Path]:
    """``src`` itself when it is a scene folder (holds ``graph.json``), else its sub-folders that are."""
    src = Path(src)
    if not src.is_dir():
        raise SceneFormatError(f"{src}: no such folder")
    if (src / L.GRAPH_FILE).exists():
        return [src]
    found = sorted(
        p for p in src.iterdir() if p.is_dir() and not p.name.startswith(".") and (p / L.GRAPH_FILE).exists()
    )
    if not found:
        raise SceneFormatError(f"{src}: no scene folder (a folder holding {L.GRAPH_FILE}) here or one level down")
    return found


def import_lineage_dataset(
    src: str | Path, dst_root: str | Path, config: ImportConfig | None = None, progress=None
) -> list[ImportStats]:
    """Import every scene folder of ``src`` (or ``src`` itself) into ``dst_root/<scene name>``."""
    dst_root = Path(dst_root)
    dst_root.mkdir(parents=True, exist_ok=True)
    out = []
    for p in find_lineage_scenes(src):
        st = import_lineage_scene(p, dst_root / p.name, config)
        out.append(st)
        if progress is not None:
            progress(st)
    return out
