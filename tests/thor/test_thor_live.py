"""Live AI2-THOR export against a stand-in controller (tests/thor_standin.py) backed by a tsnav scene.

The stand-in answers actions from the scene's state graph and renders with tsnav's renderer, so the
exported scene must reproduce the scene it stands for: the same state graph, the same visible pixels and
boxes, and visibility-map states that really show the object in the stand-in's instance masks.
"""

from __future__ import annotations

import json
import sys

import h5py
import networkx as nx
import numpy as np
import pytest

from tsnav.constants import parse_state_key
from tsnav.data.reader import load_scene
from tsnav.data.thor_export import check_lineage_layout
from tsnav.data.thor_live import LiveExportError, controller_settings, export_live

from thor_standin import StandInController


@pytest.fixture(scope="module")
def original(tiny_world):
    return min(
        (load_scene(p) for p in sorted(tiny_world.iterdir()) if (p / "COMPLETE").exists()), key=lambda s: s.num_states
    )


@pytest.fixture(scope="module")
def exported(original, tmp_path_factory):
    ctrl = StandInController(original.path, width=original.image_size)
    out = tmp_path_factory.mktemp("live")
    stats = export_live(ctrl, original.name, out, size=original.image_size)
    assert not stats.skipped and stats.dropped == 0 and stats.states == original.num_states
    return load_scene(out / original.name), ctrl, stats


def test_exported_graph_loads_with_networkx_and_matches(exported, original):
    s, ctrl, stats = exported
    g = nx.node_link_graph(json.loads((s.path / "graph.json").read_text()), edges="links")
    assert g.is_directed() and nx.is_strongly_connected(g)
    assert g.number_of_nodes() == original.num_states
    assert np.array_equal(s.keys, original.keys) and np.array_equal(s.next_state, original.next_state)
    # the graph was walked, not copied: one MoveAhead try per (position, rotation)
    P = len(np.unique(np.stack([original.x, original.z], 1), axis=0))
    assert ctrl.steps["MoveAhead"] == P * 8 and ctrl.steps["GetReachablePositions"] == 1
    assert check_lineage_layout(s.path) == []
    assert (s.path / "COMPLETE").exists() and s.meta["source"]["format"] == "ai2thor-live"


