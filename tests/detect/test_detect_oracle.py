"""Ground truth and the oracle detector on the rendered tiny world."""

from __future__ import annotations

import math

import numpy as np

from tsnav.constants import NUM_CATEGORIES
from tsnav.detect.oracle import (
    ORACLE_FEATURE_DIM,
    OracleConfig,
    category_code,
    ground_truth,
    ground_truth_reference,
    min_pixels,
    oracle_confidence,
    oracle_detections,
)


def test_ground_truth_matches_reference(tiny_scenes):
    for s in tiny_scenes:
        a, b = ground_truth(s), ground_truth_reference(s)
        for f in ("present", "boxes", "pixels", "instance"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f"{s.name} {f}")
        np.testing.assert_array_equal(a.distance, b.distance)


def test_ground_truth_is_the_largest_visible_instance(tiny_scenes):
    s = tiny_scenes[0]
    gt = ground_truth(s)
    mp = min_pixels(s)
    assert gt.present.any()
    for st, c in zip(*np.nonzero(gt.present)):
        cols = np.flatnonzero(s.object_category == c)
        o = gt.instance[st, c]
        assert o in cols
        assert s.pixels[st, o] == s.pixels[st, cols].max() >= mp
        np.testing.assert_array_equal(gt.boxes[st, c], s.boxes[st, o])
    # Present exactly when some instance of the class shows min_pixels.
    vis = s.pixels >= mp
    for c in range(NUM_CATEGORIES):
        cols = s.object_category == c
        np.testing.assert_array_equal(gt.present[:, c], vis[:, cols].any(axis=1))


def test_oracle_confidence_formula_by_hand():
    cfg = OracleConfig()
    # 16 px of 64x64 = 0.390625 % at 2.5 m: logit = 1.5 ln(0.00390625 / 0.004) + 0.
    z = 1.5 * math.log(0.00390625 / 0.004)
    assert math.isclose(float(oracle_confidence(16, 2.5, 64, cfg)), 1 / (1 + math.exp(-z)), rel_tol=1e-6)
    # A large close object is confident, a far sliver is not, an invisible one is exactly 0.
    assert oracle_confidence(0.1 * 64 * 64, 0.5, 64) > 0.9
    assert oracle_confidence(5, 4.0, 64) < 0.3
    assert oracle_confidence(0, 0.5, 64) == 0.0
    # Unknown distance: the distance term is 0.
    assert math.isclose(float(oracle_confidence(16, np.nan, 64)), float(oracle_confidence(16, 2.5, 64)))
    # Monotone: more pixels -> higher, farther -> lower.
    px = np.array([5, 10, 40, 200, 1000])
    assert (np.diff(oracle_confidence(px, np.full(5, 2.0), 64)) > 0).all()
    d = np.array([0.3, 1.0, 2.0, 4.0, 8.0])
    assert (np.diff(oracle_confidence(np.full(5, 40), d, 64)) < 0).all()


def test_oracle_table(tiny_scenes):
    for s in tiny_scenes:
        det = oracle_detections(s)
        gt = ground_truth(s)
        S = s.num_states
        assert det.scores.shape == (S, NUM_CATEGORIES) and det.labels.shape == (S, NUM_CATEGORIES)
        assert det.boxes.shape == (S, NUM_CATEGORIES, 4)
        assert det.features.shape == (S, NUM_CATEGORIES, ORACLE_FEATURE_DIM)
        np.testing.assert_array_equal(det.keys, s.keys)
        # Not visible -> score 0, no label, no box; visible -> positive score, own label, ground-truth box.
        assert (det.scores[~gt.present] == 0).all() and (det.labels[~gt.present] == -1).all()
        assert (det.boxes[~gt.present] == -1).all()
        assert (det.scores[gt.present] > 0).all()
        c = np.nonzero(gt.present)[1]
        np.testing.assert_array_equal(det.labels[gt.present], c)
        np.testing.assert_array_equal(det.boxes[gt.present], gt.boxes[gt.present])
        np.testing.assert_allclose(det.scores, oracle_confidence(gt.pixels, gt.distance, s.image_size))
        # Features: category code times confidence; geometry and tail zero when absent.
        f = det.features.astype(np.float32)
        np.testing.assert_allclose(f[..., :32], (category_code(0)[None] * det.scores[..., None]), atol=2e-3)
        assert (f[~gt.present][:, 32:] == 0).all()
        np.testing.assert_allclose(f[..., 56], det.scores, atol=1e-3)


def test_oracle_is_deterministic_and_ranks_closer_larger_higher(tiny_scenes):
    s = tiny_scenes[1]
    a, b = oracle_detections(s), oracle_detections(s)
    np.testing.assert_array_equal(a.scores, b.scores)
    np.testing.assert_array_equal(a.features, b.features)
    assert a.fingerprint == b.fingerprint == OracleConfig().fingerprint()
    assert OracleConfig(size_gain=2.0).fingerprint() != a.fingerprint
    gt = ground_truth(s)
    # Within one scene, among visible instances at the same distance, more pixels never scores lower.
    m = gt.present
    px, d, sc = gt.pixels[m], gt.distance[m], a.scores[m]
    for dist in np.unique(d)[:20]:
        k = d == dist
        order = np.argsort(px[k], kind="stable")
        assert (np.diff(sc[k][order]) >= 0).all()
