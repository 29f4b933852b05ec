"""The lineage's format pieces: derived floor, object ids, and the 22 x 264 detection table."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import shapely

from tsnav.constants import NUM_CATEGORIES
from tsnav.data import lineage as L
from tsnav.data.reader import SceneFormatError
from tsnav.data.detections import Detections


def test_parse_object_id_ai2thor_forms():
    assert L.parse_object_id("Fridge|-02.10|+00.00|+01.07")[0] == "Fridge"
    assert np.allclose(L.parse_object_id("Fridge|-02.10|+00.00|+01.07")[1], [-2.1, 0.0, 1.07])
    assert np.allclose(L.parse_object_id("Bowl|+0.31|+0.92|-2.40")[1], [0.31, 0.92, -2.4])
    t, p = L.parse_object_id("Apple|+01.00|+00.90|-00.30|AppleSliced_1")
    assert t == "Apple" and np.allclose(p, [1.0, 0.9, -0.3])
    assert L.parse_object_id("Floor") == ("Floor", None)


def test_derive_floor_hand_checked():
    # two neighbours: one 0.5 x 0.25 rectangle
    fl = L.derive_floor(np.array([[0.0, 0.0], [0.25, 0.0]]))
    assert len(fl) == 1 and shapely.Polygon(fl[0]).area == pytest.approx(0.125)
    assert np.allclose(fl[0].min(0), [-0.125, -0.125]) and np.allclose(fl[0].max(0), [0.375, 0.125])
    # diagonal neighbours only touch at a corner: two squares
    assert len(L.derive_floor([{"x": 0.0, "y": 0.9, "z": 0.0}, {"x": 0.25, "y": 0.9, "z": 0.25}])) == 2
    # a ring of 8 cells around a blocked centre: the hole (furniture) is filled -> 9 cells
    ring = np.array([[x, z] for x in (0, 0.25, 0.5) for z in (0, 0.25, 0.5) if (x, z) != (0.25, 0.25)])
    fl = L.derive_floor(ring)
    assert len(fl) == 1 and shapely.Polygon(fl[0]).area == pytest.approx(9 * 0.0625)
    with pytest.raises(ValueError, match="no reachable positions"):
        L.derive_floor(np.zeros((0, 2)))


def test_derived_floor_covers_every_reachable_position(tiny_scenes):
    for s in tiny_scenes:
        pos = np.unique(np.stack([s.x, s.z], 1).astype(np.float64), axis=0)
        floor = shapely.union_all([shapely.Polygon(p) for p in L.derive_floor(pos)])
        assert shapely.contains_xy(floor, pos[:, 0], pos[:, 1]).all(), s.name
        # with a margin of half a cell, and no more than the cells plus filled holes
        assert shapely.contains_xy(floor, pos[:, 0] + 0.12, pos[:, 1] - 0.12).all()
        assert floor.area >= len(pos) * 0.0625 - 1e-9
        # inside the scene's own floor (the reachable grid keeps 0.2 m from the walls)
        world = shapely.union_all([shapely.Polygon(p) for p in s.floor])
        assert world.buffer(1e-6).contains(floor), s.name


def _table(S=7, seed=0, image_size=64):
    rng = np.random.default_rng(seed)
    present = rng.random((S, NUM_CATEGORIES)) < 0.4
    labels = np.where(present, np.arange(NUM_CATEGORIES)[None, :], -1).astype(np.int16)
    scores = np.where(present, rng.uniform(0.05, 1, (S, NUM_CATEGORIES)), rng.uniform(0, 0.05, (S, NUM_CATEGORIES)))
    x0 = rng.integers(0, 40, (S, NUM_CATEGORIES, 2))
    boxes = np.concatenate([x0, x0 + rng.integers(0, 20, (S, NUM_CATEGORIES, 2))], -1).astype(np.float32)
    boxes[~present] = -1
    feats = rng.standard_normal((S, NUM_CATEGORIES, 256)).astype(np.float16)
    keys = np.array(sorted(f"{0.25 * i:.2f}|0.00|0|0" for i in range(S)))
    return Detections(
        keys=keys, scores=scores.astype(np.float32), labels=labels, boxes=boxes, features=feats, image_size=image_size
    )


def test_22x264_columns_hand_checked(tmp_path):
    det = _table()
    path = L.write_detections_22x264(tmp_path / "detr_features_22cls.hdf5", det)
    with h5py.File(path, "r") as f:
        assert sorted(f.keys()) == det.keys.tolist()
        k = det.keys[3]
        row = f[k][()]
        assert row.dtype == np.float32 and row.shape == (22, 264)
    s = 3
    c = int(np.flatnonzero(det.labels[s] >= 0)[0])
    n = int(np.flatnonzero(det.labels[s] < 0)[0])
    assert np.array_equal(row[c, :256], det.features[s, c].astype(np.float32))
    assert row[c, 256] == det.scores[s, c] and row[c, 257] == c + 1
    # no kept detection: DETR's "no object" label 23 (never 0, which IOM's reader files under the last class),
    # a box inside the frame (not the -1 marker rescaled to -4.6875), the class's score and feature
    assert row[n, 257] == 23 and (row[n, 260:264] == 0).all()
    assert row[n, 256] == det.scores[s, n] and np.array_equal(row[n, :256], det.features[s, n].astype(np.float32))
    assert (row[:, 257] != 0).all() and (row[:, 260:264] >= 0).all()
    assert (row[:, 258:260] == 0).all()
    assert np.allclose(row[c, 260:264], det.boxes[s, c] * 300 / 64)


def test_22x264_round_trip_exact(tmp_path):
    det = _table(S=9, seed=3)
    path = L.write_detections_22x264(tmp_path / "t.hdf5", det)  # boxes rescaled 64 -> 300
    back = L.read_detections_22x264(path, image_size=300)
    assert back.image_size == 300
    assert np.array_equal(back.keys, det.keys)
    assert np.array_equal(back.labels, det.labels)
    assert np.array_equal(back.scores, det.scores)
    assert np.array_equal(back.features, det.features)
    kept = det.labels >= 0
    assert np.array_equal(back.boxes[kept], (det.boxes[kept].astype(np.float64) * 300 / 64).astype(np.float32))
    assert (back.boxes[~kept] == -1).all()
    exact = L.table_from_22x264(det.keys, L.table_to_22x264(det, 300), image_size=300, out_size=64, own_rows=True)
    assert np.array_equal(exact.boxes, det.boxes)  # 300/64 = 75/16: exact both ways
    same = L.table_from_22x264(det.keys, L.table_to_22x264(det, None), image_size=64, own_rows=True)
    for a in ("scores", "labels", "boxes", "features"):
        assert np.array_equal(getattr(same, a), getattr(det, a)), a


def test_22x264_pads_small_features_and_reads_them_back(tmp_path):
    """tsnav's 64-d detector features: zero-padded to the lineage's 256 columns, read back at 64."""
    det = _table(S=5, seed=2)
    small = Detections(
        keys=det.keys,
        scores=det.scores,
        labels=det.labels,
        boxes=det.boxes,
        features=det.features[..., :64],
        image_size=64,
    )
    rows = L.table_to_22x264(small)
    assert rows.shape == (5, 22, 264) and (rows[:, :, 64:256] == 0).all()
    assert np.array_equal(rows[:, :, :64], small.features.astype(np.float32))
    back = L.read_detections_22x264(L.write_detections_22x264(tmp_path / "d.hdf5", small), image_size=300)
    assert back.features.shape == (5, 22, 64) and np.array_equal(back.features, small.features)
    assert np.array_equal(back.scores, small.scores) and np.array_equal(back.labels, small.labels)


def test_22x264_empty_rows_are_not_filed_under_a_class():
    """The lineage's pretraining reader gathers ``table[label - 1] = best row of label`` for labels 0..22: a row
    labelled 0 would land in row -1 (Toaster). Rows tsnav writes without a detection carry 23 and are skipped."""
    det = _table(S=6, seed=5)
    rows = L.table_to_22x264(det)
    for s in range(len(rows)):
        gathered = np.zeros((22, 264), np.float32)
        for cate_id in range(23):  # the lineage's loop, as its readers write it
            idx = rows[s, :, 257] == cate_id
            if idx.sum() > 0:
                gathered[cate_id - 1] = rows[s][idx][rows[s, idx, 256].argmax()]
        filed = gathered[:, 257].astype(int)
        assert np.array_equal(filed, np.where(det.labels[s] >= 0, det.labels[s] + 1, 0))


def test_22x264_best_row_per_class_like_the_lineage():
    """DETR-style tables with many rows: the highest-scoring row of each label wins; 'no object' is ignored."""
    rows = np.zeros((2, 5, 264), np.float32)
    rows[:, :, 257] = 23  # no object
    rows[:, :, 256] = 0.99
    rows[0, 1, [256, 257]] = [0.4, 5]  # category 4, weaker
    rows[0, 3, [256, 257]] = [0.8, 5]  # category 4, best
    rows[0, 3, 260:264] = [10, 20, 30, 40]
    rows[0, 3, :256] = 0.5
    rows[1, 0, [256, 257]] = [0.7, 22]  # Toaster
    det = L.table_from_22x264(["a", "b"], rows)
    assert det.labels[0, 4] == 4 and det.scores[0, 4] == np.float32(0.8)
    assert np.array_equal(det.boxes[0, 4], [10, 20, 30, 40]) and (det.features[0, 4] == np.float16(0.5)).all()
    assert det.labels[1, 21] == 21 and det.scores[1, 21] == np.float32(0.7)
    assert (det.labels >= 0).sum() == 2
    assert det.scores.sum() == pytest.approx(1.5)  # the 0.99 'no object' rows count for nothing
    assert (det.boxes[det.labels < 0] == -1).all()


def test_22x264_refuses_other_feature_sizes_and_bad_files(tmp_path):
    det = _table()
    big = Detections(
        keys=det.keys,
        scores=det.scores,
        labels=det.labels,
        boxes=det.boxes,
        features=np.concatenate([det.features, det.features], -1),
        image_size=64,
    )
    with pytest.raises(ValueError, match="256-d"):
        L.table_to_22x264(big)
    with pytest.raises(SceneFormatError, match="missing file"):
        L.read_detections_22x264(tmp_path / "nope.hdf5")
    bad = tmp_path / "bad.hdf5"
    with h5py.File(bad, "w") as f:
        f.create_dataset("0.00|0.00|0|0", data=np.zeros((22, 100), np.float32))
    with pytest.raises(SceneFormatError, match=r"expected an \(R, 264\) table"):
        L.read_detections_22x264(bad)
    good = L.write_detections_22x264(tmp_path / "good.hdf5", det)
    trunc = tmp_path / "trunc.hdf5"
    trunc.write_bytes(good.read_bytes()[:2000])
    with pytest.raises(SceneFormatError, match="unreadable HDF5") as e:
        L.read_detections_22x264(trunc)
    assert "\n" not in str(e.value)
