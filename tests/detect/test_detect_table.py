"""The detections_<name>.hdf5 table: round trip, validation, installing into a SceneBank."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tsnav.constants import NUM_CATEGORIES
from tsnav.detect.oracle import oracle_detections
from tsnav.data.detections import Detections, detections_path, load_detections, load_scene_detections, write_detections


def _random_table(n: int = 7, dim: int = 5, seed: int = 0) -> Detections:
    rng = np.random.default_rng(seed)
    keys = np.array(sorted(f"{i * 0.25:.2f}|0.00|0|0" for i in range(n)))
    scores = rng.random((n, NUM_CATEGORIES)).astype(np.float32)
    labels = np.where(scores > 0.5, np.arange(NUM_CATEGORIES)[None], -1)
    boxes = np.where(labels[..., None] >= 0, rng.uniform(0, 63, (n, NUM_CATEGORIES, 4)), -1)
    return Detections(
        keys,
        scores,
        labels,
        boxes,
        rng.normal(size=(n, NUM_CATEGORIES, dim)),
        detector="test",
        config={"a": 1, "b": [1, 2]},
        fingerprint="fp-1",
        image_size=64,
    )


def test_round_trip(tmp_path):
    det = _random_table()
    path = write_detections(tmp_path, "mine", det)
    assert path == detections_path(tmp_path, "mine") == tmp_path / "detections_mine.hdf5"
    assert [p.name for p in tmp_path.iterdir()] == ["detections_mine.hdf5"]  # no temp file left
    back = load_detections(tmp_path, "mine")
    np.testing.assert_array_equal(back.keys, det.keys)
    np.testing.assert_array_equal(back.scores, det.scores)
    np.testing.assert_array_equal(back.labels, det.labels)
    np.testing.assert_array_equal(back.boxes, det.boxes)
    np.testing.assert_array_equal(back.features, det.features)
    assert back.scores.dtype == np.float32 and back.labels.dtype == np.int16
    assert back.boxes.dtype == np.float32 and back.features.dtype == np.float16
    assert (back.detector, back.config, back.fingerprint, back.image_size) == ("test", det.config, "fp-1", 64)
    rows = back.rows()
    assert rows.shape == (7, NUM_CATEGORIES, 6)
    np.testing.assert_array_equal(rows[..., 0], det.scores)
    np.testing.assert_array_equal(rows[..., 1], det.labels)
    np.testing.assert_array_equal(rows[..., 2:], det.boxes)


def test_validation_errors(tmp_path):
    det = _random_table()
    with pytest.raises(ValueError, match="scores must have shape"):
        Detections(det.keys, det.scores[:, :3], det.labels, det.boxes, det.features)
    with pytest.raises(ValueError, match=r"in \[0, 1\]"):
        Detections(det.keys, det.scores + 1, det.labels, det.boxes, det.features)
    bad = det.labels.copy()
    bad[0, 0] = 5
    with pytest.raises(ValueError, match="labels"):
        Detections(det.keys, det.scores, bad, det.boxes, det.features)
    with pytest.raises(ValueError, match="sorted"):
        write_detections(tmp_path, "x", dataclasses.replace(det, keys=det.keys[::-1].copy()))
    with pytest.raises(ValueError, match="detector name"):
        write_detections(tmp_path, "a/b", det)
    with pytest.raises(FileNotFoundError, match="tsnav detect"):
        load_detections(tmp_path, "absent")
    (tmp_path / "detections_junk.hdf5").write_text("not hdf5")
    with pytest.raises(ValueError, match="unreadable"):
        load_detections(tmp_path, "junk")


def test_oracle_tables_follow_scene_keys_and_install_into_bank(tiny_scenes, tmp_path):
    from tsnav.sim.batch import SceneBank

    scenes = []
    for s in tiny_scenes[:3]:
        d = tmp_path / s.name
        d.mkdir()
        write_detections(d, "oracle", oracle_detections(s))
        scenes.append(dataclasses.replace(s, path=d))
    bank = SceneBank(scenes, cache=False)
    det = bank.install_detections("oracle")
    assert det.num_states == bank.num_states
    np.testing.assert_array_equal(det.keys, bank.keys)
    for i, s in enumerate(scenes):
        part = load_detections(s.path, "oracle")
        np.testing.assert_array_equal(part.keys, s.keys)
        sl = slice(bank.offsets[i], bank.offsets[i + 1])
        np.testing.assert_array_equal(bank.confidence[sl], part.scores)
        np.testing.assert_array_equal(bank.detections[sl], part.rows())
    # The oracle is confident only where the class is in frame (ground truth of the bank).
    assert not (bank.stage_mask & ~bank.in_frame).any()
    assert bank.stage_mask.any()

    # A table whose states do not match its scene is refused with a one-line reason.
    other = dataclasses.replace(scenes[0], path=scenes[1].path)
    with pytest.raises(ValueError, match="do not match scene"):
        load_scene_detections([other], "oracle")
