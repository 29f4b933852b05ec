"""Reach, false positives and the figures of tsnav.detect.quality: hand-made cases, slow reference, PNGs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from PIL import Image

from tsnav.constants import CATEGORY_INDEX, ROOM_TARGETS, SUCCESS_DISTANCE
from tsnav.detect.evaluate import reliability_table
from tsnav.detect.oracle import ground_truth, oracle_detections
from tsnav.detect.evaluate import average_precision
from tsnav.detect.quality import (
    detection_gallery,
    main,
    pick_gallery_states,
    reliability_figure,
    scene_targets,
    subset_ap,
    subset_report,
    switch_report,
    switch_report_reference,
)
from tsnav.data.detections import write_detections


def _noisy(det, seed):
    """The oracle table with scores shuffled towards noise (false positives and misses)."""
    rng = np.random.default_rng(seed)
    scores = np.clip(0.6 * det.scores + 0.95 * rng.random(det.scores.shape) ** 4, 0, 1).astype(np.float32)
    return dataclasses.replace(det, scores=scores)


def test_scene_targets(tiny_scenes):
    for s in tiny_scenes:
        t = scene_targets(s)
        present = set(s.categories_present())
        assert set(np.flatnonzero(t)) == {
            c
            for c in present
            if s.room_type not in ROOM_TARGETS or c in [CATEGORY_INDEX[n] for n in ROOM_TARGETS[s.room_type]]
        }


def test_switch_report_by_hand_and_against_reference(tiny_scenes):
    s = tiny_scenes[0]
    gt = ground_truth(s).present
    tgt = np.flatnonzero(scene_targets(s))
    assert len(tgt) >= 2
    det = oracle_detections(s)
    # Perfect scores: every target with a state in view is reached; no false positive at any threshold.
    exact = dataclasses.replace(det, scores=gt.astype(np.float32))
    r = switch_report([s], [exact])
    seen = int(gt[:, tgt].any(axis=0).sum())
    assert r.pairs == len(tgt) and r.reached == r.reached_in_view == seen
    # the pairs episodes ask for have a success state (in view within the success distance): all reached
    askable = int(s.category_visible_within(SUCCESS_DISTANCE)[:, tgt].any(axis=0).sum())
    assert r.episode_pairs == r.episode_reached == askable and r.episode_reach == 1.0
    assert all(v == 0 for v in r.fp_state_any.values()) and all(v == 0 for v in r.fp_pair_target.values())
    # One false positive of 0.8 for the first target in a state where it is not in view.
    i = int(np.flatnonzero(~gt[:, tgt[0]])[0])
    scores = exact.scores.copy()
    scores[i, tgt[0]] = 0.8
    r = switch_report([s], [dataclasses.replace(exact, scores=scores)])
    assert r.fp_state_any[0.7] == pytest.approx(1 / s.num_states) and r.fp_state_any[0.9] == 0
    assert r.fp_pair_target[0.5] == pytest.approx(1 / int((~gt[:, tgt]).sum()))
    assert r.fp_pair_any[0.5] == pytest.approx(1 / int((~gt).sum()))
    # Noisy tables on every scene agree with the slow reference.
    dets = [_noisy(oracle_detections(x), k) for k, x in enumerate(tiny_scenes)]
    fast = switch_report(tiny_scenes, dets)
    ref = switch_report_reference(tiny_scenes, dets)
    assert (fast.pairs, fast.reached, fast.reached_in_view) == (ref["pairs"], ref["reached"], ref["reached_in_view"])
    assert (fast.episode_pairs, fast.episode_reached) == (ref["episode_pairs"], ref["episode_reached"])
    assert 0 < fast.episode_pairs <= fast.pairs and fast.episode_reached <= fast.reached
    assert 0 < fast.fp_state_any[0.5] < 1
    for k in ("fp_state_any", "fp_state_target", "fp_pair_any", "fp_pair_target"):
        for t, v in getattr(fast, k).items():
            assert v == pytest.approx(ref[k][t]), (k, t)
    assert fast.to_json()["reach"] == pytest.approx(fast.reached / fast.pairs)
    with pytest.raises(ValueError, match="do not match"):
        switch_report([tiny_scenes[0]], [dets[1]])


def test_subset_ap_by_hand_and_on_scenes(tiny_scenes):
    # One class, 6 states: in view at 0, 1, 2 (subset: 0 and 2), not in view at 3, 4, 5.
    present = np.array([1, 1, 1, 0, 0, 0], bool)[:, None]
    subset = np.array([1, 0, 1, 0, 0, 0], bool)[:, None]
    scores = np.array([0.9, 0.1, 0.5, 0.6, 0.2, 0.3], np.float32)[:, None]
    # State 1 (in view, outside the subset) is left out: ranking 0.9+, 0.6-, 0.5+, 0.3-, 0.2- -> AP (1 + 2/3) / 2.
    assert subset_ap(scores, present, subset)[0] == pytest.approx((1 + 2 / 3) / 2)
    assert np.isnan(subset_ap(scores, present, np.zeros_like(subset))[0])
    # The whole set as the subset is the plain presence AP; the size buckets partition the positives.
    dets = [_noisy(oracle_detections(x), k) for k, x in enumerate(tiny_scenes)]
    sc = np.concatenate([d.scores for d in dets])
    gt = np.concatenate([ground_truth(x).present for x in tiny_scenes])
    full = subset_ap(sc, gt, np.ones_like(gt))
    c = int(np.argmax(gt.sum(0)))
    assert full[c] == pytest.approx(average_precision(sc[:, c], gt[:, c]))
    rep = subset_report(tiny_scenes, dets)
    assert sum(rep[b]["positives"] for b in ("small", "medium", "large")) == int(gt.sum())
    assert 0 < rep["within 1.5 m"]["positives"] <= int(gt.sum())


def test_figures_and_command(tiny_world, tiny_scenes, tmp_path, capsys):
    dets = [_noisy(oracle_detections(s), k) for k, s in enumerate(tiny_scenes)]
    gt = np.concatenate([ground_truth(s).present for s in tiny_scenes])
    rel = reliability_table(np.concatenate([d.scores for d in dets]), gt)
    p = reliability_figure([("noisy oracle", rel)], tmp_path / "rel.png", title="t")
    assert Image.open(p).size[0] > 500
    picks = pick_gallery_states(tiny_scenes, 2)
    assert picks and all(ground_truth(tiny_scenes[i]).present[j].any() for i, j in picks)
    g = detection_gallery(tiny_scenes, dets, picks, tmp_path / "gal.png", cols=3)
    assert Image.open(g).size[1] > 200
    for s, d in zip(tiny_scenes, dets):
        write_detections(s.path, "noisy", d)
    out = tmp_path / "q"
    split = tiny_scenes[0].meta.get("split", "train")
    assert main(["--data", str(tiny_world), "--name", "noisy", "--split", split, "--out", str(out)]) == 0
    assert (out / f"quality_{split}.json").exists() and (out / f"gallery_{split}.png").exists()
    assert "pairs reaching confidence > 0.7" in capsys.readouterr().out
