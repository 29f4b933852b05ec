"""Average precision, IoU and reliability tables: hand-computed values and slow references."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tsnav.detect.evaluate import (
    average_precision,
    average_precision_reference,
    box_iou,
    evaluate_detections,
    reliability_reference,
    reliability_table,
)
from tsnav.detect.oracle import ground_truth, oracle_detections


def test_average_precision_by_hand():
    # Ranks: TP, FP, TP, FP -> precision 1, 1/2, 2/3, 1/2 at recall 1/2, 1/2, 1, 1.
    # Envelope: 1, 2/3, 2/3, 1/2 -> AP = 1/2 * 1 + 1/2 * 2/3 = 5/6.
    s, p = [0.9, 0.8, 0.7, 0.6], [1, 0, 1, 0]
    assert average_precision(s, p) == pytest.approx(5 / 6)
    assert average_precision_reference(s, p) == pytest.approx(5 / 6)
    # Two more ground-truth objects never detected: recall tops out at 1/2 -> AP = 1/4 * 1 + 1/4 * 2/3.
    assert average_precision(s, p, num_positives=4) == pytest.approx(0.25 + 0.25 * 2 / 3)
    # Tied scores enter together: one threshold, precision 1/2 at recall 1.
    assert average_precision([0.5, 0.5], [1, 0]) == pytest.approx(0.5)
    assert average_precision([0.5, 0.5], [0, 1]) == pytest.approx(0.5)
    assert average_precision([0.3, 0.2], [1, 1]) == 1.0
    assert np.isnan(average_precision([0.3], [0]))
    assert average_precision([], [], num_positives=3) == 0.0


def test_average_precision_matches_reference():
    rng = np.random.default_rng(0)
    for trial in range(60):
        n = int(rng.integers(1, 40))
        scores = np.round(rng.random(n), 1)  # many ties
        pos = rng.random(n) < 0.4
        extra = int(rng.integers(0, 3))
        if pos.sum() + extra == 0:
            continue
        a = average_precision(scores, pos, int(pos.sum()) + extra)
        b = average_precision_reference(scores, pos, int(pos.sum()) + extra)
        assert a == pytest.approx(b, abs=1e-12), trial


def test_box_iou_by_hand():
    # Inclusive pixel boxes: [0,0,1,1] covers 4 pixels; overlap with [1,1,2,2] is one pixel -> 1 / 7.
    assert box_iou([0, 0, 1, 1], [1, 1, 2, 2]) == pytest.approx(1 / 7)
    assert box_iou([0, 0, 3, 3], [0, 0, 3, 3]) == 1.0
    assert box_iou([0, 0, 1, 1], [5, 5, 6, 6]) == 0.0
    assert box_iou([-1, -1, -1, -1], [-1, -1, -1, -1]) == 0.0  # "no box" never matches
    a = np.array([[0, 0, 9, 4], [2, 2, 2, 2]])
    b = np.array([[0, 0, 4, 4], [2, 2, 2, 2]])
    np.testing.assert_allclose(box_iou(a, b), [25 / 50, 1.0])


def test_reliability_by_hand():
    conf = [0.05, 0.15, 0.15, 0.95, 1.0]
    pos = [0, 1, 0, 1, 1]
    r = reliability_table(conf, pos)
    assert r.count.tolist() == [1, 1 + 1, 0, 0, 0, 0, 0, 0, 0, 2]
    assert r.confidence[0] == pytest.approx(0.05) and r.accuracy[0] == 0.0
    assert r.confidence[1] == pytest.approx(0.15) and r.accuracy[1] == 0.5
    assert r.confidence[9] == pytest.approx(0.975) and r.accuracy[9] == 1.0
    assert np.isnan(r.confidence[5]) and np.isnan(r.accuracy[5])
    # ECE = (1 * 0.05 + 2 * 0.35 + 2 * 0.025) / 5
    assert r.ece == pytest.approx((0.05 + 0.7 + 0.05) / 5)
    assert "ECE = 0.1600" in r.format()
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        reliability_table([1.2], [1])


def test_reliability_matches_reference():
    rng = np.random.default_rng(1)
    conf = np.concatenate([rng.random(300), np.linspace(0, 1, 11)])  # includes every bin edge
    pos = rng.random(len(conf)) < conf
    a, b = reliability_table(conf, pos), reliability_reference(conf, pos)
    np.testing.assert_array_equal(a.count, b.count)
    np.testing.assert_allclose(a.confidence, b.confidence)
    np.testing.assert_allclose(a.accuracy, b.accuracy)
    assert a.ece == pytest.approx(b.ece)


def test_oracle_is_perfect_and_shifted_boxes_are_not(tiny_scenes):
    scenes = tiny_scenes[:2]
    dets = [oracle_detections(s) for s in scenes]
    rep = evaluate_detections(scenes, dets)
    present = np.concatenate([ground_truth(s).present for s in scenes])
    np.testing.assert_array_equal(rep.positives, present.sum(0))
    seen = rep.positives > 0
    assert seen.any()
    np.testing.assert_allclose(rep.presence_ap[seen], 1.0)
    np.testing.assert_allclose(rep.box_ap[seen], 1.0)
    assert np.isnan(rep.presence_ap[~seen]).all()
    assert rep.reliability.count.sum() == present.size
    assert rep.states == sum(s.num_states for s in scenes)
    # Boxes moved far away: presence AP stays 1, box AP drops to 0.
    moved = [dataclasses.replace(d, boxes=np.where(d.boxes >= 0, d.boxes + 1000, d.boxes)) for d in dets]
    rep2 = evaluate_detections(scenes, moved)
    np.testing.assert_allclose(rep2.presence_ap[seen], 1.0)
    np.testing.assert_allclose(rep2.box_ap[seen], 0.0)
    text = rep.format()
    assert "presence AP" in text and "ECE" in text
    js = rep.to_json()
    assert set(js["classes"]) and js["mean_presence_ap"] == pytest.approx(1.0)
