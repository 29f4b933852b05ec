"""Build offline datasets: generate, lay out the state graph, render every state, write scene folders.

A scene is written into a hidden temporary folder next to its final place and renamed when complete, so
an interrupted build never leaves a half-written scene that looks complete; running the build again skips
finished scenes and redoes the rest. Files follow the lineage layout (DESIGN.md "The offline dataset").
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..constants import HORIZONS, ROTATIONS, VISIBILITY_DISTANCE, state_key
from ..world.navgrid import build_graph, reachable_positions
from ..world.presets import scene_spec
from ..world.spec import SceneSpec
from .reader import COMPLETE_MARKER

#: Minimum share of the frame an object must cover to count as seen (AI2-THOR casts rays; we count pixels).
MIN_PIXEL_FRACTION = 0.001


def min_pixels(image_size: int, fraction: float = MIN_PIXEL_FRACTION) -> int:
    """Pixels an object must show in a ``image_size``-square frame to count as seen (at least 2)."""
    return max(2, int(math.ceil(fraction * image_size ** 2)))


#: Height of the agent's position in ``grid.json`` (AI2-THOR reports the agent's body centre).
GRID_Y = 0.9


@dataclass
class BuildConfig:
    """Settings of one dataset build."""

    image_size: int = 64  #: side of the square frames, pixels
    store_images: bool = True  #: write images.hdf5 and depth.hdf5 (needed for pretraining and features)
    depth_dtype: str = "float16"  #: dtype of depth.hdf5 (metres); float16 keeps datasets small
    compression: str | None = None  #: HDF5 filter for images (None or "gzip"; lzf output is not byte-reproducible)
    compact: bool = False  #: small rooms (the `tiny` preset)
    world: str = "procedural"  #: layout source: "procedural" or "ithor-real" (tsnav.world.presets.WORLDS)
    seed: int = 0  #: world seed; the same name and seed give the same scene
    tiles: int = 16  #: views rendered per framebuffer read

    def min_pixels(self) -> int:
        return min_pixels(self.image_size)


@dataclass
class SceneStats:
    name: str
    states: int = 0
    positions: int = 0
    objects: int = 0
    render_s: float = 0.0
    write_s: float = 0.0
    other_s: float = 0.0
    skipped: bool = False
    extra: dict = field(default_factory=dict)


def box_distance(points: np.ndarray, centers: np.ndarray, sizes: np.ndarray, yaws: np.ndarray) -> np.ndarray:
    """Horizontal distance (P, O), metres, from agent positions (P, 2: x, z) to oriented box footprints.

    The paper's success rule ("the agent is within 1 meter of the target object", III-A) is measured on the
    floor plane from the agent's position to the nearest point of the object's footprint, so that objects on
    the floor and on a table are judged alike (a 3-D distance from a camera 1.5 m up would put every object
    lower than about 0.5 m out of reach). Boxes: base centre (x, y, z), size (x, y, z), yaw in degrees.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.shape[-1] == 3:  # accept (x, y, z) rows; y is ignored
        points = points[:, [0, 2]]
    c = np.cos(np.deg2rad(yaws))[None, :]
    s = np.sin(np.deg2rad(yaws))[None, :]
    dx = points[:, None, 0] - centers[None, :, 0]
    dz = points[:, None, 1] - centers[None, :, 2]
    # world -> local: inverse of (x = c lx + s lz, z = -s lx + c lz)
    lx = c * dx - s * dz
    lz = s * dx + c * dz
    ex = np.maximum(np.abs(lx) - sizes[None, :, 0] / 2, 0)
    ez = np.maximum(np.abs(lz) - sizes[None, :, 2] / 2, 0)
    return np.sqrt(ex ** 2 + ez ** 2)


