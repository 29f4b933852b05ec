"""An encoder-free feature cache: each frame's RGB average-pooled to a ``grid x grid`` map.

Written in the format of :mod:`tsnav.pretrain.features` (``features_<name>.hdf5``: ``features`` ``(S, 3, g, g)``
float16 normalised to zero mean / unit variance per channel with ImageNet statistics, ``keys``), so the agent
and trainers can run without a pretrained encoder: a "no encoder" reference and a fast cache for tests.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from ..data.reader import MIRROR_SUFFIX, list_scenes, load_scene, read_stack
from .data import IMAGENET_MEAN, IMAGENET_STD
from .features import write_feature_file

_MEAN = np.array(IMAGENET_MEAN, dtype=np.float32)
_STD = np.array(IMAGENET_STD, dtype=np.float32)


def pooled_pixels(rgb: np.ndarray, grid: int) -> np.ndarray:
    """``rgb (N, H, W, 3)`` uint8 -> ``(N, 3, grid, grid)`` float32: normalised RGB averaged over equal blocks
    (H and W must be multiples of ``grid``)."""
    n, h, w, _ = rgb.shape
    if h % grid or w % grid:
        raise ValueError(f"image size {h}x{w} is not a multiple of the grid {grid}")
    x = (rgb.astype(np.float32) / 255.0 - _MEAN) / _STD
    x = x.reshape(n, grid, h // grid, grid, w // grid, 3).mean(axis=(2, 4))  # [N, g, g, 3]
    return x.transpose(0, 3, 1, 2)


def cache_pixel_features(
    root: str | Path, name: str = "pixels", grid: int = 4, split: str | None = None, mirror: bool = False
) -> list[Path]:
    """Write ``features_<name>.hdf5`` of pooled pixels into every complete scene of ``root`` that lacks it; with
    ``mirror``, those of the frames flipped left to right as ``features_<name>-mirror.hdf5``."""
    out = []
    for p in list_scenes(root, split):
        f = p / f"features_{name}{MIRROR_SUFFIX if mirror else ''}.hdf5"
        if not f.exists():
            keys = load_scene(p).keys
            with h5py.File(p / "images.hdf5", "r") as fi:
                rgb = read_stack(fi, keys)
            if mirror:
                rgb = np.ascontiguousarray(rgb[:, :, ::-1])
            feats = pooled_pixels(rgb, grid).astype(np.float16)
            attrs = {
                "encoder": f"pixels:{grid}",
                "arch": "pixels",
                "method": "pooled-pixels",
                "img_size": int(rgb.shape[1]),
                "fingerprint": f"pixels-{grid}",
            }
            write_feature_file(f, feats, keys, dict(attrs, mirror=1) if mirror else attrs)
        out.append(f)
    return out
