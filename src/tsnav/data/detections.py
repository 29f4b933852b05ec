"""The per-state detection table stored with each scene (DESIGN.md "Detector").

The lineage (SAVN -> ... -> IOM, the paper's Fig. 2 "DETR" box) caches, for every state of a scene, the
best detection of each of the 22 target classes (``C`` classes of the scene's class set below: 22 for
``ithor22``, 12 for RoboTHOR's ``robothor12``). This project stores it per scene folder as
``detections_<name>.hdf5`` (``name`` = the detector, e.g. ``oracle`` or ``learned``):

=============  =====================  ==================================================================
dataset        shape / dtype          content
=============  =====================  ==================================================================
``keys``       ``(S,)`` bytes         state keys, sorted, the order of ``Scene.keys`` (row = state id)
``scores``     ``(S, C)`` float32     confidence in [0, 1] that the class is in view (paper III-B uses it
                                      for the stage switch, C_target = 0.7)
``labels``     ``(S, C)`` int16       the category index ``c`` in column ``c`` when a detection is kept,
                                      -1 when there is none
``boxes``      ``(S, C, 4)`` float32  ``[x0, y0, x1, y1]`` in pixels of the frame, inclusive corners (the
                                      convention of ``Scene.boxes``); -1 where the label is -1
``features``   ``(S, C, F)`` float16  per-class feature vector (the lineage's DETR decoder feature is
                                      256-d; this project's detectors give 64-d, see their modules)
=============  =====================  ==================================================================

File attributes: ``detector`` (kind, e.g. ``oracle``), ``name``, ``fingerprint`` (identifies the exact
detector: config and weights), ``config`` (JSON of the detector's resolved configuration),
``image_size``, ``class_set`` (:class:`~tsnav.constants.ClassSet` name; absent: ``ithor22``). A table is read
only for scenes of its class set (:func:`load_scene_detections`).

Files are written to a temporary name and renamed, so a file that exists is complete.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import h5py
import numpy as np

from ..atomic import atomic_path
from ..constants import DEFAULT_CLASS_SET, check_same_class_set, class_set as get_class_set


_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


def check_name(name: str) -> str:
    """Return ``name`` if it is usable in ``detections_<name>.hdf5``; ``ValueError`` otherwise."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(f"detector name {name!r} must use only letters, digits, '_', '-' and '.'")
    return name


def detections_path(scene_dir: str | Path, name: str) -> Path:
    """Path of the detection table ``detections_<name>.hdf5`` of a scene folder."""
    return Path(scene_dir) / f"detections_{check_name(name)}.hdf5"


