"""Import of the lineage's AI2-THOR offline data (``AI2Thor_offline_data_2.0.2`` layout) as tsnav scenes."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import shapely

from tsnav.constants import NUM_CATEGORIES, TARGET_CATEGORIES
from tsnav.data.reader import SceneFormatError, load_scene
from tsnav.data.thor_export import check_lineage_layout
from tsnav.data.thor_import import ImportConfig, import_lineage_scene
from tsnav.sim.paths import distance_fields, multi_source_bfs

from thor_standin import detections_22x264, write_lineage_scene

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "thor" / "two_cells"
KEY = re.compile(r"^-?\d+\.\d\d\|-?\d+\.\d\d\|(0|45|90|135|180|225|270|315)\|(0|30)$")


@pytest.fixture(scope="module")
def original(tiny_world):
    """The smallest tiny_world scene."""
    return min(
        (load_scene(p) for p in sorted(tiny_world.iterdir()) if (p / "COMPLETE").exists()), key=lambda s: s.num_states
    )


@pytest.fixture(scope="module")
def lineage_dir(original, tmp_path_factory):
    return write_lineage_scene(original.path, tmp_path_factory.mktemp("lineage") / original.name)


@pytest.fixture(scope="module")
def imported(lineage_dir, tmp_path_factory):
    dst = tmp_path_factory.mktemp("imported") / lineage_dir.name
    stats = import_lineage_scene(lineage_dir, dst)
    assert not stats.skipped and stats.detections and not stats.distances
    return load_scene(dst)


def _vis_rule(scene):
    """The lineage's success rule: the scene with its distances forgotten (visibility map alone)."""
    return dataclasses.replace(scene, distance=np.full_like(scene.distance, np.nan)).category_visible_within()


def test_lineage_layout_hand_checked(lineage_dir, original):
    g = json.loads((lineage_dir / "graph.json").read_text())
    assert set(g) == {"directed", "multigraph", "graph", "nodes", "links"}
    assert g["directed"] is True and g["multigraph"] is False
    assert all(set(n) == {"id"} and KEY.match(n["id"]) for n in g["nodes"])
    assert all(set(e) == {"source", "target"} for e in g["links"])
    assert "0.00|0.00|0|0" in {n["id"] for n in g["nodes"]} or any(n["id"].endswith("|315|30") for n in g["nodes"])
    grid = json.loads((lineage_dir / "grid.json").read_text())
    assert isinstance(grid, list) and all(set(p) == {"x", "y", "z"} and isinstance(p["x"], float) for p in grid)
    vis = json.loads((lineage_dir / "visible_object_map_1.5.json").read_text())
    assert all(isinstance(k, str) and len(k.split("|")) == 4 and isinstance(v, list) for k, v in vis.items())
    with h5py.File(lineage_dir / "images.hdf5", "r") as f:
        assert sorted(f.keys()) == sorted(n["id"] for n in g["nodes"])
        d = f[g["nodes"][0]["id"]]
        assert d.dtype == np.uint8 and d.shape == (64, 64, 3)
    with h5py.File(lineage_dir / "det_feature_categories.hdf5", "r") as f:
        d = f[g["nodes"][0]["id"]]
        assert d.dtype == np.float32 and d.shape == (22, 264)
    assert check_lineage_layout(lineage_dir) == []


def test_load_scene_directly_on_a_lineage_folder(lineage_dir, original):
    s = load_scene(lineage_dir)
    assert np.array_equal(s.keys, original.keys) and np.array_equal(s.next_state, original.next_state)
    assert s.floor == [] and np.isnan(s.distance).all()
    assert np.array_equal(s.category_visible_within(), _vis_rule(original))


def test_import_gives_the_same_simulator(imported, original):
    assert (imported.path / "COMPLETE").exists()
    assert np.array_equal(imported.keys, original.keys)
    assert np.array_equal(imported.next_state, original.next_state)
    # the lineage's map lists only objects seen from some state; those are the objects an import knows
    seen = original.object_ids[original.visible.any(axis=0)].tolist()
    assert imported.object_ids.tolist() == sorted(seen)
    # success states: the lineage's rule (visibility map alone), as the original under that rule
    succ = imported.category_visible_within()
    assert np.array_equal(succ, _vis_rule(original))
    assert succ.any()
    # shortest paths to every category's success states
    d_imp = distance_fields(imported.next_state, succ)
    d_org = distance_fields(original.next_state, _vis_rule(original))
    assert np.array_equal(d_imp, d_org)
    for c in imported.categories_present():
        assert np.array_equal(multi_source_bfs(imported.next_state, succ[:, c]), d_org[:, c])
    # the batched simulator takes it as it is
    from tsnav.sim.batch import SceneBank

    bank = SceneBank([imported])
    assert bank.next_state.shape == (imported.num_states, 6)


