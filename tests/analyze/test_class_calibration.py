"""tsnav analyze class-calibration: the Platt fit against a generic optimiser, the identity map leaves a table as it
was, and on a built world the written tables carry the maps and the switch report runs before and after."""

import json

import numpy as np
import pytest
from script_helpers import load_analysis

from tsnav.constants import TARGET_CATEGORIES
from tsnav.data.detections import load_detections
from tsnav.data.reader import list_scenes


@pytest.fixture(scope="module")
def mod():
    return load_analysis("class_calibration")


def test_platt_fit_matches_the_reference(mod):
    rng = np.random.default_rng(0)
    z = rng.normal(0.0, 2.0, 3000)
    y = rng.random(3000) < 1.0 / (1.0 + np.exp(-(1.7 * z + 0.8)))
    for prior in (0.0, 1.0, 50.0):
        a, b = mod.fit_platt(z, y, prior)
        ra, rb = mod.fit_platt_reference(z, y, prior)
        assert a == pytest.approx(ra, abs=1e-4) and b == pytest.approx(rb, abs=1e-4)
    a, b = mod.fit_platt(z, y, 0.0)
    assert a == pytest.approx(1.7, abs=0.2) and b == pytest.approx(0.8, abs=0.2)  # recovers the generating map
    a, b = mod.fit_platt(z[:5], y[:5], 1e6)
    assert a == pytest.approx(1.0, abs=1e-3) and b == pytest.approx(0.0, abs=1e-3)  # a strong prior holds it
    assert np.allclose(mod.sigmoid(np.array([-800.0, 0.0, 800.0])), [0.0, 0.5, 1.0])  # no overflow


@pytest.fixture(scope="module")
def world(tiny_real_learned4):
    return tiny_real_learned4


def test_identity_and_written_tables(mod, world, tmp_path, capsys):
    p = list_scenes(world, "val")[0]
    det = load_detections(p, "learned4")
    same = mod.apply_maps(det, np.tile([1.0, 0.0], (22, 1)), 0.05)
    assert np.allclose(same.scores, det.scores, atol=2e-6)
    assert np.array_equal(same.labels, det.labels) and np.array_equal(same.boxes, det.boxes)
    out = tmp_path / "c.json"
    assert (
        mod.main(
            [
                "--data",
                str(world),
                "--from",
                "learned4",
                "--fit-split",
                "val",
                "--report-split",
                "test",
                "--min-positives",
                "1",
                "--name",
                "lc",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    res = json.loads(out.read_text())
    assert {"val_before", "val_crossfit", "test_before", "test_after", "maps"} <= set(res)
    for q in list_scenes(world):
        t = load_detections(q, "lc")
        assert t.config["class_calibration"]["maps"] == res["maps"]
        a, b = np.array([res["maps"][k] for k in TARGET_CATEGORIES]).T
        src = load_detections(q, "learned4")
        want = mod.sigmoid(mod.logit(src.scores) * a[None, :] + b[None, :])
        assert np.allclose(t.scores, want, atol=1e-3)  # maps rounded to 4 decimals in the JSON
        assert ((t.labels == -1) == ((t.scores < 0.05) | (src.labels == -1))).all()
    capsys.readouterr()
    assert mod.main(["--data", str(world), "--name", "learned4"]) == 2
    assert "--name must differ" in capsys.readouterr().err
    assert mod.main(["--data", str(world / "nope")]) == 2
    assert "no such dataset folder" in capsys.readouterr().err


def test_maps_have_one_row_per_class_of_the_set(mod):
    """The maps follow the world's class set (RoboTHOR's 12 classes, not iTHOR's 22); a fold without rooms keeps
    the identity for every class."""
    from tsnav.constants import class_set

    robo = class_set("robothor12")
    maps = mod.fit_maps([], [], min_positives=1, prior=1.0, size=robo.size)
    assert maps.shape == (12, 2) and np.array_equal(maps, np.tile([1.0, 0.0], (12, 1)))
