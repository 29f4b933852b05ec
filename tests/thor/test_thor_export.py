"""tsnav scenes in the lineage's layout: the layout check and the 22 x 264 detection export."""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pytest

from tsnav.constants import NUM_CATEGORIES
from tsnav.data import lineage as L
from tsnav.data.reader import SceneFormatError, list_scenes, load_scene
from tsnav.data.thor_export import check_lineage_layout, export_detections_22x264
from tsnav.data.detections import Detections, write_detections


def test_tsnav_scenes_pass_the_lineage_layout_check(tiny_world):
    for p in list_scenes(tiny_world):
        assert check_lineage_layout(p) == [], p.name


@pytest.fixture
def small_copy(tmp_path):
    """A copy of the hand-written two-cell lineage scene with an images.hdf5."""
    from pathlib import Path

    src = Path(__file__).resolve().parents[1] / "fixtures" / "thor" / "two_cells"
    d = tmp_path / "scene"
    shutil.copytree(src, d)
    # the fixture lists the never-seen sofa with no state (for the import); the lineage's maps do not list it
    vis = json.loads((d / "visible_object_map_1.5.json").read_text())
    (d / "visible_object_map_1.5.json").write_text(json.dumps({k: v for k, v in vis.items() if v}))
    keys = [n["id"] for n in json.loads((d / "graph.json").read_text())["nodes"]]
    with h5py.File(d / "images.hdf5", "w") as f:
        for k in keys:
            f.create_dataset(k, data=np.zeros((6, 6, 3), np.uint8))
    assert check_lineage_layout(d) == []
    return d, keys


def _edit_json(path, fn):
    path.write_text(json.dumps(fn(json.loads(path.read_text()))))


def test_layout_check_finds_each_problem(small_copy):
    d, keys = small_copy

    def graph_bad_key(g):
        g["nodes"][0]["id"] = "0.0|0.00|0|0"
        return g

    _edit_json(d / "graph.json", graph_bad_key)
    probs = check_lineage_layout(d)
    assert any("node '0.0|0.00|0|0' is not a state key" in p for p in probs)
    assert any("images.hdf5: dataset '0.00|0.00|0|0' is not a state of graph.json" in p for p in probs)

    def graph_jump(g):
        g["nodes"] = [{"id": k} for k in keys]
        g["links"].append({"source": "0.00|0.00|0|0", "target": "0.25|0.00|90|30"})
        g["directed"] = False
        return g

    _edit_json(d / "graph.json", graph_jump)
    probs = check_lineage_layout(d)
    assert "graph.json: 'directed' must be true (a DiGraph)" in probs
    assert "graph.json: link 0.00|0.00|0|0 -> 0.25|0.00|90|30 is not a single action" in probs

    def fix(g):
        g["links"].pop()
        g["directed"] = True
        return g

    _edit_json(d / "graph.json", fix)
    assert check_lineage_layout(d) == []
    (d / "grid.json").write_text(json.dumps([{"x": 0.0, "y": 0.9, "z": 0.0}]))
    assert "grid.json: state position (0.25, 0.00) of graph.json is missing" in check_lineage_layout(d)
    (d / "grid.json").write_text(json.dumps([{"x": "0", "z": 0}]))
    assert any(p.startswith("grid.json: expected") for p in check_lineage_layout(d))
    (d / "grid.json").write_text(json.dumps([{"x": 0.0, "y": 0.9, "z": 0.0}, {"x": 0.25, "y": 0.9, "z": 0.0}]))
    (d / "visible_object_map_1.5.json").write_text(
        json.dumps({"Television": ["0.00|0.00|90|0"], "Mug|+1.00|+0.90|+0.00": ["9.00|0.00|0|0"]})
    )
    probs = check_lineage_layout(d)
    assert "visible_object_map_1.5.json: object id 'Television' is not 'Type|x|y|z'" in probs
    assert any("state '9.00|0.00|0|0' of Mug|+1.00|+0.90|+0.00 is not a node" in p for p in probs)
    (d / "visible_object_map_1.5.json").write_text("{}")
    with h5py.File(d / "images.hdf5", "a") as f:
        del f[keys[1]]
        f.create_dataset(keys[1] + "x", data=np.zeros((6, 6, 3), np.uint8))
        del f[keys[2]]
        f.create_dataset(keys[2], data=np.zeros((6, 6), np.float32))
    probs = check_lineage_layout(d)
    assert "images.hdf5: no dataset for 1 of 32 states" in probs
    assert f"images.hdf5: '{keys[2]}' holds float32 (6, 6), expected uint8 (H, W, 3)" in probs
    with h5py.File(d / "det_feature_categories.hdf5", "w") as f:
        f.create_dataset(keys[0], data=np.zeros((22, 264), np.float64))
    assert (
        f"det_feature_categories.hdf5: '{keys[0]}' holds float64 (22, 264), expected float32 (22, 264)"
        in check_lineage_layout(d)
    )
    raw = (d / "images.hdf5").read_bytes()
    (d / "images.hdf5").write_bytes(raw[:100])
    assert any(p.startswith("images.hdf5: unreadable HDF5") for p in check_lineage_layout(d))
    (d / "graph.json").unlink()
    assert "graph.json: missing file" in check_lineage_layout(d)


