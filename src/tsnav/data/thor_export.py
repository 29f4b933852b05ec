"""Export tsnav scenes to the lineage's layout, and check a folder against what the lineage's readers expect.

tsnav scene folders already hold the lineage's files (``graph.json``, ``grid.json``,
``visible_object_map_1.5.json``, ``images.hdf5``); of what the lineage's agents additionally read, the
22 x 264 DETR table is written here from a tsnav detection table (:mod:`tsnav.data.detections`); the rest
(ResNet features, optimal actions, episode lists) by ``tsnav thor export-lineage``
(:mod:`tsnav.thor.lineage_export`). :func:`check_lineage_layout` lists every way a scene folder departs from
the layout of :mod:`tsnav.data.lineage` (key formats, JSON shapes, HDF5 dataset names, shapes, dtypes and
contents), as SAVN's ``OfflineControllerWithSmallRotation`` and the VTNet / DOA / IOM readers would meet it;
:func:`check_lineage_dataset` does so for every scene of a dataset and its episode lists.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from ..constants import HORIZONS, NUM_ACTIONS, ROTATIONS, TARGET_CATEGORIES, parse_state_keys
from . import lineage as L
from . import lineage_splits as LS
from .detections import Detections
from .reader import SceneFormatError, edge_actions, list_scenes, load_scene


#: At most this many problems are reported per check (a broken file would otherwise list every state).
MAX_REPORTED = 5


def _json(path: Path, problems: list[str]):
    if not path.exists():
        problems.append(f"{path.name}: missing file")
        return None
    try:
        with open(path) as f:
            return json.load(f)
    except json.JSONDecodeError as e:
        problems.append(f"{path.name}: not valid JSON ({e.msg} at line {e.lineno})")
    return None


def _bad_keys(keys: list[str]) -> list[str]:
    """Keys that are not ``x|z|rotation|horizon`` with 2 decimals and a rotation / horizon of the lineage."""
    out = []
    rot_ok, hor_ok = {str(r) for r in ROTATIONS}, {str(h) for h in HORIZONS}
    for k in keys:
        if not isinstance(k, str) or not L.KEY_PATTERN.match(k):
            out.append(k)
            continue
        _, _, r, h = k.split("|")
        if r not in rot_ok or h not in hor_ok:
            out.append(k)
    return out


def _check_graph(d: Path, problems: list[str]) -> list[str] | None:
    g = _json(d / L.GRAPH_FILE, problems)
    if g is None:
        return None
    name = L.GRAPH_FILE
    if not isinstance(g, dict) or not isinstance(g.get("nodes"), list) or not isinstance(g.get("links"), list):
        problems.append(f"{name}: expected networkx node_link_data with 'nodes' and 'links' lists")
        return None
    if g.get("directed") is not True:
        problems.append(f"{name}: 'directed' must be true (a DiGraph)")
    if g.get("multigraph", False):
        problems.append(f"{name}: 'multigraph' must be false")
    try:
        nodes = [n["id"] for n in g["nodes"]]
        links = [(e["source"], e["target"]) for e in g["links"]]
    except (TypeError, KeyError):
        problems.append(f"{name}: nodes need 'id', links need 'source' and 'target'")
        return None
    bad = _bad_keys(nodes)
    for k in bad[:MAX_REPORTED]:
        problems.append(f"{name}: node {k!r} is not a state key 'x.xx|z.zz|rotation|horizon' of the lineage")
    if len(set(nodes)) != len(nodes):
        problems.append(f"{name}: duplicate nodes")
    node_set = set(nodes)
    off = [(a, b) for a, b in links if a not in node_set or b not in node_set]
    for a, b in off[:MAX_REPORTED]:
        problems.append(f"{name}: link {a!r} -> {b!r} joins a key that is not a node")
    ok = [
        (a, b)
        for a, b in links
        if a in node_set
        and b in node_set
        and isinstance(a, str)
        and isinstance(b, str)
        and L.KEY_PATTERN.match(a)
        and L.KEY_PATTERN.match(b)
    ]
    if ok:
        x0, z0, r0, h0 = parse_state_keys([a for a, _ in ok])
        x1, z1, r1, h1 = parse_state_keys([b for _, b in ok])
        act = edge_actions(x0, z0, r0, h0, x1, z1, r1, h1)
        for j in np.flatnonzero(act < 0)[:MAX_REPORTED]:
            problems.append(f"{name}: link {ok[j][0]} -> {ok[j][1]} is not a single action")
    return nodes


def check_lineage_layout(scene_dir: str | Path, complete: bool = False, image_size: int | None = None) -> list[str]:
    """Problems that keep ``scene_dir`` from being read by the lineage's code (empty list: none found).

    Checks ``graph.json`` (node-link JSON of a directed graph; keys ``x.xx|z.zz|rotation|horizon`` with
    rotations 0..315 by 45 and horizons 0 / 30; every link one action between nodes), ``grid.json`` (list of
    ``{"x","y","z"}`` numbers; every state position in it), ``visible_object_map_1.5.json`` (objectId
    ``Type|x|y|z`` -> a non-empty list of state keys of the graph), and the other files when present:
    ``images.hdf5`` (a ``uint8 (H, W, 3)`` dataset for every state, nothing else; ``H = W = image_size``
    when given), ``depth.hdf5`` (float ``(H, W)``), ``resnet18_featuremap.hdf5`` (float32 ``(1, 512, 7, 7)``),
    the 22 x 264 detection tables (float32 ``(22, 264)``; labels 1..23, never 0, which IOM's reader files
    under the last class; boxes inside the 300 px frame), ``optimal_action.json`` (state key -> target
    type -> action id 0..5). ``complete``: also require every file the lineage's trainer and evaluator read
    (images, ResNet features, a detection table, optimal actions).
    """
    d = Path(scene_dir)
    if not d.is_dir():
        return [f"{d}: not a folder"]
    required = (L.IMAGES_FILE, L.RESNET_FILE, L.OPTIMAL_ACTION_FILE) if complete else ()
    absent = [
        f"{name}: missing file (the lineage's code reads it; `tsnav thor export-lineage` writes it)"
        for name in required
        if not (d / name).exists()
    ]
    problems: list[str] = []
    nodes = _check_graph(d, problems)
    node_set = set(nodes or [])

    grid = _json(d / L.GRID_FILE, problems)
    if grid is not None:
        if (
            not isinstance(grid, list)
            or not grid
            or not all(
                isinstance(p, dict)
                and all(isinstance(p.get(a), (int, float)) and not isinstance(p.get(a), bool) for a in "xyz")
                for p in grid
            )
        ):
            problems.append(f'{L.GRID_FILE}: expected a non-empty list of {{"x", "y", "z"}} numbers')
        elif nodes:
            have = {(round(p["x"] * 100), round(p["z"] * 100)) for p in grid}  # centimetres: -0.00 == 0.00
            pos = {tuple(k.split("|")[:2]) for k in nodes if L.KEY_PATTERN.match(str(k))}
            missing = sorted(p for p in pos if (round(float(p[0]) * 100), round(float(p[1]) * 100)) not in have)
            for x, z in missing[:MAX_REPORTED]:
                problems.append(f"{L.GRID_FILE}: state position ({x}, {z}) of graph.json is missing")

    vis = _json(d / L.VISIBLE_MAP_FILE, problems)
    if vis is not None:
        if not isinstance(vis, dict) or not all(isinstance(v, list) for v in vis.values()):
            problems.append(f"{L.VISIBLE_MAP_FILE}: expected {{objectId: [state key, ...]}}")
        else:
            n = 0
            for oid, keys in vis.items():
                if L.parse_object_id(oid)[1] is None and n < MAX_REPORTED:
                    problems.append(f"{L.VISIBLE_MAP_FILE}: object id {oid!r} is not 'Type|x|y|z'")
                    n += 1
                if not keys and n < MAX_REPORTED:
                    problems.append(
                        f"{L.VISIBLE_MAP_FILE}: object {oid} is listed with no state (the lineage's maps "
                        f"never list one; IOM's planner finds no path to it)"
                    )
                    n += 1
                for k in keys:
                    if k not in node_set and nodes is not None and n < MAX_REPORTED:
                        problems.append(f"{L.VISIBLE_MAP_FILE}: state {k!r} of {oid} is not a node of graph.json")
                        n += 1
                        break

    _check_h5(d / L.IMAGES_FILE, nodes, problems, kind="image", required_all=True, size=image_size)
    _check_h5(d / L.DEPTH_FILE, nodes, problems, kind="depth")
    _check_h5(d / L.RESNET_FILE, nodes, problems, kind="resnet", required_all=True)
    for name in L.DETECTION_FILES:
        _check_h5(d / name, nodes, problems, kind="detection", required_all=True)
        _check_detection_rows(d / name, problems)
    _check_optimal_actions(d / L.OPTIMAL_ACTION_FILE, nodes, problems)
    if complete and not any((d / n).exists() for n in L.DETECTION_FILES):
        absent.append(
            f"{L.DETECTION_FILES[0]}: missing file (the lineage's agents read the 22 x 264 DETR table; "
            f"`tsnav thor export-lineage --detections NAME` writes it)"
        )
    return absent + problems


def _check_detection_rows(path: Path, problems: list[str]) -> None:
    """Content of a 22 x 264 table: labels integers 1..23 (0 is filed under the last class by the lineage's
    ``table[label - 1]`` readers), boxes of every row inside the 300 px frame (no -1 markers)."""
    if not path.exists():
        return
    name, n = path.name, 0
    try:
        with h5py.File(path, "r") as f:
            for k in f.keys():
                ds = f[k]
                if (
                    n >= MAX_REPORTED
                    or not isinstance(ds, h5py.Dataset)
                    or ds.ndim != 2
                    or ds.shape[1] != L.TABLE_WIDTH
                ):
                    continue
                r = ds[()]
                lab = r[:, L.LABEL_COL]
                box = r[:, L.BOX_COLS]
                if (lab != np.round(lab)).any() or (lab < 0).any() or (lab > L.NO_OBJECT_LABEL).any():
                    problems.append(f"{name}: {k!r} has labels outside 0..{L.NO_OBJECT_LABEL}")
                    n += 1
                elif (lab == L.EMPTY_LABEL).any():
                    problems.append(
                        f"{name}: {k!r} has rows labelled 0; the lineage's readers file them under the "
                        f"last class (label rows without a detection {L.NO_OBJECT_LABEL})"
                    )
                    n += 1
                elif (box < 0).any() or (box > L.LINEAGE_IMAGE_SIZE).any():
                    problems.append(
                        f"{name}: {k!r} has boxes outside the {L.LINEAGE_IMAGE_SIZE} px frame "
                        f"(min {box.min():g}, max {box.max():g})"
                    )
                    n += 1
    except OSError:
        pass  # reported by _check_h5


def _check_optimal_actions(path: Path, nodes, problems: list[str]) -> None:
    """``optimal_action.json``: {state key of the graph: {target type of the 22: action id 0..5}}."""
    if not path.exists():
        return
    name = path.name
    doc = _json(path, problems)
    if doc is None:
        return
    if not isinstance(doc, dict) or not all(isinstance(v, dict) for v in doc.values()):
        problems.append(f"{name}: expected {{state key: {{target type: action id}}}}")
        return
    node_set = set(nodes or [])
    n = 0
    for k, targets in doc.items():
        if n >= MAX_REPORTED:
            break
        if nodes is not None and k not in node_set:
            problems.append(f"{name}: {k!r} is not a state of graph.json")
            n += 1
            continue
        for t, a in targets.items():
            if t not in TARGET_CATEGORIES or isinstance(a, bool) or not isinstance(a, int) or not 0 <= a < NUM_ACTIONS:
                problems.append(
                    f"{name}: {k!r} -> {t!r}: {a!r} is not an action id 0..{NUM_ACTIONS - 1} of a target type"
                )
                n += 1
                break
    if nodes is not None and n < MAX_REPORTED:
        missing = len(node_set - set(doc))
        if missing:
            problems.append(f"{name}: no entry for {missing} of {len(node_set)} states")


def check_lineage_dataset(
    root: str | Path, complete: bool = False, image_size: int | None = None
) -> dict[str, list[str]]:
    """:func:`check_lineage_layout` of every scene folder of ``root`` (key: scene name) and of the episode lists
    (key ``test_val_split``; :func:`check_lineage_splits`). ``complete``: the lists must be there too."""
    root = Path(root)
    out = {}
    dirs = sorted(p for p in root.iterdir() if p.is_dir() and (p / L.GRAPH_FILE).exists()) if root.is_dir() else []
    if not dirs:
        dirs = list_scenes(root) if root.is_dir() else []
    for d in dirs:
        out[d.name] = check_lineage_layout(d, complete, image_size)
    out[L.SPLIT_DIR] = check_lineage_splits(root, dirs, required=complete)
    return out


def check_lineage_splits(root: str | Path, scene_dirs, required: bool = False) -> list[str]:
    """Problems of ``root/test_val_split/*.pkl`` as the lineage's evaluator reads them: each file a list of
    episode dicts (read with the restricted unpickler) whose scene is a folder of ``root``, state a state of
    it, goal type one of the 22, task_data object ids of the scene's visibility map of that type, and
    glove_embedding a float ``(60, 1)`` one-hot array."""
    folder = Path(root) / L.SPLIT_DIR
    files = sorted(folder.glob("*_22.pkl")) if folder.is_dir() else []
    if not files:
        return (
            [f"{L.SPLIT_DIR}: no episode lists {{room}}_{{test,val}}_22.pkl (`tsnav thor export-lineage` writes them)"]
            if required
            else []
        )
    problems: list[str] = []
    scenes = {LS.scene_base_name(Path(d).name): Path(d) for d in scene_dirs}
    graphs: dict[str, set] = {}
    vismaps: dict[str, dict] = {}
    for p in files:
        try:
            records = LS.read_split(p)
        except LS.SplitFormatError as e:
            problems.append(f"{L.SPLIT_DIR}/{p.name}: {str(e).split(': ', 1)[-1]}")
            continue
        n = 0
        for i, r in enumerate(records):
            if n >= MAX_REPORTED:
                break
            why = None
            name = LS.scene_base_name(r["scene"])
            if name not in scenes:
                why = f"scene {r['scene']} is not a folder of {root}"
            else:
                if name not in graphs:
                    g = _json(scenes[name] / L.GRAPH_FILE, []) or {}
                    graphs[name] = {x.get("id") for x in g.get("nodes", []) if isinstance(x, dict)}
                    vismaps[name] = _json(scenes[name] / L.VISIBLE_MAP_FILE, []) or {}
                glove = r.get("glove_embedding")
                if r["state"] not in graphs[name]:
                    why = f"state {r['state']} is not a state of {r['scene']}"
                elif r["goal_object_type"] not in TARGET_CATEGORIES:
                    why = f"goal_object_type {r['goal_object_type']!r} is not one of the 22 targets"
                elif not r["task_data"] or any(
                    t not in vismaps[name] or t.split("|")[0] != r["goal_object_type"] for t in r["task_data"]
                ):
                    why = "task_data does not list object ids of the target in the scene's visibility map"
                elif not isinstance(glove, np.ndarray) or glove.shape != LS.GLOVE_SHAPE or glove.dtype.kind != "f":
                    why = f"glove_embedding is not a float array of shape {LS.GLOVE_SHAPE}"
                elif glove.sum() != 1 or (glove.max() != 1):
                    why = "glove_embedding is not one-hot"
            if why:
                problems.append(f"{L.SPLIT_DIR}/{p.name}: episode {i}: {why}")
                n += 1
    return problems


def _check_h5(
    path: Path, nodes, problems: list[str], kind: str, required_all: bool = False, size: int | None = None
) -> None:
    if not path.exists():
        return
    name = path.name
    try:
        with h5py.File(path, "r") as f:
            keys = list(f.keys())
            node_set = set(nodes or [])
            extra = [k for k in keys if nodes is not None and k not in node_set]
            for k in extra[:MAX_REPORTED]:
                problems.append(f"{name}: dataset {k!r} is not a state of graph.json")
            if required_all and nodes is not None:
                missing = len(node_set - set(keys))
                if missing:
                    problems.append(f"{name}: no dataset for {missing} of {len(node_set)} states")
            n = 0
            shapes = set()
            for k in keys:
                if n >= MAX_REPORTED:
                    break
                ds = f[k]
                if not isinstance(ds, h5py.Dataset):
                    problems.append(f"{name}: {k!r} is a group, expected a dataset")
                    n += 1
                    continue
                why = _dataset_problem(ds, kind)
                if not why and size is not None and kind == "image" and ds.shape[:2] != (size, size):
                    why = f"is {ds.shape[0]} x {ds.shape[1]}, expected {size} x {size} (build the world with --size {size})"
                if why:
                    problems.append(f"{name}: {k!r} {why}")
                    n += 1
                shapes.add(ds.shape)
            if len(shapes) > 1:
                problems.append(f"{name}: datasets have different shapes {sorted(shapes)[:3]}")
    except OSError as e:
        problems.append(f"{name}: unreadable HDF5 ({' '.join(str(e).split())})")


def _dataset_problem(ds, kind: str) -> str | None:
    dt, sh = ds.dtype, ds.shape
    if kind == "image" and (dt != np.uint8 or len(sh) != 3 or sh[2] != 3):
        return f"holds {dt} {sh}, expected uint8 (H, W, 3)"
    if kind == "depth" and (dt.kind != "f" or len(sh) != 2):
        return f"holds {dt} {sh}, expected float (H, W) metres"
    if kind == "resnet" and (dt != np.float32 or tuple(sh) != L.RESNET_SHAPE):
        return f"holds {dt} {sh}, expected float32 {L.RESNET_SHAPE}"
    if kind == "detection" and (dt != np.float32 or len(sh) != 2 or sh[1] != L.TABLE_WIDTH):
        return f"holds {dt} {sh}, expected float32 (22, {L.TABLE_WIDTH})"
    return None


def export_detections_22x264(
    scene_dir: str | Path,
    detections_file: str | Path,
    out_path: str | Path | None = None,
    box_size: int | None = L.LINEAGE_IMAGE_SIZE,
) -> Path:
    """Write the lineage's 22 x 264 table (float32 per state key) from a tsnav detection table.

    ``detections_file``: a ``detections_<name>.hdf5`` of the detect stage (a path, or a name relative to
    ``scene_dir``); features of up to 256 dimensions (the lineage's DETR feature is 256-d; tsnav's detectors give
    64-d, zero-padded, see :func:`tsnav.data.lineage.table_to_22x264`). ``out_path`` defaults to
    ``scene_dir/detr_features_22cls.hdf5``. Boxes are rescaled to ``box_size`` pixels (the lineage's 300 x 300
    frames; None keeps the table's pixels). Every key must be a state of the scene's ``graph.json``.
    Read back with :func:`tsnav.data.lineage.read_detections_22x264`; the round trip is exact for scores,
    labels and features, and for the boxes of kept detections whenever ``box_size / image_size`` is a
    power-of-two fraction (as 300 / 64) or 1.
    """
    scene_dir = Path(scene_dir)
    p = Path(detections_file)
    if not p.is_absolute() and not p.exists():
        p = scene_dir / p
    if not p.exists():
        raise SceneFormatError(f"{p}: missing file")
    try:
        with h5py.File(p, "r") as f:
            det = Detections(
                keys=f["keys"][()].astype(str),
                scores=f["scores"][()],
                labels=f["labels"][()],
                boxes=f["boxes"][()],
                features=f["features"][()],
                image_size=int(f.attrs.get("image_size", 0)),
            )
    except (OSError, KeyError) as e:
        raise SceneFormatError(f"{p}: not a readable detection table ({' '.join(str(e).split())})") from None
    except ValueError as e:
        raise SceneFormatError(f"{p}: {e}") from None
    if box_size is not None and det.image_size <= 0:
        raise SceneFormatError(f"{p}: no image_size attribute; cannot rescale boxes to {box_size} px")
    scene = load_scene(scene_dir)
    try:
        scene.indices(det.keys)
    except KeyError as e:
        raise SceneFormatError(f"{p}: {e.args[0]}") from None
    out = Path(out_path) if out_path is not None else scene_dir / L.DETECTION_FILES[0]
    try:
        return L.write_detections_22x264(out, det, box_size)
    except ValueError as e:
        raise SceneFormatError(f"{p}: {e}") from None