def object_stats(ids: np.ndarray, lut: np.ndarray, num_objects: int):
    """Per view and object: visible pixel count (V, O) and pixel box (V, O, 4) ``[x0, y0, x1, y1]`` (-1 if none).

    ``ids`` (V, H, W) instance ids; ``lut`` maps an instance id to an object column (-1 for non-objects).
    """
    V = ids.shape[0]
    col = lut[ids]
    v, y, x = np.nonzero(col >= 0)
    key = v * num_objects + col[v, y, x]
    pixels = np.bincount(key, minlength=V * num_objects).reshape(V, num_objects).astype(np.int32)
    big = np.iinfo(np.int32).max
    x0 = np.full(V * num_objects, big, np.int64)
    y0 = np.full(V * num_objects, big, np.int64)
    x1 = np.full(V * num_objects, -1, np.int64)
    y1 = np.full(V * num_objects, -1, np.int64)
    np.minimum.at(x0, key, x)
    np.minimum.at(y0, key, y)
    np.maximum.at(x1, key, x)
    np.maximum.at(y1, key, y)
    boxes = np.stack([x0, y0, x1, y1], axis=1).reshape(V, num_objects, 4)
    boxes[pixels == 0] = -1
    return pixels, boxes.astype(np.int16)


def object_stats_reference(ids: np.ndarray, lut: np.ndarray, num_objects: int):
    """Slow reference for :func:`object_stats`: loops over views and objects with boolean masks."""
    V = ids.shape[0]
    pixels = np.zeros((V, num_objects), np.int32)
    boxes = np.full((V, num_objects, 4), -1, np.int16)
    for v in range(V):
        for inst in np.unique(ids[v]):
            o = lut[inst]
            if o < 0:
                continue
            ys, xs = np.nonzero(ids[v] == inst)
            pixels[v, o] += len(xs)
            b = boxes[v, o]
            if b[0] < 0:
                boxes[v, o] = [xs.min(), ys.min(), xs.max(), ys.max()]
            else:
                boxes[v, o] = [min(b[0], xs.min()), min(b[1], ys.min()), max(b[2], xs.max()), max(b[3], ys.max())]
    return pixels, boxes


def _write_json(path: Path, obj) -> None:
    with open(path, "w") as f:
        json.dump(obj, f, separators=(",", ":"), sort_keys=False)