def test_import_writes_floor_objects_and_detections(imported, original, lineage_dir):
    meta = imported.meta
    assert meta["format"] == "tsnav-scene" and meta["source"]["format"] == "ai2thor-offline-data"
    assert meta["room_type"] == original.room_type and meta["image_size"] == 64
    floor = shapely.union_all([shapely.Polygon(p) for p in imported.floor])
    assert shapely.contains_xy(floor, imported.x.astype(float), imported.z.astype(float)).all()
    by_id = {o["objectId"]: o for o in meta["objects"]}
    seen = set(original.object_ids[original.visible.any(axis=0)].tolist())
    for o in original.meta["objects"]:
        if o["objectId"] not in seen:
            continue
        rec = by_id[o["objectId"]]
        assert rec["objectType"] == o["objectType"]
        assert rec["position"]["x"] == pytest.approx(float(o["objectId"].split("|")[1]))
    assert set(np.asarray(imported.object_category)[imported.object_category >= 0]) <= set(range(NUM_CATEGORIES))
    # detections in the detect stage's layout, equal to the hand-built lineage rows
    from tsnav.data.detections import load_detections, load_scene_detections

    det = load_detections(imported.path, "lineage")
    assert np.array_equal(det.keys, imported.keys) and det.image_size == 300
    rows = detections_22x264(original)
    lab = rows[:, :, 257].astype(int)
    found = lab == np.arange(1, 23)[None, :]
    assert np.array_equal(det.labels >= 0, found)
    assert np.array_equal(det.scores[found], rows[:, :, 256][found])
    assert np.array_equal(det.boxes[found], rows[:, :, 260:264][found])
    assert np.array_equal(det.features.astype(np.float32), rows[:, :, :256] * found[..., None])
    assert (det.scores[~found] == 0).all() and (det.boxes[~found] == -1).all()
    assert load_scene_detections([imported], "lineage").num_states == imported.num_states
    # the lineage's own files are still there for the lineage's code
    assert (imported.path / "det_feature_categories.hdf5").exists() and (imported.path / "images.hdf5").exists()
    assert check_lineage_layout(imported.path) == []


def test_import_with_raw_metadata_derives_distances(original, tmp_path):
    src = write_lineage_scene(original.path, tmp_path / "lin" / original.name, metadata=True, detections=False)
    import_lineage_scene(src, tmp_path / "imp" / original.name, ImportConfig(copy_mode="none"))
    s = load_scene(tmp_path / "imp" / original.name)
    assert not (s.path / "images.hdf5").exists() and not (s.path / "metadata.json").exists()
    assert not np.isnan(s.distance).any()
    col = [original.object_ids.tolist().index(o) for o in s.object_ids]
    d0 = original.distance[:, col]
    # the axis-aligned footprint holds the rotated one: never farther, equal for yaws that are multiples of 90
    assert (s.distance <= d0 + 1e-5).all()
    yaw = np.array(
        [next(o["bbox"]["yaw"] for o in original.meta["objects"] if o["objectId"] == oid) for oid in s.object_ids]
    )
    square = np.isclose(np.mod(yaw + 1e-9, 90), 0, atol=1e-6)
    assert square.any()
    assert np.allclose(s.distance[:, square], d0[:, square], atol=1e-5)
    # the paper's rule: visible (1.5 m map) and within 1.0 m
    assert np.array_equal(s.visible, original.visible[:, col])
    succ = s.category_visible_within(1.0)
    expect = np.zeros_like(succ)
    ok = s.visible & (s.distance <= 1.0)
    for j, c in enumerate(s.object_category):
        if c >= 0:
            expect[:, c] |= ok[:, j]
    assert np.array_equal(succ, expect)


