"""tsnav analyze recall-by-size: the vectorised counts against a state-by-state reference, and end to end on a built
world, a table scoring exactly the in-view states of one band comes back at 100 % there and 0 % elsewhere; the
picture's shape; bad input in one line."""

import json
import shutil

import numpy as np
import pytest
from script_helpers import load_analysis

from tsnav.data.detections import Detections, write_detections
from tsnav.data.reader import list_scenes, load_scene
from tsnav.detect.oracle import ground_truth


@pytest.fixture(scope="module")
def mod():
    return load_analysis("recall_by_size")


@pytest.fixture(scope="module")
def world(tiny_world, tmp_path_factory):
    root = tmp_path_factory.mktemp("rbs")
    for p in list_scenes(tiny_world):
        shutil.copytree(p, root / p.name, ignore=shutil.ignore_patterns("detections_*", "features_*"))
    return root


def test_counts_match_the_reference(mod):
    rng = np.random.default_rng(0)
    for _ in range(20):
        S, C = rng.integers(1, 60), rng.integers(1, 9)
        present = rng.random((S, C)) < 0.4
        pixels = np.where(present, rng.integers(1, 1000, (S, C)), 0)
        scores = rng.random((S, C)).astype(np.float32)
        edges = sorted(rng.choice(np.arange(1, 900), rng.integers(1, 5), replace=False).tolist())
        np.testing.assert_array_equal(
            mod.recall_counts(present, pixels, scores, edges, 0.5),
            mod.recall_counts_reference(present, pixels, scores, edges, 0.5),
        )
    assert mod.band_labels([100, 200]) == ["<100", "100-200", ">=200"]


def _table(scene, scores):
    S, C = scores.shape
    labels = np.where(scores > 0, np.arange(C)[None, :], -1).astype(np.int16)
    boxes = np.where((labels >= 0)[..., None], ground_truth(scene).boxes, -1.0).astype(np.float32)
    return Detections(
        keys=scene.keys,
        scores=scores.astype(np.float32),
        labels=labels,
        boxes=boxes,
        features=np.zeros((S, C, 4), np.float16),
        detector="test",
        fingerprint="banded",
        image_size=scene.image_size,
        class_set=scene.class_set.name,
    )


@pytest.fixture(scope="module")
def totals(world):
    """Tables 'banded' (0.9 exactly where a class shows 20-79 px) and 'none' (nothing scored) in the train scenes;
    the ground truth's in-view states per class in the bands <20, 20-79, >=80."""
    totals = {}
    for p in list_scenes(world, split="train"):
        scene = load_scene(p)
        gt = ground_truth(scene)
        band = gt.present & (gt.pixels >= 20) & (gt.pixels < 80)
        write_detections(p, "banded", _table(scene, np.where(band, 0.9, 0.0)))
        write_detections(p, "none", _table(scene, np.zeros(gt.present.shape)))
        for c, name in enumerate(scene.class_set.categories):
            n = totals.setdefault(name, [0, 0, 0])
            n[0] += int((gt.present[:, c] & (gt.pixels[:, c] < 20)).sum())
            n[1] += int(band[:, c].sum())
            n[2] += int((gt.present[:, c] & (gt.pixels[:, c] >= 80)).sum())
    return totals


def test_a_banded_table_end_to_end(mod, world, totals, tmp_path, capsys):
    """'banded' comes back at 100 % in its band and 0 % in the others, 'none' at 0 %; the states counted are the
    ground truth's."""
    edges = [20, 80]
    out, png = tmp_path / "rbs.json", tmp_path / "rbs.png"
    argv = ["--data", str(world), "--split", "train", "--tables", "banded", "none", "--bands", "20,80"]
    cls = max(totals, key=lambda k: totals[k][1])
    assert totals[cls][1] > 0
    argv += ["--json", str(out), "--picture", str(png), "--class", cls, "--examples", "3", "--min-pixels", "20"]
    assert mod.main(argv) == 0
    doc = json.loads(out.read_text())
    assert doc["bands"] == edges and doc["tables"] == ["banded", "none"]
    for name, c in doc["classes"].items():
        assert [row[0] for row in c["bands"]] == totals[name]
        assert [row[1] for row in c["bands"]] == [0, totals[name][1], 0]
        assert all(row[2] == 0 for row in c["bands"])
    assert set(doc["classes"]) == {k for k, v in totals.items() if sum(v)}
    printed = capsys.readouterr().out
    assert f"| {cls} |" in printed and f"{totals[cls][1]}: 100 / 0" in printed
    from PIL import Image

    with Image.open(png) as im:  # three states, a column per table, each 256 px with its caption
        assert im.size == (2 * 256, 3 * (256 + 30))


def totals_class(totals) -> str:
    return max(totals, key=lambda k: totals[k][1])


def test_bad_input_is_one_line(mod, world, totals, tmp_path):
    from tsnav.errors import CommandError

    base = ["--data", str(world), "--split", "train", "--tables", "banded"]
    for argv, msg in (
        (["--data", str(tmp_path / "none"), "--tables", "x"], "no such world folder"),
        (base[:4] + ["--tables", "missing"], "no detections_missing.hdf5"),
        (base + ["--bands", "a,b"], "--bands a,b"),
        (base + ["--bands", "0,10"], "positive pixel counts"),
        (base + ["--picture", str(tmp_path / "p.png")], "give --class NAME"),
        (base + ["--frames", "other=" + str(world)], "TABLE one of --tables"),
        (base + ["--frames", "banded=" + str(tmp_path / "no")], "no such folder"),
        (base + ["--picture", str(tmp_path / "p.png"), "--class", "Nothing"], "not a class"),
        (
            base
            + ["--picture", str(tmp_path / "p.png"), "--class", totals_class(totals), "--frames", f"banded={tmp_path}"],
            "no complete scene",
        ),
    ):
        with pytest.raises(CommandError, match=msg):
            mod.main(argv)
    assert not (tmp_path / "p.png").exists()
