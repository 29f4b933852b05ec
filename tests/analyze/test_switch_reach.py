"""tsnav analyze switch-reach: presence tables follow their pixel rule cell by cell, the precision and recall of a
table are the counts of a loop over the cells, and the command evaluates the explorer on each switch of a real room."""

import json
import shutil

import numpy as np
import pytest
from script_helpers import load_analysis

from tsnav.data.detections import Detections, load_detections
from tsnav.data.reader import list_scenes, load_scene
from tsnav.detect.quality import scene_targets
from tsnav.errors import CommandError


@pytest.fixture(scope="module")
def mod():
    return load_analysis("switch_reach")


def test_class_pixels_is_the_largest_instance_of_each_class(mod, tiny_real):
    scene = load_scene(list_scenes(tiny_real)[0])
    px = mod.class_pixels(scene)
    for s in range(0, scene.num_states, 37):
        for c in range(scene.num_categories):
            cols = [o for o in range(len(scene.object_ids)) if scene.object_category[o] == c]
            want = max([max(int(scene.pixels[s, o]), 0) for o in cols], default=0)
            assert px[s, c] == want


def test_presence_table_cell_by_cell(mod):
    rng = np.random.default_rng(0)
    S, C = 30, 22
    oracle = Detections(
        keys=np.array([f"s{i}" for i in range(S)]),
        scores=rng.uniform(0, 1, (S, C)).astype(np.float32),
        labels=np.full((S, C), -1, np.int16),
        boxes=rng.uniform(0, 60, (S, C, 4)).astype(np.float32),
        features=rng.normal(size=(S, C, 4)).astype(np.float16),
        fingerprint="o",
    )
    pixels = rng.integers(0, 50, (S, C)).astype(np.int32)
    t = mod.presence_table(oracle, pixels, 10)
    for i in range(S):
        for c in range(C):
            on = pixels[i, c] >= 10
            assert t.scores[i, c] == (1.0 if on else 0.0)
            assert t.labels[i, c] == (c if on else -1)
            assert np.array_equal(t.boxes[i, c], oracle.boxes[i, c] if on else np.full(4, -1.0, np.float32))
    assert np.array_equal(t.features, oracle.features) and t.fingerprint != oracle.fingerprint
    with pytest.raises(ValueError, match="min_pixels"):
        mod.presence_table(oracle, pixels, 0)
    with pytest.raises(ValueError, match="cells"):
        mod.presence_table(oracle, pixels[:, :2], 10)


def test_precision_and_recall_against_a_cell_loop(mod, tiny_real_learned4):
    scenes = [load_scene(p) for p in list_scenes(tiny_real_learned4)]
    tables = [load_detections(s.path, "learned4") for s in scenes]
    got = mod.cell_precision_recall(scenes, tables, [0.3, 0.7], recall_pixels=10)
    for row in got:
        t = row["threshold"]
        above = true = showing = hit = 0
        for s, d in zip(scenes, tables):
            px = mod.class_pixels(s)
            targets = scene_targets(s)
            for i in range(s.num_states):
                for c in np.flatnonzero(targets):
                    fired = d.scores[i, c] > t
                    above += fired
                    true += fired and px[i, c] > 0
                    showing += px[i, c] >= 10
                    hit += fired and px[i, c] >= 10
        assert (row["cells_above"], row["cells_showing"]) == (above, showing)
        assert row["precision"] == pytest.approx(true / above) and row["recall"] == pytest.approx(hit / showing)
    assert got[0]["recall"] >= got[1]["recall"]  # a lower threshold fires on more cells


def test_command_on_a_real_room(mod, tiny_real_learned4, tmp_path, capsys):
    from tsnav.cli import main

    world = tmp_path / "world"
    shutil.copytree(tiny_real_learned4, world)
    assert main(["detect", "--data", str(world), "--detector", "oracle", "--no-eval", "--quiet"]) == 0
    eps = tmp_path / "eps.json"
    assert main(["episodes", "--data", str(world), "--split", "test", "--per-room-type", "20", "--out", str(eps)]) == 0
    out = tmp_path / "reach.json"
    argv = ["--data", str(world), "--episodes", str(eps), "--detections", "learned4", "--c-target", "0.5,0.7"]
    assert mod.main(argv + ["--min-pixels", "1,200", "--work", str(tmp_path / "work"), "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    switches = [r["switch"] for r in res["rows"]]
    assert switches == [
        "target shows >= 1 px",
        "target shows >= 200 px",
        "oracle score > 0.7",
        "learned4 score > 0.5",
        "learned4 score > 0.7",
    ]
    a, b = res["rows"][0], res["rows"][1]
    # the explorer acts the same until its first switch, and presence-1 fires wherever presence-200 does
    assert a["never_switched"] <= b["never_switched"]
    assert a["metrics"]["ALL"]["episodes"] == 20 and [c["threshold"] for c in res["cells"]] == [0.5, 0.7]
    assert "presence-1: SR" in capsys.readouterr().out
    with pytest.raises(CommandError, match="no such folder"):
        mod.main(["--data", str(tmp_path / "nope"), "--episodes", str(eps), "--work", "w", "--out", str(out)])