def build_scene(name: str, out_dir: str | Path, cfg: BuildConfig, renderer=None) -> SceneStats:
    """Generate, render and write scene ``name`` into ``out_dir/name`` (skipped when already complete)."""
    out_dir = Path(out_dir)
    final = out_dir / name
    stats = SceneStats(name)
    if (final / COMPLETE_MARKER).exists():
        stats.skipped = True
        return stats
    t0 = time.perf_counter()
    spec: SceneSpec = scene_spec(name, cfg.world, seed=cfg.seed, compact=cfg.compact)
    positions, move = reachable_positions(spec)
    nodes, edges = build_graph(positions, move)
    js = spec.to_json()
    objects = spec.objects
    O = len(objects)
    lut = np.full(len(spec.instances), -1, np.int64)
    for j, o in enumerate(objects):
        lut[o.inst] = j
    # Render order: position, rotation, horizon; the tables are stored in sorted key order.
    poses = np.array([(x, z, r, h) for x, z in positions for r in ROTATIONS for h in HORIZONS], dtype=np.float64)
    keys = np.array([state_key(*p) for p in poses])
    order = np.argsort(keys, kind="stable")
    stats.other_s += time.perf_counter() - t0

    own = renderer is None
    if own:
        from ..render.gl import Renderer

        renderer = Renderer(cfg.image_size, cfg.tiles)
    renderer.set_scene(np.array(js["parts"], dtype=np.float32), js["light"])
    tmp = out_dir / f".{name}.partial-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    import h5py

    V = len(poses)
    pixels = np.zeros((V, O), np.int32)
    boxes = np.full((V, O, 4), -1, np.int16)
    img_f = dep_f = None
    try:
        if cfg.store_images:
            img_f = h5py.File(tmp / "images.hdf5", "w", track_order=False)
            dep_f = h5py.File(tmp / "depth.hdf5", "w", track_order=False)
        chunk = renderer.tiles * 4
        for start in range(0, V, chunk):
            t1 = time.perf_counter()
            rgb, depth, ids = renderer.render(poses[start:start + chunk])
            px, bx = object_stats(ids, lut, O) if O else (np.zeros((len(ids), 0), np.int32), np.zeros((len(ids), 0, 4), np.int16))
            pixels[start:start + len(ids)] = px
            boxes[start:start + len(ids)] = bx
            t2 = time.perf_counter()
            stats.render_s += t2 - t1
            if cfg.store_images:
                dd = depth.astype(cfg.depth_dtype)
                for i in range(len(ids)):
                    k = keys[start + i]
                    img_f.create_dataset(k, data=rgb[i], compression=cfg.compression, track_times=False)
                    dep_f.create_dataset(k, data=dd[i], track_times=False)
            stats.write_s += time.perf_counter() - t2
        t3 = time.perf_counter()
        if img_f is not None:
            img_f.close()
            dep_f.close()
            img_f = dep_f = None
        # Distances: agent position to the nearest point of each object's footprint (floor plane); per position.
        if O:
            dist_pos = box_distance(positions, np.array([o.center for o in objects]), np.array([o.size for o in objects]),
                                    np.array([o.yaw for o in objects]))
        else:
            dist_pos = np.zeros((len(positions), 0))
        per_pos = len(ROTATIONS) * len(HORIZONS)
        distance = np.repeat(dist_pos, per_pos, axis=0).astype(np.float32)
        keys_s, pixels_s, boxes_s, distance_s = keys[order], pixels[order], boxes[order], distance[order]
        min_px = cfg.min_pixels()
        vis = (pixels_s >= min_px) & (distance_s <= VISIBILITY_DISTANCE)
        vis_map = {o.objectId: keys_s[vis[:, j]].tolist() for j, o in enumerate(objects)}
        _write_json(tmp / "visible_object_map_1.5.json", vis_map)
        _write_json(tmp / "grid.json", [{"x": float(x), "y": GRID_Y, "z": float(z)} for x, z in positions])
        _write_json(tmp / "graph.json", {"directed": True, "multigraph": False, "graph": {},
                                         "nodes": [{"id": k} for k in sorted(nodes)],
                                         "links": [{"source": a, "target": b} for a, b in edges]})
        with h5py.File(tmp / "states.hdf5", "w") as f:
            f.create_dataset("keys", data=keys_s.astype("S"), track_times=False)
            f.create_dataset("object_ids", data=np.array([o.objectId for o in objects], dtype="S"), track_times=False)
            f.create_dataset("pixels", data=pixels_s, track_times=False)
            f.create_dataset("boxes", data=boxes_s, track_times=False)
            f.create_dataset("distance", data=distance_s, track_times=False)
            f.attrs["image_size"] = cfg.image_size
            f.attrs["min_pixels"] = min_px
        js.update({"image_size": cfg.image_size, "compact": cfg.compact,
                   "visibility": {"min_pixels": min_px, "min_pixel_fraction": MIN_PIXEL_FRACTION,
                                  "distance": VISIBILITY_DISTANCE},
                   "num_states": len(keys), "num_positions": len(positions)})
        _write_json(tmp / "scene.json", js)
        (tmp / COMPLETE_MARKER).write_text("ok\n")
        if final.exists():  # an old incomplete folder (e.g. from another tool); replace it
            shutil.rmtree(final)
        os.replace(tmp, final)
        stats.write_s += time.perf_counter() - t3
    except BaseException:
        for f in (img_f, dep_f):
            if f is not None:
                try:
                    f.close()
                except Exception:
                    pass
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if own:
            renderer.release()
    stats.states, stats.positions, stats.objects = len(keys), len(positions), O
    return stats


def write_index(out_dir: Path, preset: str, names: list[str], cfg: BuildConfig) -> None:
    tmp = out_dir / ".index.json.tmp"
    _write_json(tmp, {"format": "tsnav-dataset", "preset": preset, "scenes": names, "config": asdict(cfg)})
    os.replace(tmp, out_dir / "index.json")
