"""Training data of the learned detector: rendered frames and their ground truth per class.

Frames come from each scene's ``images.hdf5`` (one uint8 ``H x W x 3`` dataset per state key, the lineage
layout); targets from :func:`tsnav.detect.oracle.ground_truth` (present when an instance shows at least
``min_pixels``; the box of the visible instance with most pixels), boxes normalised to [0, 1] as continuous
``[x0, y0, x1, y1]`` (:func:`tsnav.data.detections.pixel_to_unit`). The detector is trained on the TRAIN split
only and calibrated on VAL.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import torch
from tqdm import tqdm

from ..data.detections import pixel_to_unit
from ..data.reader import Scene, SceneFormatError, is_complete, list_scenes, load_scene, read_stack
from ..errors import CommandError
from .oracle import ground_truth, min_pixels


def read_images(scene_dir: str | Path, keys) -> np.ndarray:
    """``(len(keys), H, W, 3)`` uint8 frames of ``keys`` from ``scene_dir/images.hdf5``, in that order."""
    path = Path(scene_dir) / "images.hdf5"
    if not path.exists():
        raise FileNotFoundError(f"{path}: missing (build the world with images)")
    keys = [str(k) for k in keys]
    try:
        with h5py.File(path, "r") as f:
            missing = [k for k in keys if k not in f]
            if missing:
                raise SceneFormatError(f"{path}: lacks state {missing[0]!r} ({len(missing)} missing)")
            if not keys:
                return np.zeros((0, 0, 0, 3), np.uint8)
            out = read_stack(f, keys).astype(np.uint8, copy=False)
    except OSError as e:
        raise SceneFormatError(f"{path}: unreadable ({e})") from None
    return out


def frame_twins(scenes: list[Path], frames: Path, what: str) -> list[tuple[Path, Path, int, int]]:
    """Each scene folder of ``scenes`` with its twin in ``frames``, a build of the same scenes at another side
    (``tsnav world --size``): ``(scene, twin, scene's frame side, twin's frame side)``. One-line error, prefixed
    ``what``, for a scene that ``frames`` lacks or holds with other states."""
    out = []
    for p in scenes:
        q = Path(frames) / p.name
        if not is_complete(q):
            raise CommandError(f"{what}: no complete scene {p.name} (build it with tsnav world --size)")
        scene, twin = load_scene(p), load_scene(q)
        if not np.array_equal(twin.keys, scene.keys):
            raise CommandError(f"{what}: {p.name} has other states than in {p.parent} (not a build of that scene)")
        out.append((p, q, scene.image_size, twin.image_size))
    return out


@dataclass
class FrameSet:
    """Frames and targets of several scenes (``N`` frames, ``K`` = most target objects in one scene).

    Attributes:
        images: ``(N, H, W, 3)`` uint8.
        present: ``(N, C)`` bool, the class is in view (ground truth of :mod:`tsnav.detect.oracle`).
        boxes: ``(N, C, 4)`` float32 normalised continuous ground-truth box per class (0 where absent).
        obj_boxes: ``(N, K, 4)`` float32 normalised continuous box of every target object (0 if not in view).
        obj_category: ``(N, K)`` int16 class of each object column (-1: padding).
        obj_state: ``(N, K)`` int8: 0 not in view, 1 fewer than ``min_pixels`` pixels, 2 visible.
        scenes: scene names; offsets: ``(len(scenes)+1,)`` row ranges of each scene.
    """

    images: np.ndarray
    present: np.ndarray
    boxes: np.ndarray
    obj_boxes: np.ndarray
    obj_category: np.ndarray
    obj_state: np.ndarray
    scenes: list
    offsets: np.ndarray

    def __len__(self) -> int:
        return len(self.images)


def scene_targets(scene: Scene, rows: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Targets of ``scene`` for state ids ``rows`` (default all): the per-class ``present`` / ``boxes`` and
    the per-object ``obj_boxes`` / ``obj_category`` / ``obj_state`` of :class:`FrameSet`."""
    gt = ground_truth(scene)
    rows = np.arange(scene.num_states) if rows is None else np.asarray(rows)
    present = gt.present[rows]
    boxes = np.where(present[..., None], pixel_to_unit(gt.boxes[rows], scene.image_size), 0.0)
    cols = np.flatnonzero(scene.object_category >= 0)
    px = scene.pixels[np.ix_(rows, cols)]
    state = np.where(px >= min_pixels(scene), 2, np.where(px > 0, 1, 0)).astype(np.int8)
    ob = scene.boxes[rows][:, cols].astype(np.float32)
    ob = np.where(state[..., None] > 0, pixel_to_unit(ob, scene.image_size), 0.0).astype(np.float32)
    cat = np.broadcast_to(scene.object_category[cols].astype(np.int16), state.shape)
    return {
        "present": present,
        "boxes": boxes.astype(np.float32),
        "obj_boxes": ob,
        "obj_category": cat,
        "obj_state": state,
    }