def test_exported_tables_match_the_renders(exported, original):
    s, ctrl, _ = exported
    cols = [original.object_ids.tolist().index(o) for o in s.object_ids]
    assert sorted(s.object_ids.tolist()) == sorted(original.object_ids.tolist())  # furniture filtered out
    # the same renderer; a different tile layout moves a few edge pixels (as for the images below)
    dpx = np.abs(s.pixels - original.pixels[:, cols])
    assert dpx.max() <= 8 and (dpx > 0).mean() < 0.002, (dpx.max(), (dpx > 0).sum())
    dbox = np.abs(s.boxes.astype(int) - original.boxes[:, cols].astype(int))
    assert ((s.boxes < 0) == (original.boxes[:, cols] < 0)).mean() > 0.998 and (
        dbox[(s.boxes >= 0) & (original.boxes[:, cols] >= 0)] <= 1
    ).all()
    # axis-aligned footprints hold the rotated ones: never farther than the scene's own distances
    assert (s.distance <= original.distance[:, cols] + 1e-5).all()
    with h5py.File(s.path / "images.hdf5", "r") as a, h5py.File(original.path / "images.hdf5", "r") as b:
        for k in s.keys[:: max(1, s.num_states // 25)]:
            # the same renderer; a different tile layout moves a few edge pixels
            diff = np.abs(a[k][()].astype(int) - b[k][()].astype(int))
            assert a[k].dtype == np.uint8 and (diff > 0).mean() < 0.02 and diff.mean() < 1.0
    with h5py.File(s.path / "depth.hdf5", "r") as f:
        k = s.keys[0]
        assert f[k].dtype == np.float16 and f[k].shape == (s.image_size, s.image_size)
    floor = s.floor
    import shapely

    fl = shapely.union_all([shapely.Polygon(p) for p in floor])
    assert shapely.contains_xy(fl, s.x.astype(float), s.z.astype(float)).all()


def test_visibility_map_states_show_the_object(exported):
    s, ctrl, _ = exported
    vis = json.loads((s.path / "visible_object_map_1.5.json").read_text())
    min_px = s.meta["visibility"]["min_pixels"]
    rng = np.random.default_rng(0)
    checked = 0
    for oid, keys in vis.items():
        for k in rng.choice(keys, size=min(4, len(keys)), replace=False) if keys else []:
            x, z, r, h = parse_state_key(str(k))
            ev = ctrl.step(
                action="Teleport", position={"x": x, "y": 0.9, "z": z}, rotation={"x": 0, "y": r, "z": 0}, horizon=h
            )
            assert ev.metadata["lastActionSuccess"]
            assert ev.instance_masks[oid].sum() >= min_px
            box = next(o["axisAlignedBoundingBox"] for o in ev.metadata["objects"] if o["objectId"] == oid)
            dx = max(abs(x - box["center"]["x"]) - box["size"]["x"] / 2, 0)
            dz = max(abs(z - box["center"]["z"]) - box["size"]["z"] / 2, 0)
            assert np.hypot(dx, dz) <= 1.5 + 1e-6
            checked += 1
    assert checked >= 5


def test_reader_arrays_agree_with_files(exported):
    s, _, _ = exported
    graph = json.loads((s.path / "graph.json").read_text())
    assert sorted(n["id"] for n in graph["nodes"]) == s.keys.tolist()
    edges = {(e["source"], e["target"]) for e in graph["links"]}
    a, b = np.nonzero(s.next_state != np.arange(s.num_states)[:, None])
    assert {(s.keys[i], s.keys[s.next_state[i, k]]) for i, k in zip(a, b)} == edges
    vis = json.loads((s.path / "visible_object_map_1.5.json").read_text())
    for j, oid in enumerate(s.object_ids):
        assert set(s.keys[s.visible[:, j]].tolist()) == set(vis.get(str(oid), []))
    assert all(vis.values())  # the lineage's maps never list an object with no state
    grid = json.loads((s.path / "grid.json").read_text())
    assert {(round(p["x"], 2), round(p["z"], 2)) for p in grid} == set(
        zip(np.round(s.x, 2).tolist(), np.round(s.z, 2).tolist())
    )
    with h5py.File(s.path / "states.hdf5", "r") as f:
        assert f["thor_visible"].shape == s.visible.shape and f["thor_visible"].dtype == bool
        # AI2-THOR's own flag (stand-in: any mask pixel within 1.5 m) holds every map state
        assert (f["thor_visible"][()] | ~s.visible).all()


def test_blocked_moves_are_left_out_and_unreachable_states_dropped(original, tmp_path):
    """A MoveAhead the simulator refuses is no edge; states cut off from the rest are dropped."""
    ctrl = StandInController(original.path, width=original.image_size)
    ns = ctrl.scene.next_state
    move = ns[:, 0] != np.arange(len(ns))
    # refuse every move into the position with the fewest ways in: it becomes unreachable and is dropped
    target_pos = {}
    for i in np.flatnonzero(move):
        t = ns[i, 0]
        target_pos.setdefault((float(ctrl.scene.x[t]), float(ctrl.scene.z[t])), []).append(i)
    pos, sources = min(target_pos.items(), key=lambda kv: len(kv[1]))
    ns[sources, 0] = sources
    stats = export_live(ctrl, original.name, tmp_path, size=original.image_size)
    s = load_scene(tmp_path / original.name)
    assert stats.dropped == 16 and s.num_states == original.num_states - 16
    assert not ((np.abs(s.x - pos[0]) < 1e-6) & (np.abs(s.z - pos[1]) < 1e-6)).any()
    g = nx.node_link_graph(json.loads((s.path / "graph.json").read_text()), edges="links")
    assert nx.is_strongly_connected(g)
    # resumable: a complete scene is skipped
    assert export_live(ctrl, original.name, tmp_path, size=original.image_size).skipped


def test_controller_without_depth_or_masks_is_refused(original, tmp_path):
    ctrl = StandInController(original.path, width=original.image_size, renderDepthImage=False)
    for depth, seg, what in ((False, True, "renderDepthImage"), (True, False, "renderInstanceSegmentation")):
        ctrl.depth_on, ctrl.seg_on = depth, seg  # as if made with renderDepthImage / renderInstanceSegmentation off
        with pytest.raises(LiveExportError, match=what) as e:
            export_live(ctrl, original.name, tmp_path, size=original.image_size)
        assert "\n" not in str(e.value)
        assert not (tmp_path / original.name).exists() and not list(tmp_path.glob(".*"))
    ctrl.depth_on = ctrl.seg_on = True
    with pytest.raises(LiveExportError, match=r"expected \(32, 32, 3\)"):
        export_live(ctrl, original.name, tmp_path, size=32)


def test_settings_and_missing_ai2thor(monkeypatch, tmp_path, capsys):
    cfg = controller_settings(300)
    assert cfg["gridSize"] == 0.25 and cfg["rotateStepDegrees"] == 45 and cfg["fieldOfView"] == 90
    assert cfg["renderDepthImage"] and cfg["renderInstanceSegmentation"] and cfg["width"] == cfg["height"] == 300
    monkeypatch.setitem(sys.modules, "ai2thor", None)
    monkeypatch.setitem(sys.modules, "ai2thor.controller", None)
    from tsnav.cli import main

    assert main(["thor", "export-live", "--scenes", "FloorPlan1,FloorPlan2", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "ai2thor is not installed" in err and "tsnav[thor]" in err
    assert not (tmp_path / "x").exists()
