"""Ground truth and the oracle detector, from the renderer's instance ids (DESIGN.md "Detector").

Ground truth per state and class (:func:`ground_truth`): the class is *present* when one of its instances
shows at least the scene's ``min_pixels`` (``scene.json`` ``visibility.min_pixels``, the visibility rule of
the dataset writer); the ground-truth *instance* is the visible one with the most pixels (ties: the nearer,
then the lower object index) and the ground-truth *box* is that instance's pixel box ``Scene.boxes`` (the
box of all its visible pixels, inclusive corners).

The oracle detector (:func:`oracle_detections`) reports exactly that instance and box, with a confidence
that stands in for a detector's score (paper III-B switches stage at confidence > C_target = 0.7):

    conf = sigmoid(size_gain * ln(f / half_fraction) + distance_gain * (half_distance - d))

where ``f`` is the instance's visible pixel fraction of the frame and ``d`` its distance in metres from the
camera (``Scene.distance``; the distance term is 0 when unknown). conf = 0 when the class is not present.
With the defaults a 10 %-of-frame object at 0.5 m scores 0.999, a 40-pixel (1 % of 64x64) object at 1.5 m
0.91, and a 5-pixel sliver at 4 m 0.04. Deterministic. The confidence is a hand-made stand-in for a
detector's score (a real detector's score does fall with distance, as objects shrink and blur), so it depends
on the true distance; the oracle is therefore an explicitly named option only (``--detections oracle``), never
a silent default, and its *feature* carries no distance (below).

Oracle feature (64-d, :data:`ORACLE_FEATURE_DIM`), fixed, no learning:

* ``[0:32)``  the category code (fixed random signs +-1/sqrt(32), seed ``OracleConfig.seed``) times conf;
* ``[32:56)`` Fourier features of the box geometry ``g = (cx, cy, w, h) / image_size``:
  ``sin(pi 2^k g), cos(pi 2^k g)`` for k = 0, 1, 2 (zero when not present);
* ``[56:64)`` ``conf, present, sqrt(f), 0, x0 / W, y0 / H, (x1 + 1) / W, (y1 + 1) / H``
  (zero when not present).

Slot 59 held the true distance ``min(d, 5) / 5`` up to ``OracleConfig.version`` 1 (issue 14: nothing privileged
reaches the agent). It is kept, always zero, so the feature stays 64-d and tables, agents and the lineage export
keep their shapes; version 2 changes the fingerprint, so oracle tables written before are recomputed by
``ensure_oracle_detections`` instead of being silently reused.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass

import numpy as np

from ..constants import ITHOR22
from ..data.reader import Scene
from ..data.detections import Detections

#: Size of the oracle's per-class feature vector.
ORACLE_FEATURE_DIM = 64
_CODE_DIM = 32
_FOURIER_OCTAVES = 3


@dataclass
class OracleConfig:
    """Confidence model of the oracle detector (see the module docstring for the formula)."""

    half_fraction: float = 0.004
    """Visible pixel fraction of the frame at which the size term of the logit is zero (0.4 %: 16 px at 64x64)."""
    size_gain: float = 1.5
    """Logit added per e-fold of the visible pixel fraction."""
    half_distance: float = 2.5
    """Distance in metres at which the distance term of the logit is zero."""
    distance_gain: float = 1.0
    """Logit added per metre nearer than ``half_distance``."""
    seed: int = 0
    """Seed of the fixed random category code of the feature."""
    version: int = 2
    """Layout version of the oracle table (2: feature slot 59, the true distance in version 1, is zero)."""

    def fingerprint(self) -> str:
        return "oracle-" + hashlib.sha256(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()[:12]


@dataclass
class GroundTruth:
    """Per state and class ground truth of a scene (``S`` states, ``C`` classes of the scene's class set).

    Attributes:
        present: ``(S, C)`` bool, an instance shows at least ``min_pixels``.
        boxes: ``(S, C, 4)`` float32 box of the ground-truth instance, inclusive pixel corners; -1 if absent.
        pixels: ``(S, C)`` int32 visible pixels of that instance (0 if absent).
        distance: ``(S, C)`` float32 its distance from the camera, metres (NaN if absent or unknown).
        instance: ``(S, C)`` int64 its object column in the scene, -1 if absent.
    """

    present: np.ndarray
    boxes: np.ndarray
    pixels: np.ndarray
    distance: np.ndarray
    instance: np.ndarray


def min_pixels(scene: Scene) -> int:
    """Pixels an instance must show to count as seen (the dataset's visibility rule; at least 1)."""
    return max(1, int(scene.meta.get("visibility", {}).get("min_pixels", 1)))


def ground_truth(scene: Scene) -> GroundTruth:
    """Ground truth of every state of ``scene``: presence, instance and box per class (batched over states;
    the loop runs over the scene's classes)."""
    S, C = scene.num_states, scene.num_categories
    present = np.zeros((S, C), bool)
    boxes = np.full((S, C, 4), -1.0, np.float32)
    pixels = np.zeros((S, C), np.int32)
    distance = np.full((S, C), np.nan, np.float32)
    instance = np.full((S, C), -1, np.int64)
    if (scene.pixels < 0).all() and scene.pixels.size:
        raise ValueError(f"scene {scene.name}: no per-state pixel counts (states.hdf5) for ground truth")
    vis = scene.pixels >= min_pixels(scene)
    rows = np.arange(S)
    for c in range(C):
        cols = np.flatnonzero(scene.object_category == c)
        if cols.size == 0:
            continue
        px = np.where(vis[:, cols], scene.pixels[:, cols], -1)  # (S, k)
        best_px = px.max(axis=1)
        # Most pixels first, then the nearer (unknown distance counts as very far), then the first column.
        dist = np.nan_to_num(scene.distance[:, cols].astype(np.float64), nan=1e30, posinf=1e30)
        best = cols[np.argmin(np.where(px == best_px[:, None], dist, np.inf), axis=1)]
        ok = best_px >= 0
        present[:, c] = ok
        instance[ok, c] = best[ok]
        pixels[ok, c] = scene.pixels[rows[ok], best[ok]]
        distance[ok, c] = scene.distance[rows[ok], best[ok]]
        boxes[ok, c] = scene.boxes[rows[ok], best[ok]].astype(np.float32)
    return GroundTruth(present, boxes, pixels, distance, instance)


def ground_truth_reference(scene: Scene) -> GroundTruth:
    """Slow reference for :func:`ground_truth`: loops over states and objects."""
    S, C = scene.num_states, scene.num_categories
    present = np.zeros((S, C), bool)
    boxes = np.full((S, C, 4), -1.0, np.float32)
    pixels = np.zeros((S, C), np.int32)
    distance = np.full((S, C), np.nan, np.float32)
    instance = np.full((S, C), -1, np.int64)
    mp = min_pixels(scene)
    for s in range(S):
        best: dict[int, tuple] = {}
        for o in range(len(scene.object_ids)):
            c = int(scene.object_category[o])
            px = int(scene.pixels[s, o])
            if c < 0 or px < mp:
                continue
            d = float(scene.distance[s, o])
            rank = (-px, d if np.isfinite(d) else np.inf, o)
            if c not in best or rank < best[c]:
                best[c] = rank
        for c, (_, _, o) in best.items():
            present[s, c] = True
            instance[s, c] = o
            pixels[s, c] = scene.pixels[s, o]
            distance[s, c] = scene.distance[s, o]
            boxes[s, c] = scene.boxes[s, o]
    return GroundTruth(present, boxes, pixels, distance, instance)


def oracle_confidence(
    pixels: np.ndarray, distance: np.ndarray, image_size: int, cfg: OracleConfig | None = None
) -> np.ndarray:
    """Oracle confidence (float32 in [0, 1]) of instances showing ``pixels`` pixels at ``distance`` metres in a
    ``image_size``-square frame; 0 where ``pixels`` is 0. Formula in the module docstring."""
    cfg = cfg or OracleConfig()
    pixels = np.asarray(pixels, dtype=np.float64)
    frac = pixels / float(image_size) ** 2
    d = np.asarray(distance, dtype=np.float64)
    dist_term = np.where(np.isfinite(d), cfg.distance_gain * (cfg.half_distance - np.nan_to_num(d)), 0.0)
    with np.errstate(divide="ignore"):
        logit = cfg.size_gain * np.log(np.maximum(frac, 1e-12) / cfg.half_fraction) + dist_term
    conf = 1.0 / (1.0 + np.exp(-logit))
    return np.where(pixels > 0, conf, 0.0).astype(np.float32)


def category_code(seed: int = 0, num_categories: int = ITHOR22.size) -> np.ndarray:
    """``(C, 32)`` fixed category code of the oracle feature: random signs scaled to unit norm (C = 22 by
    default; another class set's code is drawn the same way at its own size)."""
    rng = np.random.default_rng(seed)
    return (rng.integers(0, 2, size=(num_categories, _CODE_DIM)) * 2 - 1).astype(np.float32) / np.sqrt(_CODE_DIM)


def oracle_features(gt: GroundTruth, conf: np.ndarray, image_size: int, seed: int = 0) -> np.ndarray:
    """``(S, C, 64)`` float16 oracle feature (layout in the module docstring): a function of the box, the
    visible pixel fraction and ``conf`` only (``gt.distance`` is not read)."""
    S, C = gt.present.shape
    W = float(image_size)
    pres = gt.present[..., None].astype(np.float32)
    code = category_code(seed, C)[None] * conf[..., None]  # (S, C, 32)
    b = gt.boxes.astype(np.float32)
    x0, y0, x1, y1 = b[..., 0], b[..., 1], b[..., 2] + 1, b[..., 3] + 1
    g = np.stack([(x0 + x1) / 2 / W, (y0 + y1) / 2 / W, (x1 - x0) / W, (y1 - y0) / W], axis=-1)  # (S, C, 4)
    ang = np.pi * g[..., None, :] * (2.0 ** np.arange(_FOURIER_OCTAVES, dtype=np.float32))[:, None]  # (S,C,3,4)
    four = np.concatenate([np.sin(ang), np.cos(ang)], axis=-2).reshape(S, C, -1) * pres
    frac = gt.pixels.astype(np.float32) / W**2
    no_distance = np.zeros_like(frac)  # slot 59: the true distance until version 1; nothing privileged now
    tail = (
        np.stack(
            [conf, gt.present.astype(np.float32), np.sqrt(frac), no_distance, x0 / W, y0 / W, x1 / W, y1 / W], axis=-1
        )
        * pres
    )
    out = np.concatenate([code, four, tail], axis=-1)
    assert out.shape[-1] == ORACLE_FEATURE_DIM
    return out.astype(np.float16)


def oracle_detections(scene: Scene, cfg: OracleConfig | None = None) -> Detections:
    """The oracle detector's table for every state of ``scene`` (module docstring)."""
    cfg = cfg or OracleConfig()
    if scene.image_size <= 0:
        raise ValueError(f"scene {scene.name}: unknown image size (scene.json / states.hdf5)")
    gt = ground_truth(scene)
    conf = oracle_confidence(gt.pixels, gt.distance, scene.image_size, cfg)
    labels = np.where(gt.present, np.arange(scene.num_categories, dtype=np.int16)[None, :], -1).astype(np.int16)
    # The columns are the scene's class set's (recorded in the table, which only scenes of that set read).
    return Detections(
        keys=scene.keys,
        scores=conf,
        labels=labels,
        boxes=gt.boxes,
        features=oracle_features(gt, conf, scene.image_size, cfg.seed),
        detector="oracle",
        config=dict(asdict(cfg), mirror=True) if scene.mirror else asdict(cfg),
        fingerprint=cfg.fingerprint(),
        image_size=scene.image_size,
        class_set=scene.class_set.name,
    )
