"""The one writer of the scene folder format (DESIGN.md "The offline dataset", the lineage layout).

Every producer of scene folders (the procedural world, the lineage import, the live AI2-THOR export) writes
through this module: :func:`scene_folder` is the atomic commit (a hidden temporary folder next to the final
place, ``COMPLETE`` written last, then renamed, so an interrupted write never leaves a half-written scene
that looks complete), :class:`FrameWriter` writes ``images.hdf5`` / ``depth.hdf5``, :func:`write_states`
the per-state object table ``states.hdf5``, and :func:`write_json` the JSON files (``graph.json``,
``grid.json``, ``visible_object_map_1.5.json``, ``scene.json``) in one compact form. It also holds the
per-view visibility statistics the producers share (:func:`object_stats`, :func:`box_distance`).
"""

from __future__ import annotations

import json
import math
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import h5py
import numpy as np

from ..atomic import atomic_folder
from .reader import COMPLETE_MARKER

#: Minimum share of the frame an object must cover to count as seen (AI2-THOR casts rays; we count pixels).
MIN_PIXEL_FRACTION = 0.001


def min_pixels(image_size: int, fraction: float = MIN_PIXEL_FRACTION) -> int:
    """Pixels an object must show in a ``image_size``-square frame to count as seen (at least 2)."""
    return max(2, int(math.ceil(fraction * image_size**2)))


#: Height of the agent's position in ``grid.json`` (AI2-THOR reports the agent's body centre).
GRID_Y = 0.9


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
    return np.sqrt(ex**2 + ez**2)


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


def write_json(path: str | Path, obj) -> None:
    """Write ``obj`` as compact JSON (the form of every JSON file of a scene folder)."""
    with open(path, "w") as f:
        json.dump(obj, f, separators=(",", ":"), sort_keys=False)


def write_graph(folder: Path, nodes, edges) -> None:
    """``graph.json``: networkx node-link directed graph; ``nodes`` state keys, ``edges`` ``(source, target)``."""
    write_json(
        folder / "graph.json",
        {
            "directed": True,
            "multigraph": False,
            "graph": {},
            "nodes": [{"id": k} for k in nodes],
            "links": [{"source": a, "target": b} for a, b in edges],
        },
    )


def write_states(
    folder: Path,
    keys: np.ndarray,
    object_ids,
    pixels: np.ndarray,
    boxes: np.ndarray,
    distance: np.ndarray,
    image_size: int,
    min_pixels: int | None = None,
    extra: dict[str, np.ndarray] | None = None,
) -> None:
    """``states.hdf5``: per state (``keys`` sorted) and object: ``pixels`` (S, O) int32 visible pixel count
    (-1 unknown), ``boxes`` (S, O, 4) int16 ``[x0, y0, x1, y1]``, ``distance`` (S, O) metres on the floor
    plane; ``extra`` datasets of the same row order; attributes ``image_size`` and ``min_pixels``."""
    with h5py.File(folder / "states.hdf5", "w") as f:
        f.create_dataset("keys", data=np.asarray(keys).astype("S"), track_times=False)
        f.create_dataset("object_ids", data=np.array(list(object_ids), dtype="S"), track_times=False)
        f.create_dataset("pixels", data=pixels, track_times=False)
        f.create_dataset("boxes", data=boxes, track_times=False)
        f.create_dataset("distance", data=distance, track_times=False)
        for name, data in (extra or {}).items():
            f.create_dataset(name, data=data, track_times=False)
        f.attrs["image_size"] = image_size
        if min_pixels is not None:
            f.attrs["min_pixels"] = min_pixels


#: HDF5 filters a frame file may use: the ones every stock h5py reads with no plugin (the lineage's readers
#: open the files unchanged). ``None``: stored raw.
FRAME_COMPRESSIONS = (None, "gzip", "lzf")
#: The writers' default: gzip level 1, one chunk per frame. The flat-shaded renders of this project compress
#: about 4.5x at 128 px (BENCHMARKS.md "Frames at a fraction of the disk"); higher levels gain a few per cent
#: for much more CPU time, and byte shuffling makes float16 depth larger, not smaller.
DEFAULT_COMPRESSION = "gzip"
DEFAULT_COMPRESSION_LEVEL = 1


