"""A tiny synthetic RGB-D dataset in the lineage's scene-folder layout, for tests and benchmarks.

Each scene is a small grid of states; each state's frame is a floor plane (depth grows towards the horizon)
with a few boxes at constant depth whose brightness falls with their depth, so that RGB carries depth
cues a probe can find. Objects of target categories appear in ``states.hdf5`` with pixel counts, so the
supervised-ResNet baseline and the probe have labels. Not a renderer: only the file layout is real.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from ..constants import CAMERA_HEIGHT, HORIZONS, ROTATIONS, TARGET_CATEGORIES, state_key
from ..data.reader import COMPLETE_MARKER


def synth_frame(rng: np.random.Generator, size: int, cats: list[int], max_boxes: int = 3):
    """One RGB-D frame: returns ``rgb uint8 [S, S, 3]``, ``depth float32 [S, S]`` metres, ``pixels [len(cats)]``."""
    rows = np.arange(size, dtype=np.float32)[:, None] + 0.5
    horizon = size * 0.4
    below = rows > horizon
    floor = np.where(below, CAMERA_HEIGHT * size / (2.0 * np.maximum(rows - horizon, 1e-3)), 6.0)
    depth = np.minimum(np.repeat(floor, size, axis=1), 6.0).astype(np.float32)
    shade = (255 * (1 - depth / 6.5)).astype(np.float32)
    rgb = np.stack([shade * 0.9, shade * 0.8, shade * 0.6], axis=-1)
    ids = np.full((size, size), -1, dtype=np.int64)  # which object each pixel shows
    for _ in range(int(rng.integers(1, max_boxes + 1))):
        j = int(rng.integers(len(cats)))
        w, h = rng.integers(size // 8, size // 2, size=2)
        x0, y0 = rng.integers(0, size - w), rng.integers(0, size - h)
        d = float(rng.uniform(0.5, 5.0))
        region = (slice(y0, y0 + h), slice(x0, x0 + w))
        closer = depth[region] > d
        depth[region] = np.where(closer, d, depth[region])
        ids[region] = np.where(closer, j, ids[region])
        colour = np.array([(37 * cats[j]) % 255, (91 * cats[j]) % 255, (53 * cats[j] + 80) % 255], np.float32)
        rgb[region] = np.where(closer[..., None], colour * (1.1 - d / 5.5), rgb[region])
    labels = np.bincount(ids[ids >= 0], minlength=len(cats)).astype(np.int32)
    return np.clip(rgb, 0, 255).astype(np.uint8), depth, labels


def write_synthetic_dataset(
    root: str | Path,
    scenes: dict[str, str] | None = None,
    size: int = 32,
    positions: int = 2,
    seed: int = 0,
    num_objects: int = 3,
) -> Path:
    """Write scene folders under ``root``: ``{name: split}`` (default two train and one val scene).

    Each scene has ``positions`` grid positions x 8 rotations x 2 horizons states, ``images.hdf5`` /
    ``depth.hdf5`` (one dataset per state key), ``graph.json``, ``scene.json``, ``states.hdf5`` and the
    ``COMPLETE`` marker. Returns ``root``.
    """
    root = Path(root)
    scenes = scenes or {"Synth1": "train", "Synth2": "train", "Synth3": "val"}
    rng = np.random.default_rng(seed)
    for si, (name, split) in enumerate(scenes.items()):
        d = root / name
        d.mkdir(parents=True, exist_ok=True)
        cats = sorted(rng.choice(len(TARGET_CATEGORIES), size=num_objects, replace=False).tolist())
        oids = [f"{TARGET_CATEGORIES[c]}|{si}|{j}" for j, c in enumerate(cats)]
        keys = sorted(state_key(0.25 * i, 0.0, r, h) for i in range(positions) for r in ROTATIONS for h in HORIZONS)
        pixels = np.zeros((len(keys), len(cats)), dtype=np.int32)
        with h5py.File(d / "images.hdf5", "w") as fi, h5py.File(d / "depth.hdf5", "w") as fd:
            for i, k in enumerate(keys):
                rgb, depth, px = synth_frame(rng, size, cats)
                fi.create_dataset(k, data=rgb)
                fd.create_dataset(k, data=depth)
                pixels[i] = px
        with h5py.File(d / "states.hdf5", "w") as f:
            f.create_dataset("keys", data=np.array(keys, dtype="S"))
            f.create_dataset("object_ids", data=np.array(oids, dtype="S"))
            f.create_dataset("distance", data=np.ones(pixels.shape, np.float32))
            f.create_dataset("pixels", data=pixels)
            f.create_dataset("boxes", data=np.full(pixels.shape + (4,), -1, np.int16))
            f.attrs["image_size"] = size
        # rotate in place: RotateRight / RotateLeft edges only (enough for the reader)
        links = []
        for k in keys:
            x, z, r, h = k.split("|")
            links.append({"source": k, "target": f"{x}|{z}|{(int(r) + 45) % 360}|{h}"})
        (d / "graph.json").write_text(
            json.dumps({"directed": True, "nodes": [{"id": k} for k in keys], "links": links})
        )
        (d / "scene.json").write_text(
            json.dumps(
                {
                    "name": name,
                    "split": split,
                    "image_size": size,
                    "room_type": "kitchen",
                    "objects": [{"objectId": o} for o in oids],
                    "visibility": {"min_pixels": 1},
                }
            )
        )
        (d / COMPLETE_MARKER).write_text("")
    return root