@dataclass
class Detections:
    """Best detection per class for every state of a scene (or of several scenes, concatenated).

    Attributes (``S`` states, ``C`` classes of ``class_set``, ``F`` feature size):
        keys: ``(S,)`` str state keys (sorted per scene, the order of ``Scene.keys``).
        scores: ``(S, C)`` float32 confidence in [0, 1].
        labels: ``(S, C)`` int16 category index, -1 where no detection is kept.
        boxes: ``(S, C, 4)`` float32 ``[x0, y0, x1, y1]`` pixels, inclusive corners; -1 without detection.
        features: ``(S, C, F)`` float16 per-class feature.
        detector: the detector kind (``oracle`` / ``learned``).
        config: the detector's resolved configuration (JSON-able dict).
        fingerprint: identifies the detector (config hash, plus the weights' hash for learned ones).
        image_size: side of the square frames the boxes refer to, pixels.
        class_set: name of the class set whose classes are the columns (``ithor22``: 22, ``robothor12``: 12).
    """

    keys: np.ndarray
    scores: np.ndarray
    labels: np.ndarray
    boxes: np.ndarray
    features: np.ndarray
    detector: str = ""
    config: dict = field(default_factory=dict)
    fingerprint: str = ""
    image_size: int = 0
    class_set: str = DEFAULT_CLASS_SET

    def __post_init__(self) -> None:
        self.class_set = get_class_set(self.class_set).name
        self.keys = np.asarray(self.keys, dtype=str)
        self.scores = np.asarray(self.scores, dtype=np.float32)
        self.labels = np.asarray(self.labels, dtype=np.int16)
        self.boxes = np.asarray(self.boxes, dtype=np.float32)
        self.features = np.asarray(self.features, dtype=np.float16)
        self.validate()

    @property
    def num_states(self) -> int:
        return len(self.keys)

    @property
    def feature_dim(self) -> int:
        return int(self.features.shape[-1])

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first array whose shape or values break the table contract."""
        S, C = len(self.keys), get_class_set(self.class_set).size
        for name, arr, shape in (
            ("scores", self.scores, (S, C)),
            ("labels", self.labels, (S, C)),
            ("boxes", self.boxes, (S, C, 4)),
        ):
            if arr.shape != shape:
                raise ValueError(f"detections: {name} must have shape {shape}, got {arr.shape}")
        if self.features.ndim != 3 or self.features.shape[:2] != (S, C):
            raise ValueError(f"detections: features must have shape ({S}, {C}, F), got {self.features.shape}")
        if S and not (np.isfinite(self.scores).all() and self.scores.min() >= 0 and self.scores.max() <= 1):
            raise ValueError("detections: scores must be finite and in [0, 1]")
        ok = (self.labels == -1) | (self.labels == np.arange(C, dtype=np.int16)[None, :])
        if not ok.all():
            raise ValueError("detections: labels must be the column's category index or -1")

    def rows(self) -> np.ndarray:
        """``(S, C, 6)`` float32 rows ``(score, label, x0, y0, x1, y1)`` (the form of
        :meth:`tsnav.sim.batch.SceneBank.set_detections`)."""
        return np.concatenate(
            [self.scores[..., None], self.labels[..., None].astype(np.float32), self.boxes], axis=-1
        ).astype(np.float32)

    @classmethod
    def concatenate(cls, parts: Sequence["Detections"]) -> "Detections":
        """Stack the tables of several scenes (in the given order); they must share the feature size."""
        if not parts:
            raise ValueError("detections: nothing to concatenate")
        sets = {p.class_set for p in parts}
        if len(sets) > 1:
            raise ValueError(f"detections: class sets differ between scenes ({sorted(sets)})")
        dims = {p.feature_dim for p in parts}
        if len(dims) > 1:
            raise ValueError(f"detections: feature sizes differ between scenes ({sorted(dims)})")
        p0 = parts[0]
        return cls(
            keys=np.concatenate([p.keys for p in parts]),
            scores=np.concatenate([p.scores for p in parts]),
            labels=np.concatenate([p.labels for p in parts]),
            boxes=np.concatenate([p.boxes for p in parts]),
            features=np.concatenate([p.features for p in parts]),
            detector=p0.detector,
            config=p0.config,
            fingerprint=p0.fingerprint,
            image_size=p0.image_size,
            class_set=p0.class_set,
        )


def pixel_to_unit(boxes: np.ndarray, image_size: int) -> np.ndarray:
    """Inclusive pixel boxes ``[x0, y0, x1, y1]`` -> continuous boxes normalised to [0, 1]."""
    b = np.asarray(boxes, dtype=np.float32)
    out = np.stack([b[..., 0], b[..., 1], b[..., 2] + 1, b[..., 3] + 1], axis=-1) / float(image_size)
    return out.astype(np.float32)


def unit_to_pixel(boxes: np.ndarray, image_size: int) -> np.ndarray:
    """Inverse of :func:`pixel_to_unit` (float pixels, inclusive corners; at least one pixel wide)."""
    b = np.asarray(boxes, dtype=np.float32) * float(image_size)
    x1 = np.maximum(b[..., 2] - 1, b[..., 0])  # a box narrower than a pixel still covers one column
    y1 = np.maximum(b[..., 3] - 1, b[..., 1])
    return np.stack([b[..., 0], b[..., 1], x1, y1], axis=-1).astype(np.float32)


def rescale_detections(det: Detections, image_size: int) -> Detections:
    """``det`` with its boxes in the pixels of ``image_size``-px frames: a table written from frames of another side
    of the same states (``tsnav detect --frames``). Each box goes through its continuous form
    (:func:`pixel_to_unit`, :func:`unit_to_pixel`), so it stays at least one pixel wide, inside the frame; rows
    without a detection (label -1) keep their -1 box. Scores, labels and features are unchanged; ``config`` records
    the side the detector saw (``frames_size``)."""
    if det.image_size <= 0:
        raise ValueError("detections: the table records no frame size to rescale from")
    if image_size <= 0:
        raise ValueError(f"detections: cannot rescale to {image_size}px frames")
    scaled = np.clip(unit_to_pixel(pixel_to_unit(det.boxes, det.image_size), image_size), 0, image_size - 1)
    boxes = np.where((det.labels >= 0)[..., None], scaled, det.boxes).astype(np.float32)
    config = {**det.config, "frames_size": int(det.config.get("frames_size", det.image_size))}
    return replace(det, boxes=boxes, image_size=int(image_size), config=config)


def write_rescaled(src_dir: str | Path, dst_dir: str | Path, name: str, image_size: int) -> Path:
    """Write ``src_dir``'s table ``detections_<name>.hdf5`` into ``dst_dir`` with its boxes in the pixels of
    ``image_size``-px frames (:func:`rescale_detections`): the same states built at another side."""
    return write_detections(dst_dir, name, rescale_detections(load_detections(src_dir, name), image_size))


def _attr_str(x) -> str:
    return x.decode() if isinstance(x, bytes) else str(x)


def write_detections(scene_dir: str | Path, name: str, det: Detections) -> Path:
    """Write ``det`` to ``scene_dir/detections_<name>.hdf5`` atomically (temp file + rename)."""
    det.validate()
    if len(det.keys) > 1 and not (det.keys[:-1] < det.keys[1:]).all():
        raise ValueError("detections: keys must be sorted and unique (the order of Scene.keys)")
    path = detections_path(scene_dir, name)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.create_dataset("keys", data=det.keys.astype("S"), track_times=False)
        f.create_dataset("scores", data=det.scores, track_times=False)
        f.create_dataset("labels", data=det.labels, track_times=False)
        f.create_dataset("boxes", data=det.boxes, track_times=False)
        f.create_dataset("features", data=det.features, track_times=False)
        f.attrs["detector"] = det.detector
        f.attrs["name"] = name
        f.attrs["fingerprint"] = det.fingerprint
        f.attrs["config"] = json.dumps(det.config, sort_keys=True)
        f.attrs["image_size"] = int(det.image_size)
        if det.class_set != DEFAULT_CLASS_SET:  # absent reads as ithor22: iTHOR tables keep their bytes
            f.attrs["class_set"] = det.class_set
    return path


def read_fingerprint(scene_dir: str | Path, name: str) -> str | None:
    """Fingerprint of the detector that wrote a scene's table, or None when the scene has no table."""
    path = detections_path(scene_dir, name)
    if not path.exists():
        return None
    try:
        with h5py.File(path, "r") as f:
            return _attr_str(f.attrs.get("fingerprint", ""))
    except OSError as e:
        raise ValueError(f"{path}: unreadable ({e})") from None


