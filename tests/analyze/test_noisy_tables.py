"""``tsnav analyze noisy-tables`` (issue 23 analysis): tables of the shipped detector on noisy frames for one split and
the clean tables of the others under the new name. With no noise it writes exactly the shipped detector's own table;
with noise it is the same on every run and records the noise; bad input gets one line."""

import numpy as np
import pytest

from tsnav.data.detections import load_detections
from tsnav.data.reader import list_scenes
from script_helpers import load_analysis

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _script():
    return load_analysis("noisy_tables")


@pytest.fixture(scope="module")
def world(tiny_real_learned4):
    return tiny_real_learned4


def test_noisy_tables(world, capsys):
    mod = _script()
    train = list_scenes(world, "train")
    others = [p for p in list_scenes(world) if p not in train]
    assert train and others
    assert mod.main(["--data", str(world), "--name", "n0", "--sigma", "0", "--workers", "1"]) == 0
    for p in train + others:  # no noise: the shipped detector's own table, config aside
        a, b = load_detections(p, "learned4"), load_detections(p, "n0")
        for k in ("keys", "scores", "labels", "boxes", "features"):
            assert np.array_equal(getattr(a, k), getattr(b, k)), (p.name, k)
        assert b.fingerprint == a.fingerprint
    assert load_detections(train[0], "n0").config["frame_noise"]["sigma"] == 0
    assert "frame_noise" not in load_detections(others[0], "n0").config  # the other splits' clean tables
    for name in ("n16a", "n16b"):
        assert mod.main(["--data", str(world), "--name", name, "--sigma", "16", "--workers", "1"]) == 0
    a, b, clean = (load_detections(train[0], n) for n in ("n16a", "n16b", "learned4"))
    assert np.array_equal(a.scores, b.scores) and np.array_equal(a.boxes, b.boxes)  # the same noise every run
    assert not np.array_equal(a.scores, clean.scores) and a.config["frame_noise"]["sigma"] == 16
    assert np.array_equal(load_detections(others[0], "n16a").scores, load_detections(others[0], "learned4").scores)
    capsys.readouterr()
    assert mod.main(["--data", str(world), "--name", "learned4", "--sigma", "16"]) == 2
    assert "--name must differ" in capsys.readouterr().err
    assert mod.main(["--data", str(world), "--name", "x", "--sigma", "-1"]) == 2
    assert "--sigma must be >= 0" in capsys.readouterr().err
    assert mod.main(["--data", str(world), "--name", "x", "--sigma", "1", "--from", "nope"]) == 2
    assert "has no detections_nope.hdf5" in capsys.readouterr().err