def test_two_cells_fixture_hand_checked(tmp_path):
    src = tmp_path / "two_cells"
    shutil.copytree(FIXTURE, src)
    tv = "Television|+01.20|+01.20|+00.00"
    import_lineage_scene(src, tmp_path / "with_meta")
    s = load_scene(tmp_path / "with_meta")
    assert s.num_states == 32 and (s.next_state != np.arange(32)[:, None]).sum() == 100
    j = s.object_ids.tolist().index(tv)
    at0, at1 = (s.x == 0), (s.x == 0.25)
    assert np.allclose(s.distance[at0, j], 1.15) and np.allclose(s.distance[at1, j], 0.90)
    sofa = s.object_ids.tolist().index("Sofa|+00.10|+00.00|-01.50")
    assert s.object_category[sofa] == -1 and np.allclose(s.distance[:, sofa], 1.10)
    c = TARGET_CATEGORIES.index("Television")
    succ = s.success_mask("Television")
    assert set(s.keys[succ]) == {"0.25|0.00|45|0", "0.25|0.00|90|0", "0.25|0.00|135|0"}
    start = s.index("0.00|0.00|0|0")
    assert multi_source_bfs(s.next_state, succ)[start] == 3
    assert distance_fields(s.next_state, s.category_visible_within())[start, c] == 3
    floor = shapely.union_all([shapely.Polygon(p) for p in s.floor])
    assert floor.area == pytest.approx(0.125)
    # without metadata.json: the lineage's rule (visibility map alone)
    (src / "metadata.json").unlink()
    import_lineage_scene(src, tmp_path / "map_only")
    m = load_scene(tmp_path / "map_only")
    assert not (m.path / "states.hdf5").exists() and np.isnan(m.distance).all()
    assert set(m.keys[m.success_mask("Television")]) == {
        "0.00|0.00|90|0",
        "0.25|0.00|45|0",
        "0.25|0.00|90|0",
        "0.25|0.00|135|0",
    }
    assert multi_source_bfs(m.next_state, m.success_mask(c))[start] == 2


def test_savn_names_and_swapped_metadata(tmp_path):
    """SAVN's ``visible_object_map.json``, or that map saved as ``metadata.json``, import the same."""
    vis = json.loads((FIXTURE / "visible_object_map_1.5.json").read_text())
    for name in ("visible_object_map.json", "metadata.json"):
        src = tmp_path / name / "FloorPlan5_physics"
        src.mkdir(parents=True)
        for f in ("graph.json", "grid.json"):
            shutil.copy(FIXTURE / f, src / f)
        (src / name).write_text(json.dumps(vis))
        st = import_lineage_scene(src, tmp_path / name / "out" / "FloorPlan5_physics")
        s = load_scene(tmp_path / name / "out" / "FloorPlan5_physics")
        # the map as it was, less the objects it listed with no state (the lineage's maps never list one)
        assert json.loads((s.path / "visible_object_map_1.5.json").read_text()) == {k: v for k, v in vis.items() if v}
        assert any(not v for v in vis.values())
        assert s.room_type == "kitchen" and s.meta["split"] == "train" and not st.distances


def test_skip_and_overwrite(tmp_path):
    src = tmp_path / "src"
    shutil.copytree(FIXTURE, src)
    dst = tmp_path / "dst"
    assert not import_lineage_scene(src, dst).skipped
    assert import_lineage_scene(src, dst).skipped
    assert not import_lineage_scene(src, dst, ImportConfig(overwrite=True)).skipped
    assert not list(tmp_path.glob(".*partial*"))


def _h5_images(src, dtype=np.uint8, shape=(8, 8, 3)):
    keys = [n["id"] for n in json.loads((src / "graph.json").read_text())["nodes"]]
    with h5py.File(src / "images.hdf5", "w") as f:
        for k in keys:
            f.create_dataset(k, data=np.zeros(shape, dtype))


def _truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 3])


def _det_with_extra_key(src):
    with h5py.File(src / "detr_features_22cls.hdf5", "w") as f:
        f.create_dataset("9.00|9.00|0|0", data=np.zeros((22, 264), np.float32))


def _truncated_det(src):
    keys = [n["id"] for n in json.loads((src / "graph.json").read_text())["nodes"]]
    with h5py.File(src / "detr_features_22cls.hdf5", "w") as f:
        for k in keys:
            f.create_dataset(k, data=np.zeros((22, 264), np.float32))
    _truncate(src / "detr_features_22cls.hdf5")


def _vis_bad_key(src):
    (src / "visible_object_map_1.5.json").write_text(
        json.dumps({"Television|+01.20|+01.20|+00.00": ["0.50|0.00|90|0"]})
    )


def _meta_bad_key(src):
    m = json.loads((src / "metadata.json").read_text())
    m["0.00|0.25|0|0"] = m["0.00|0.00|0|0"]
    (src / "metadata.json").write_text(json.dumps(m))