def load_detections(scene_dir: str | Path, name: str) -> Detections:
    """Read ``scene_dir/detections_<name>.hdf5`` into a :class:`Detections` (one-line error when absent or
    malformed)."""
    path = detections_path(scene_dir, name)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no detection table (run `tsnav detect --detector ...`)")
    try:
        with h5py.File(path, "r") as f:
            cfg = _attr_str(f.attrs.get("config", "{}"))
            return Detections(
                keys=f["keys"][()].astype(str),
                scores=f["scores"][()],
                labels=f["labels"][()],
                boxes=f["boxes"][()],
                features=f["features"][()],
                detector=_attr_str(f.attrs.get("detector", "")),
                config=json.loads(cfg),
                fingerprint=_attr_str(f.attrs.get("fingerprint", "")),
                image_size=int(f.attrs.get("image_size", 0)),
                class_set=_attr_str(f.attrs.get("class_set", DEFAULT_CLASS_SET)),
            )
    except (OSError, KeyError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: unreadable detection table ({e})") from None
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def load_scene_detections(scenes: Sequence, name: str) -> Detections:
    """The tables of ``scenes`` (:class:`~tsnav.data.reader.Scene` objects) concatenated in that order,
    each checked against its scene's state keys and class set; a mirrored scene's is ``<name>-mirror``
    (:meth:`~tsnav.data.reader.Scene.cache_name`)."""
    parts = []
    for s in scenes:
        own = s.cache_name(name)  # a mirrored scene reads the table of its flipped frames
        if own != name and not detections_path(s.path, own).exists():
            raise FileNotFoundError(
                f"{detections_path(s.path, own)}: no table of the mirrored room (run `tsnav "
                f"detect --mirror --name {name}` with the detector of {name})"
            )
        d = load_detections(s.path, own)
        check_same_class_set(d.class_set, s.class_set, str(detections_path(s.path, own)), f"scene {s.name}")
        if len(d.keys) != len(s.keys) or not (d.keys == s.keys).all():
            raise ValueError(
                f"{detections_path(s.path, own)}: its states do not match scene {s.name} (rerun `tsnav detect`)"
            )
        parts.append(d)
    return Detections.concatenate(parts)