def _pad(parts: list[np.ndarray], width: int, fill) -> np.ndarray:
    out = []
    for a in parts:
        pad = [(0, 0), (0, width - a.shape[1])] + [(0, 0)] * (a.ndim - 2)
        out.append(np.pad(a, pad, constant_values=fill))
    return np.concatenate(out)


def load_frames(
    root: str | Path,
    split: str,
    max_states_per_scene: int | None = None,
    seed: int = 0,
    progress: bool = False,
    scenes: Collection[str] | None = None,
) -> FrameSet:
    """Frames and targets of every complete scene of ``split`` under ``root`` (optionally a random subset of
    at most ``max_states_per_scene`` states per scene, drawn with ``seed``; optionally only the scenes named in
    ``scenes``, as if the world held no others)."""
    paths = [p for p in list_scenes(root, split=split) if scenes is None or p.name in scenes]
    if not paths:
        only = " among the scenes asked for" if scenes is not None else ""
        raise ValueError(f"{root}: no complete scene of split {split!r}{only}")
    picked, targets, names, sizes = [], [], [], []
    size, classes = None, None
    for p in paths:  # the states of each scene first, then the frames straight into one array (no second copy)
        s = load_scene(p)
        if size is None:
            size, classes = s.image_size, s.class_set
        elif s.image_size != size:
            raise ValueError(f"scene {s.name} has {s.image_size}px frames, others {size}px")
        elif s.class_set != classes:
            raise ValueError(f"scene {s.name} uses class set {s.class_set.name}, others {classes.name}")
        rows = np.arange(s.num_states)
        if max_states_per_scene is not None and s.num_states > max_states_per_scene:
            rng = np.random.default_rng([seed, len(names)])
            rows = np.sort(rng.choice(s.num_states, max_states_per_scene, replace=False))
        picked.append((p, s.keys[rows]))
        targets.append(scene_targets(s, rows))
        names.append(s.name)
        sizes.append(len(rows))
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    images = np.empty((int(offsets[-1]), size, size, 3), np.uint8)
    bar = tqdm(picked, desc=f"frames {split}", unit="scene", disable=not progress, dynamic_ncols=True)
    for i, (p, keys) in enumerate(bar):
        if len(keys):
            images[offsets[i] : offsets[i + 1]] = read_images(p, keys)
    K = max(1, max(t["obj_category"].shape[1] for t in targets))
    return FrameSet(
        images=images,
        present=np.concatenate([t["present"] for t in targets]),
        boxes=np.concatenate([t["boxes"] for t in targets]),
        obj_boxes=_pad([t["obj_boxes"] for t in targets], K, 0.0),
        obj_category=_pad([t["obj_category"] for t in targets], K, -1),
        obj_state=_pad([t["obj_state"] for t in targets], K, 0),
        scenes=names,
        offsets=offsets,
    )


def flip_boxes(boxes: torch.Tensor) -> torch.Tensor:
    """Normalised continuous boxes under a horizontal flip of the frame: x0' = 1 - x1, x1' = 1 - x0."""
    return torch.stack([1 - boxes[..., 2], boxes[..., 1], 1 - boxes[..., 0], boxes[..., 3]], dim=-1)


@dataclass
class Batch:
    """A training batch: uint8 ``images`` ``[B, H, W, 3]``; ``present`` ``[B, 22]``; ``boxes``
    ``[B, C, 4]``; ``obj_boxes`` ``[B, K, 4]``; ``obj_category``, ``obj_state`` ``[B, K]`` (see
    :class:`FrameSet`)."""

    images: torch.Tensor
    present: torch.Tensor
    boxes: torch.Tensor
    obj_boxes: torch.Tensor
    obj_category: torch.Tensor
    obj_state: torch.Tensor


def make_batch(frames: FrameSet, index: np.ndarray, flip: np.ndarray) -> Batch:
    """The rows ``index`` of ``frames``, with the frames where ``flip`` is True mirrored left-right (their
    boxes mirrored with them). The source arrays are never modified."""
    index = np.asarray(index)
    img = torch.from_numpy(frames.images[index])
    present = torch.from_numpy(frames.present[index])
    boxes = torch.from_numpy(frames.boxes[index])
    ob = torch.from_numpy(frames.obj_boxes[index])
    state = torch.from_numpy(frames.obj_state[index].astype(np.int64))
    f = torch.from_numpy(np.asarray(flip, dtype=bool))
    if f.any():
        img[f] = img[f].flip(2)
        boxes[f] = torch.where(present[f][..., None], flip_boxes(boxes[f]), boxes[f])
        ob[f] = torch.where((state[f] > 0)[..., None], flip_boxes(ob[f]), ob[f])
    return Batch(img, present, boxes, ob, torch.from_numpy(frames.obj_category[index].astype(np.int64)), state)