class FrameWriter:
    """``images.hdf5`` (RGB uint8 HxWx3) and ``depth.hdf5`` (metres, ``depth_dtype``), one dataset per state
    key; a context manager that closes both files.

    ``compression`` (:data:`FRAME_COMPRESSIONS`; ``level`` for gzip) applies to both files, with each frame
    one HDF5 chunk (h5py's automatic chunking would split a 128 px frame into four chunks and compress
    worse); plain ``h5py`` reads the datasets as before (``f[key][()]``), decompressing as it reads.
    """

    def __init__(
        self,
        folder: Path,
        depth_dtype: str = "float16",
        compression: str | None = DEFAULT_COMPRESSION,
        level: int | None = DEFAULT_COMPRESSION_LEVEL,
    ):
        if compression not in FRAME_COMPRESSIONS:
            raise ValueError(
                f"unknown frame compression {compression!r} (choose from "
                f"{', '.join(str(c) for c in FRAME_COMPRESSIONS)})"
            )
        if compression == "gzip" and level is not None and not 0 <= int(level) <= 9:
            raise ValueError(f"gzip level must be in 0..9, got {level}")
        self.depth_dtype, self.compression = depth_dtype, compression
        self.level = None if compression != "gzip" else (4 if level is None else int(level))
        self._dcpl: dict[tuple, object] = {}
        self.images = h5py.File(folder / "images.hdf5", "w", track_order=False)
        try:
            self.depth = h5py.File(folder / "depth.hdf5", "w", track_order=False)
        except BaseException:
            self.images.close()
            raise

    def _put(self, f, key: str, data: np.ndarray) -> None:
        """One dataset ``key`` holding ``data``, through h5py's low-level calls with one creation property list
        per shape (h5py's ``create_dataset`` rebuilds the filter pipeline for every dataset: about a third of
        the write time of a compressed frame); the files read as any h5py-written ones."""
        data = np.ascontiguousarray(data)
        sig = (data.shape, data.dtype.str)
        dcpl = self._dcpl.get(sig)
        if dcpl is None:
            dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
            dcpl.set_obj_track_times(False)
            if self.compression is not None:
                dcpl.set_chunk(data.shape)  # one chunk per frame
                if self.compression == "gzip":
                    dcpl.set_deflate(self.level)
                else:
                    dcpl.set_filter(h5py.h5z.FILTER_LZF, h5py.h5z.FLAG_OPTIONAL)
            self._dcpl[sig] = dcpl
        ds = h5py.h5d.create(
            f.id, key.encode(), h5py.h5t.py_create(data.dtype), h5py.h5s.create_simple(data.shape), dcpl=dcpl
        )
        ds.write(h5py.h5s.ALL, h5py.h5s.ALL, data)

    def add(self, key: str, rgb: np.ndarray, depth: np.ndarray) -> None:
        """Store the frame of state ``key``: ``rgb`` (H, W, 3) uint8 and ``depth`` (H, W) metres."""
        self._put(self.images, key, np.asarray(rgb))
        self._put(self.depth, key, np.asarray(depth).astype(self.depth_dtype))

    def add_many(self, keys, rgb: np.ndarray, depth: np.ndarray) -> None:
        """Store the frames of states ``keys`` (N), in that order: ``rgb`` (N, H, W, 3) uint8 and ``depth``
        (N, H, W) metres, converted to ``depth_dtype`` once for the batch. The files equal those of
        :meth:`add` called frame by frame."""
        depth = np.asarray(depth).astype(self.depth_dtype)
        if not (len(keys) == len(rgb) == len(depth)):
            raise ValueError(f"add_many: {len(keys)} keys, {len(rgb)} RGB frames, {len(depth)} depth frames")
        for key, c, d in zip(keys, rgb, depth):
            self._put(self.images, key, c)
            self._put(self.depth, key, d)

    def close(self) -> None:
        for f in (self.images, self.depth):
            try:
                f.close()
            except Exception:  # noqa: BLE001 - closing after an error must not hide it
                pass

    def __enter__(self) -> "FrameWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@contextmanager
def scene_folder(final: str | Path) -> Iterator[Path]:
    """Atomic commit of the scene folder ``final``: yields an empty hidden temporary folder next to it; when
    the block ends without error writes ``COMPLETE`` into it, replaces an old (incomplete or overwritten)
    ``final`` and renames (:func:`tsnav.atomic.atomic_folder`); on any error removes the temporary folder."""
    with atomic_folder(final) as tmp:
        yield tmp
        (tmp / COMPLETE_MARKER).write_text("ok\n")
