"""The learned detector's detection table (DESIGN.md "Detector"; stands in for the paper's DETR, Fig. 2).

For every state of a scene and each class: ``score = sigmoid(logit / T)`` of the presence logit (``T``
fitted on the VAL scenes by :func:`tsnav.detect.train.calibrate`), the box of the class's best cell
converted to inclusive pixel corners, and that cell's ``dim``-d feature (64-d by default). A class's
detection is kept (label = the class) when its score reaches ``min_score`` (0.05, the usual detector
output threshold); otherwise label and box are -1. Scores are stored for every class either way, because the stage switch (paper III-B) and the
calibration tables read them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..constants import check_same_class_set
from ..data.reader import Scene, load_scene
from .data import read_images
from .model import GridDetector
from ..data.detections import Detections, unit_to_pixel, write_detections
from ..scene_pool import as_is, map_scenes
from .train import load_model, predict, weights_fingerprint


class LearnedDetector:
    """A trained, calibrated :class:`~tsnav.detect.model.GridDetector` loaded from a checkpoint folder."""

    def __init__(
        self, model: GridDetector, temperature: float = 1.0, min_score: float = 0.05, meta: dict | None = None
    ):
        if not temperature > 0:
            raise ValueError(f"temperature must be positive, got {temperature}")
        self.model = model.eval()
        self.temperature = float(temperature)
        self.min_score = float(min_score)
        self.meta = meta or {}
        self.fingerprint = weights_fingerprint(model, self.temperature)

    @classmethod
    def load(cls, ckpt: str | Path, pinned: bool = False) -> "LearnedDetector":
        """The detector of the newest checkpoint of ``ckpt`` (``pinned``: of the files at its top only)."""
        model, meta = load_model(ckpt, pinned=pinned)
        if meta.get("calibrated_step", -1) != meta.get("step"):
            # Not (re)calibrated after the last training step: temperature 1 is the honest default.
            meta = dict(meta, temperature=1.0)
        return cls(model, float(meta.get("temperature", 1.0)), float(meta.get("min_score", 0.05)), meta)

    @property
    def image_size(self) -> int:
        return self.model.cfg.image_size

    @property
    def class_set(self) -> str:
        """The class set whose classes the detector scores (its columns)."""
        return self.model.cfg.class_set

    @property
    def num_classes(self) -> int:
        return int(self.model.cfg.num_classes)

    def config(self) -> dict:
        return {
            "model": self.model.cfg.to_dict(),
            "temperature": self.temperature,
            "min_score": self.min_score,
            "step": self.meta.get("step"),
            "train": self.meta.get("train"),
            "calibration_split": self.meta.get("calibration_split"),
        }

    def detect_images(
        self, images: np.ndarray, batch_size: int = 256
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(scores ``(N, C)``, labels ``(N, C)``, pixel boxes ``(N, C, 4)``, features ``(N, C, dim)``) of
        uint8 frames ``(N, H, W, 3)``."""
        if images.ndim != 4 or images.shape[1:] != (self.image_size, self.image_size, 3):
            raise ValueError(f"frames must be (N, {self.image_size}, {self.image_size}, 3), got {images.shape}")
        logits, unit, feats = predict(self.model, images, batch_size)
        scores = 1.0 / (1.0 + np.exp(-logits.astype(np.float64) / self.temperature))
        keep = scores >= self.min_score
        labels = np.where(keep, np.arange(self.num_classes, dtype=np.int16)[None, :], -1).astype(np.int16)
        boxes = np.clip(unit_to_pixel(unit, self.image_size), 0, self.image_size - 1)
        boxes = np.where(keep[..., None], boxes, -1.0).astype(np.float32)
        return scores.astype(np.float32), labels, boxes, feats

    def detect_scene(
        self, scene: Scene, batch_size: int = 256, chunk: int = 2048, bar=None, transform=None
    ) -> Detections:
        """The detection table of every state of ``scene`` (frames read ``chunk`` at a time; a mirrored scene's
        frames flipped left to right, :meth:`Scene.mirrored <tsnav.data.reader.Scene.mirrored>`, its table's
        ``config["mirror"]`` true). ``transform``, when given, maps each chunk of uint8 frames ``(n, H, W, 3)`` to the frames the detector sees (the same shape and
        dtype; e.g. ``scripts/noisy_tables.py``'s pixel noise), called once per chunk in state order."""
        if scene.image_size != self.image_size:
            raise ValueError(
                f"scene {scene.name} has {scene.image_size}px frames; the detector takes {self.image_size}px"
            )
        check_same_class_set(self.class_set, scene.class_set, "the detector", f"scene {scene.name}")
        S, C = scene.num_states, self.num_classes
        scores = np.empty((S, C), np.float32)
        labels = np.empty((S, C), np.int16)
        boxes = np.empty((S, C, 4), np.float32)
        feats = np.empty((S, C, self.model.cfg.dim), np.float16)
        for a in range(0, S, chunk):
            img = read_images(scene.path, scene.keys[a : a + chunk])
            if scene.mirror:
                img = np.ascontiguousarray(img[:, :, ::-1])
            if transform is not None:
                img = transform(img)
            sc, lb, bx, ft = self.detect_images(img, batch_size)
            n = len(img)
            scores[a : a + n], labels[a : a + n], boxes[a : a + n], feats[a : a + n] = sc, lb, bx, ft
            if bar is not None:
                bar.update(n)
        config = dict(self.config(), mirror=True) if scene.mirror else self.config()
        return Detections(
            keys=scene.keys,
            scores=scores,
            labels=labels,
            boxes=boxes,
            features=feats,
            detector="learned",
            config=config,
            fingerprint=self.fingerprint,
            image_size=self.image_size,
            class_set=self.class_set,
        )


def write_scene_tables(det: LearnedDetector, scenes: list[Scene], name: str, bar=None, workers: int = 1) -> None:
    """Write ``det``'s table ``detections_<name>.hdf5`` into every scene of ``scenes`` (``<name>-mirror`` for a
    mirrored scene, of its flipped frames). ``workers`` > 1: the scenes
    are shared by that many processes on one torch thread each (:func:`tsnav.scene_pool.map_scenes`; the same
    tables as here on one thread); else here, on the caller's threads. ``bar`` (tqdm) counts states."""
    if workers > 1 and len(scenes) > 1:
        for _, n in map_scenes(_scene_table, [(s.path, name, s.mirror) for s in scenes], as_is, det, workers):
            if bar is not None:
                bar.update(n)
        return
    for s in scenes:
        write_detections(s.path, s.cache_name(name), det.detect_scene(s, bar=bar))


def _scene_table(det: LearnedDetector, task) -> int:
    """One room's table, in a worker of :func:`write_scene_tables`; returns its number of states."""
    path, name, mirror = task
    scene = load_scene(path)
    scene = scene.mirrored() if mirror else scene
    write_detections(path, scene.cache_name(name), det.detect_scene(scene))
    return scene.num_states