def _det256(scene, seed=0):
    """A 256-d detection table for ``scene`` (as a DETR-feature detector would write), from the renders."""
    rng = np.random.default_rng(seed)
    S = scene.num_states
    labels = np.full((S, NUM_CATEGORIES), -1, np.int16)
    boxes = np.full((S, NUM_CATEGORIES, 4), -1, np.float32)
    for j, c in enumerate(scene.object_category):
        if c >= 0:
            seen = scene.pixels[:, j] > 0
            labels[seen, c] = c
            boxes[seen, c] = scene.boxes[seen, j]
    scores = np.where(labels >= 0, rng.uniform(0.3, 1, labels.shape), rng.uniform(0, 0.05, labels.shape))
    feats = rng.standard_normal((S, NUM_CATEGORIES, 256)).astype(np.float16)
    return Detections(
        keys=scene.keys,
        scores=scores.astype(np.float32),
        labels=labels,
        boxes=boxes,
        features=feats,
        detector="test",
        image_size=scene.image_size,
    )


def test_export_detections_round_trip(tiny_scenes, tmp_path):
    s = tiny_scenes[0]
    det = _det256(s)
    write_detections(tmp_path, "detr", det)
    out = export_detections_22x264(s.path, tmp_path / "detections_detr.hdf5", tmp_path / "detr_features_22cls.hdf5")
    with h5py.File(out, "r") as f:
        assert sorted(f.keys()) == s.keys.tolist()
        assert all(f[k].dtype == np.float32 and f[k].shape == (22, 264) for k in s.keys[:20])
        r = f[s.keys[0]][()]
    assert set(np.unique(r[:, 257])) <= set(range(1, 24))  # 1..22 detections, 23 "no object"; never 0
    back = L.read_detections_22x264(out, image_size=300)
    at64 = L.table_from_22x264(back.keys, L.table_to_22x264(back, None), image_size=300, out_size=64, own_rows=True)
    for a in ("keys", "scores", "labels", "features", "boxes"):
        assert np.array_equal(getattr(at64, a), getattr(det, a)), a
    assert np.array_equal(back.boxes[back.labels >= 0], det.boxes[det.labels >= 0] * np.float32(300 / 64))
    # the copy in the scene's layout passes the layout check (written beside a copy of the scene)
    d = tmp_path / "scene"
    shutil.copytree(s.path, d)
    shutil.copy(out, d / "detr_features_22cls.hdf5")
    assert check_lineage_layout(d) == []


def test_export_detections_errors(tiny_scenes, tmp_path):
    s = tiny_scenes[0]
    from tsnav.detect.oracle import oracle_detections

    write_detections(tmp_path, "oracle", oracle_detections(s))
    # tsnav's own (64-d) detector is accepted: its features are zero-padded to 256
    out = export_detections_22x264(s.path, tmp_path / "detections_oracle.hdf5", tmp_path / "ok.hdf5")
    back = L.read_detections_22x264(out, image_size=300)
    assert back.features.shape[2] == oracle_detections(s).features.shape[2] < 256
    with h5py.File(out, "r") as f:
        assert f[s.keys[0]].shape == (22, 264)
    with pytest.raises(SceneFormatError, match="missing file"):
        export_detections_22x264(s.path, "detections_nope.hdf5", tmp_path / "x.hdf5")
    other = tiny_scenes[1]
    write_detections(tmp_path, "other", _det256(other))
    with pytest.raises(SceneFormatError, match=r"is not in scene"):
        export_detections_22x264(s.path, tmp_path / "detections_other.hdf5", tmp_path / "x.hdf5")
    assert not (tmp_path / "x.hdf5").exists() and not list(tmp_path.glob(".x.hdf5*"))


def test_thor_check_and_export_commands(tiny_scenes, tmp_path, capsys):
    from tsnav.cli import main

    s = tiny_scenes[0]
    write_detections(tmp_path, "detr", _det256(s))
    out = tmp_path / "t.hdf5"
    assert (
        main(
            [
                "thor",
                "export-detections",
                str(s.path),
                "--detections",
                str(tmp_path / "detections_detr.hdf5"),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert f"wrote {out}" in capsys.readouterr().out
    assert main(["thor", "check", str(s.path)]) == 0
    assert capsys.readouterr().out.strip() == f"{s.path}: ok"
    bad = tmp_path / "bad"
    bad.mkdir()
    assert main(["thor", "check", str(bad)]) == 1
    assert "graph.json: missing file" in capsys.readouterr().out
    assert main(["thor", "export-detections", str(s.path), "--detections", "detections_missing.hdf5"]) == 2
    err = capsys.readouterr().err.strip()
    assert "missing file" in err and "\n" not in err
    assert load_scene(s.path).num_states == s.num_states  # the shared scene was not touched