MALFORMED = [
    ("no_graph", lambda s: (s / "graph.json").unlink(), r"graph\.json: missing file"),
    ("no_grid", lambda s: (s / "grid.json").unlink(), r"grid\.json: missing file"),
    (
        "no_visibility",
        lambda s: [(s / "visible_object_map_1.5.json").unlink(), (s / "metadata.json").unlink()],
        r"no visible_object_map_1\.5\.json, visible_object_map\.json or metadata\.json",
    ),
    ("bad_json", lambda s: (s / "grid.json").write_text("[{"), r"grid\.json: not valid JSON"),
    ("grid_shape", lambda s: (s / "grid.json").write_text('{"x": 1}'), r"grid\.json: expected a list"),
    (
        "grid_missing_position",
        lambda s: (s / "grid.json").write_text('[{"x": 0.0, "y": 0.9, "z": 0.0}]'),
        r"grid\.json: position of state 0\.25\|0\.00\|\S+ \(graph\.json\) is not in the grid",
    ),
    (
        "vis_key_not_in_graph",
        _vis_bad_key,
        r"visible_object_map_1\.5\.json: visible state of Television\S* '0\.50\|0\.00\|90\|0' is not a node of graph\.json",
    ),
    (
        "meta_key_not_in_graph",
        _meta_bad_key,
        r"metadata\.json: state key '0\.00\|0\.25\|0\|0' is not a state of graph\.json",
    ),
    (
        "graph_link_not_a_node",
        lambda s: (s / "graph.json").write_text(
            json.dumps(
                {
                    "directed": True,
                    "nodes": [{"id": "0.00|0.00|0|0"}],
                    "links": [{"source": "0.00|0.00|0|0", "target": "0.25|0.00|0|0"}],
                }
            )
        ),
        r"graph\.json: edge target '0\.25\|0\.00\|0\|0' is not a node",
    ),
    ("truncated_images", lambda s: [_h5_images(s), _truncate(s / "images.hdf5")], r"images\.hdf5: unreadable HDF5"),
    (
        "images_dtype",
        lambda s: _h5_images(s, np.float32),
        r"images\.hdf5: state .* holds float32 \(8, 8, 3\), expected uint8",
    ),
    (
        "det_key_not_in_graph",
        _det_with_extra_key,
        r"detr_features_22cls\.hdf5: state key '9\.00\|9\.00\|0\|0' is not a state",
    ),
    ("truncated_detections", _truncated_det, r"detr_features_22cls\.hdf5: unreadable HDF5"),
]


@pytest.mark.parametrize("name,mutate,message", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_malformed_input_one_clear_line(tmp_path, name, mutate, message):
    src = tmp_path / name
    shutil.copytree(FIXTURE, src)
    mutate(src)
    dst = tmp_path / "out" / name
    with pytest.raises(SceneFormatError) as e:
        import_lineage_scene(src, dst)
    msg = str(e.value)
    assert re.search(message, msg), msg
    assert "\n" not in msg and str(src) in msg
    assert not dst.exists()
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())  # no partial folder left


def test_thor_import_command(tmp_path, capsys):
    from tsnav.cli import main

    root = tmp_path / "AI2Thor_offline_data_2.0.2"
    for name in ("FloorPlan1", "FloorPlan201"):
        shutil.copytree(FIXTURE, root / name)
    assert main(["thor", "import", str(root), "--out", str(tmp_path / "ds"), "--copy", "copy"]) == 0
    out = capsys.readouterr().out
    assert "2 scenes" in out and "2 imported" in out and "distances from metadata.json" in out
    from tsnav.data.reader import list_scenes

    assert [p.name for p in list_scenes(tmp_path / "ds")] == ["FloorPlan1", "FloorPlan201"]
    assert load_scene(tmp_path / "ds" / "FloorPlan201").room_type == "living_room"
    assert main(["thor", "import", str(root / "FloorPlan1"), "--out", str(tmp_path / "ds")]) == 0
    assert "already complete" in capsys.readouterr().out
    (root / "FloorPlan1" / "grid.json").unlink()
    assert main(["thor", "import", str(root), "--out", str(tmp_path / "ds2")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "grid.json: missing file" in err
    assert main(["thor", "import", str(tmp_path / "nothing"), "--out", str(tmp_path / "ds3")]) == 2
    assert "no such folder" in capsys.readouterr().err
