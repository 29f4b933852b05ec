"""The embedded world: generator, renderer, dataset files and reader (issue: embedded world)."""

from __future__ import annotations

import filecmp
import json
import subprocess
import sys
from pathlib import Path

import h5py
import networkx as nx
import numpy as np
import pytest
import shapely
from shapely.geometry import Polygon
from shapely.ops import unary_union

from tsnav.constants import ACTIONS, GRID_SIZE, MOVE_AHEAD, parse_state_key, parse_state_keys, state_key
from tsnav.data.reader import SceneFormatError, edge_actions, load_scene
from tsnav.data.writer import box_distance, object_stats, object_stats_reference
from tsnav.data.names import ithor_scenes, robothor_scenes, scene_info
from tsnav.world.house import generate
from tsnav.world.navgrid import AGENT_RADIUS


def test_state_key_format():
    assert state_key(0.5, 3.5, 315, 30) == "0.50|3.50|315|30"
    assert state_key(-1.25, 0, -45, 0) == "-1.25|0.00|315|0"
    assert parse_state_key("0.50|3.50|315|30") == (0.5, 3.5, 315, 30)
    x, z, r, h = parse_state_keys(["0.50|3.50|315|30", "-1.00|2.25|0|0"])
    assert x.tolist() == [0.5, -1.0] and z.tolist() == [3.5, 2.25] and r.tolist() == [315, 0] and h.tolist() == [30, 0]
    with pytest.raises(ValueError, match="malformed"):
        parse_state_key("0.5|3.5|90")


def test_scene_names_and_splits():
    assert len(ithor_scenes()) == 120 and len(robothor_scenes()) == 75
    assert scene_info("FloorPlan20") == ("kitchen", "train")
    assert scene_info("FloorPlan221") == ("living_room", "val")
    assert scene_info("FloorPlan330") == ("bedroom", "test")
    assert scene_info("FloorPlan_Val3_5") == ("apartment", "val")
    assert len(ithor_scenes(split="val")) == 20 and len(ithor_scenes(split="test")) == 20
    with pytest.raises(ValueError, match="unknown scene"):
        scene_info("FloorPlan31")
    from tsnav.data import lineage_splits
    from tsnav.data.names import lineage_scene_info, scene_base_name

    assert scene_base_name("FloorPlan24_physics") == "FloorPlan24" == scene_base_name("FloorPlan24")
    assert scene_base_name("FloorPlan_physics2") == "FloorPlan_physics2"  # only a suffix is stripped
    assert lineage_splits.scene_base_name is scene_base_name  # one definition
    assert lineage_scene_info("FloorPlan330_physics") == ("bedroom", "test")
    assert lineage_scene_info("Kitchen_physics") == ("unknown", None)


def test_generator_deterministic_and_varied():
    a, b = generate("FloorPlan7").to_json(), generate("FloorPlan7").to_json()
    assert json.dumps(a) == json.dumps(b)
    c = generate("FloorPlan8").to_json()
    assert a["parts"] != c["parts"]
    apt = generate("FloorPlan_Train3_2")
    assert len(apt.rooms) >= 3 and len(apt.doors) >= len(apt.rooms) - 1


def test_graph_json_loads_with_networkx(tiny_world):
    for scene in sorted(p for p in tiny_world.iterdir() if p.is_dir()):
        data = json.loads((scene / "graph.json").read_text())
        g = nx.node_link_graph(data, edges="links")
        assert g.is_directed() and g.number_of_nodes() > 100
        assert nx.is_strongly_connected(g), scene.name
        for k in list(g.nodes)[:50]:
            assert state_key(*parse_state_key(k)) == k


def test_moves_never_cross_walls_or_furniture(tiny_scenes):
    for s in tiny_scenes:
        spec_obstacles = [Polygon(f["footprint"]) for f in s.meta["furniture"]]
        spec_obstacles += [Polygon(_fp(o)) for o in s.meta["objects"] if o["support"] == "floor"]
        blocked = unary_union(spec_obstacles).buffer(AGENT_RADIUS - 1e-3)
        floor = unary_union([Polygon(p) for p in s.floor]).buffer(-(AGENT_RADIUS - 1e-3))
        i = np.flatnonzero(s.next_state[:, MOVE_AHEAD] != np.arange(s.num_states))
        j = s.next_state[i, MOVE_AHEAD]
        for t in np.linspace(0, 1, 9):
            px = s.x[i] + t * (s.x[j] - s.x[i])
            pz = s.z[i] + t * (s.z[j] - s.z[i])
            assert not shapely.intersects_xy(blocked, px, pz).any(), s.name
            assert shapely.contains_xy(floor, px, pz).all(), s.name
        # a move is one grid step along the heading
        step = np.hypot(s.x[j] - s.x[i], s.z[j] - s.z[i])
        assert np.allclose(step[s.rotation[i] % 90 == 0], GRID_SIZE)
        assert np.allclose(step[s.rotation[i] % 90 == 45], GRID_SIZE * np.sqrt(2))


def _fp(o):
    from tsnav.world.spec import box_footprint

    b = o["bbox"]
    return box_footprint(b["center"], b["size"], b["yaw"])


def test_visibility_map_matches_renders(tiny_world, tiny_scenes):
    """Every state listed for an object really shows that object's id and is within range."""
    from tsnav.world.show import render_views

    rng = np.random.default_rng(0)
    s = tiny_scenes[0]
    vis = json.loads((s.path / "visible_object_map_1.5.json").read_text())
    inst = {o["objectId"]: o["inst"] for o in s.meta["objects"]}
    checked = 0
    for oid, keys in vis.items():
        if not keys:
            continue
        for k in rng.choice(keys, size=min(3, len(keys)), replace=False):
            x, z, r, h = parse_state_key(str(k))
            _, _, ids = render_views(s, np.array([[x, z, r, h]]), size=s.image_size)
            assert (ids[0] == inst[oid]).sum() >= s.meta["visibility"]["min_pixels"]
            o = next(o for o in s.meta["objects"] if o["objectId"] == oid)
            d = box_distance(
                np.array([[x, z]]),
                np.array([o["bbox"]["center"]]),
                np.array([o["bbox"]["size"]]),
                np.array([o["bbox"]["yaw"]]),
            )[0, 0]
            assert d <= 1.5 + 1e-6
            checked += 1
    assert checked >= 5


def test_object_stats_fast_equals_reference():
    rng = np.random.default_rng(1)
    ids = rng.integers(0, 9, size=(5, 16, 16)).astype(np.int32)
    lut = np.array([-1, -1, 0, 1, -1, 2, 3, 3, -1])
    a = object_stats(ids, lut, 4)
    b = object_stats_reference(ids, lut, 4)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_render_depth_and_orientation(tiny_scenes):
    """Depth is the distance along the view axis; rotation 90 looks along +x (AI2-THOR convention)."""
    from tsnav.world.show import render_views

    s = tiny_scenes[0]
    x0, z0, x1, z1 = s.meta["rooms"][0]["rect"]
    i = int(np.argmin(np.abs(s.x - (x0 + x1) / 2) + np.abs(s.z - (z0 + z1) / 2)))
    x, z = float(s.x[i]), float(s.z[i])
    rgb, depth, ids = render_views(s, np.array([[x, z, 90, 0], [x, z, 0, 0]]), size=64)
    wall = s.meta["instances"].index("Wall")
    # the centre pixel at horizon 0 looks straight ahead at camera height: the first thing hit on the ray.
    for v, expect_far in ((0, x1 - 0.05 - x), (1, z1 - 0.05 - z)):
        c = depth[v, 31:33, 31:33].mean()
        assert c <= expect_far + 0.05
        if ids[v, 32, 32] == wall:
            assert abs(c - expect_far) < 0.05
    assert rgb.dtype == np.uint8 and rgb.shape == (2, 64, 64, 3)


def test_reader_arrays_agree_with_json(tiny_scenes):
    for s in tiny_scenes:
        graph = json.loads((s.path / "graph.json").read_text())
        assert sorted(n["id"] for n in graph["nodes"]) == s.keys.tolist()
        edges = {(e["source"], e["target"]) for e in graph["links"]}
        a, b = np.nonzero(s.next_state != np.arange(s.num_states)[:, None])
        from_arrays = {(s.keys[i], s.keys[s.next_state[i, k]]) for i, k in zip(a, b)}
        assert from_arrays == edges
        vis = json.loads((s.path / "visible_object_map_1.5.json").read_text())
        for j, oid in enumerate(s.object_ids):
            assert set(s.keys[s.visible[:, j]].tolist()) == set(vis.get(str(oid), []))
        grid = json.loads((s.path / "grid.json").read_text())
        assert {(round(p["x"], 2), round(p["z"], 2)) for p in grid} == set(
            zip(np.round(s.x, 2).tolist(), np.round(s.z, 2).tolist())
        )
        with h5py.File(s.path / "images.hdf5", "r") as f:
            k = s.keys[len(s.keys) // 2]
            assert f[k].shape == (64, 64, 3) and f[k].dtype == np.uint8
        # rotation edges are labelled correctly by geometry
        acts = edge_actions(s.x, s.z, s.rotation, s.horizon, s.x, s.z, (s.rotation + 45) % 360, s.horizon)
        assert (acts == ACTIONS.index("RotateRight")).all()


def test_determinism_two_builds_identical(tmp_path):
    from tsnav.world.build import BuildConfig
    from tsnav.world.build import build_dataset

    cfg = BuildConfig(image_size=32, compact=True)
    for d in ("a", "b"):
        build_dataset(tmp_path / d, scenes=["FloorPlan401"], cfg=cfg, progress=False)
    cmp = filecmp.dircmp(tmp_path / "a" / "FloorPlan401", tmp_path / "b" / "FloorPlan401")
    assert cmp.left_only == [] and cmp.right_only == []
    for f in cmp.common_files:
        assert filecmp.cmp(tmp_path / "a" / "FloorPlan401" / f, tmp_path / "b" / "FloorPlan401" / f, shallow=False), f


def test_camera_height_renders_from_another_eye(tmp_path, capsys):
    """``camera_height`` (``tsnav world --camera-height``) renders the frames and visibility tables from another
    height, recorded in scene.json; a folder of finished scenes from another height is refused in one line, and so
    is a height out of range, before anything is built."""
    from tsnav.cli import main
    from tsnav.world.build import BuildConfig, build_dataset

    low = BuildConfig(image_size=32, compact=True, camera_height=0.88)
    build_dataset(tmp_path / "low", scenes=["FloorPlan401"], cfg=low, progress=False)
    build_dataset(
        tmp_path / "std", scenes=["FloorPlan401"], cfg=BuildConfig(image_size=32, compact=True), progress=False
    )
    meta = json.loads((tmp_path / "low" / "FloorPlan401" / "scene.json").read_text())
    assert meta["camera"] == {"height": 0.88, "field_of_view": 90.0}
    a, b = load_scene(tmp_path / "low" / "FloorPlan401"), load_scene(tmp_path / "std" / "FloorPlan401")
    assert (a.x == b.x).all() and (a.z == b.z).all()  # the same states and graph
    assert not np.array_equal(a.pixels, b.pixels)  # the visibility tables are rendered from the camera too
    with (
        h5py.File(tmp_path / "low" / "FloorPlan401" / "depth.hdf5") as fa,
        h5py.File(tmp_path / "std" / "FloorPlan401" / "depth.hdf5") as fb,
    ):
        k = sorted(fa.keys())[0]
        da, db = np.asarray(fa[k], np.float32), np.asarray(fb[k], np.float32)
    assert not np.array_equal(da, db)  # another eye, another frame
    from tsnav.world.show import render_views

    pose = np.array([[a.x[0], a.z[0], a.rotation[0], a.horizon[0]]], np.float64)
    key = state_key(float(a.x[0]), float(a.z[0]), int(a.rotation[0]), int(a.horizon[0]))
    with h5py.File(tmp_path / "low" / "FloorPlan401" / "depth.hdf5") as fa:
        stored = np.asarray(fa[key], np.float32)
    again = render_views(a, pose, size=32)[1][0]  # drawn again from the scene's own camera height
    assert np.allclose(again, stored, atol=0.01)
    with pytest.raises(
        ValueError, match=r"rendered from a camera 0.88 m high, this build from 1.5 m: use another --out"
    ):
        build_dataset(
            tmp_path / "low", scenes=["FloorPlan402"], cfg=BuildConfig(image_size=32, compact=True), progress=False
        )
    assert not (tmp_path / "low" / "FloorPlan402").exists()
    with pytest.raises(ValueError, match="camera_height must be between 0.1 and 3.0 metres"):
        BuildConfig(camera_height=5.0)
    assert main(["world", "--preset", "tiny", "--camera-height", "0", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--camera-height: camera_height must be between 0.1 and 3.0 metres, got 0.0" in err and "\n" not in err
    assert not (tmp_path / "x").exists()


def test_interrupted_build_resumes(tmp_path):
    """A build killed mid-way leaves no complete-looking partial scene; rerunning finishes the rest."""
    out = tmp_path / "w"
    code = (
        "import os, tsnav.world.build as b\n"
        "orig = b.build_scene\n"
        "def boom(name, *a, **k):\n"
        "    if name == 'FloorPlan402':\n"
        "        (lambda: os._exit(3))()\n"
        "    return orig(name, *a, **k)\n"
        "b.build_scene = boom\n"
        "from tsnav.world.build import BuildConfig\n"
        f"b.build_dataset({str(out)!r}, scenes=['FloorPlan401', 'FloorPlan402'], cfg=BuildConfig(image_size=32, compact=True), progress=False)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True)
    assert r.returncode == 3
    assert (out / "FloorPlan401" / "COMPLETE").exists() and not (out / "FloorPlan402").exists()
    # a half-written temporary folder from a kill inside the writer is never taken for a scene
    (out / ".FloorPlan402.partial-99").mkdir()
    from tsnav.data.reader import list_scenes
    from tsnav.world.build import BuildConfig
    from tsnav.world.build import build_dataset

    assert [p.name for p in list_scenes(out)] == ["FloorPlan401"]
    stats = build_dataset(
        out, scenes=["FloorPlan401", "FloorPlan402"], cfg=BuildConfig(image_size=32, compact=True), progress=False
    )
    assert [s.skipped for s in stats] == [True, False]
    assert [p.name for p in list_scenes(out)] == ["FloorPlan401", "FloorPlan402"]
    assert not list(out.glob(".*partial*"))


def test_cli_errors_are_one_line(tmp_path):
    def run(*args):
        return subprocess.run([sys.executable, "-m", "tsnav.cli", *args], capture_output=True, text=True)

    r = run("world", "--preset", "nope", "--out", str(tmp_path / "x"))
    assert r.returncode == 2 and "unknown preset 'nope'" in r.stderr and "Traceback" not in r.stderr
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    r = run("world", "--preset", "tiny", "--out", str(ro / "sub"))
    ro.chmod(0o700)
    import os

    if os.geteuid() != 0:  # root can write anywhere
        assert r.returncode == 2 and "cannot write" in r.stderr
    r = run("world", "--preset", "tiny", "--out", "/proc/nonexistent/x")
    assert r.returncode == 2 and "cannot write" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run(
        [sys.executable, "-m", "tsnav.cli", "world", "--preset", "tiny", "--out", str(tmp_path / "y")],
        capture_output=True,
        text=True,
        env={
            "PATH": "/usr/bin:/bin",
            "LD_LIBRARY_PATH": str(tmp_path),
            "PYTHONPATH": str(Path(__file__).parents[2] / "src"),
            "TSNAV_EGL_LIBRARY": "libEGL_missing.so.1",
        },
    )
    assert r.returncode == 2 and "EGL" in r.stderr and "Traceback" not in r.stderr


def test_reader_malformed_input(tmp_path):
    with pytest.raises(SceneFormatError, match="not a scene folder"):
        load_scene(tmp_path / "missing")
    d = tmp_path / "bad"
    d.mkdir()
    (d / "graph.json").write_text("{not json")
    with pytest.raises(SceneFormatError, match="not valid JSON"):
        load_scene(d)
    (d / "graph.json").write_text(
        json.dumps(
            {"nodes": [{"id": "0.00|0.00|0|0"}], "links": [{"source": "0.00|0.00|0|0", "target": "9.00|0.00|0|0"}]}
        )
    )
    with pytest.raises(SceneFormatError, match="is not a node"):
        load_scene(d)


def test_box_distance_by_hand():
    # a 1 x 1 m box centred at (2, 0, 0): 1.5 m from the origin along x; rotated 45 deg: 2 - sqrt(0.5)
    d = box_distance(
        np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 3.0]]),
        np.array([[2.0, 0.0, 0.0]]),
        np.array([[1.0, 0.5, 1.0]]),
        np.array([0.0]),
    )
    assert np.allclose(d[:, 0], [1.5, 0.0, 2.5])
    d45 = box_distance(
        np.array([[0.0, 0.0]]), np.array([[2.0, 0.0, 0.0]]), np.array([[1.0, 0.5, 1.0]]), np.array([45.0])
    )
    assert np.isclose(d45[0, 0], 2 - np.sqrt(0.5))


def test_targets_can_be_seen_and_reached(tiny_scenes):
    """Objects are not buried in walls or furniture: nearly all show up in some frame, and most categories
    present in a scene have states that satisfy the paper's success rule (in view within 1 m)."""
    seen = np.concatenate([(s.pixels >= s.meta["visibility"]["min_pixels"]).any(0) for s in tiny_scenes])
    assert seen.mean() >= 0.9
    ok = [s.category_visible_within(1.0)[:, s.categories_present()].any(0) for s in tiny_scenes]
    assert np.concatenate(ok).mean() >= 0.75


@pytest.mark.parametrize(
    "name,world", [("FloorPlan1", "procedural"), ("FloorPlan21", "procedural"), ("FloorPlan301", "ithor-real")]
)
def test_state_tables_equal_reference(name, world):
    """The array forms of the build (``state_poses``, ``state_keys``, ``graph_edges``) against the slow
    per-state loop (``build_graph`` and the poses loop the build used before): same rows, keys and edges in
    the same order; the sorted keys are the sorted nodes."""
    from tsnav.constants import HORIZONS, ROTATIONS
    from tsnav.world.navgrid import build_graph, graph_edges, reachable_positions, state_keys, state_poses
    from tsnav.world.presets import scene_spec

    positions, move = reachable_positions(scene_spec(name, world, compact=world == "procedural"))
    assert (move < 0).any() and (move >= 0).any()
    nodes, edges = build_graph(positions, move)
    poses_ref = np.array([(x, z, r, h) for x, z in positions for r in ROTATIONS for h in HORIZONS], dtype=np.float64)
    poses = state_poses(positions)
    assert poses.dtype == np.float64 and np.array_equal(poses, poses_ref)
    keys = state_keys(positions)
    assert keys.tolist() == nodes == [state_key(*p) for p in poses_ref]
    src, dst = graph_edges(move)
    assert list(zip(keys[src].tolist(), keys[dst].tolist())) == edges
    assert keys[np.argsort(keys, kind="stable")].tolist() == sorted(nodes)


def test_built_graph_and_keys_equal_reference(tiny_world, tmp_path):
    """A built scene's ``graph.json`` is byte for byte the one the per-state reference writes, and its
    ``states.hdf5`` rows are the sorted reference nodes."""
    from tsnav.data.writer import write_graph
    from tsnav.world.navgrid import build_graph, reachable_positions
    from tsnav.world.presets import scene_spec

    name = "FloorPlan201"
    nodes, edges = build_graph(*reachable_positions(scene_spec(name, compact=True)))
    write_graph(tmp_path, sorted(nodes), edges)
    assert filecmp.cmp(tmp_path / "graph.json", tiny_world / name / "graph.json", shallow=False)
    with h5py.File(tiny_world / name / "states.hdf5", "r") as f:
        assert [k.decode() for k in f["keys"][:]] == sorted(nodes)


@pytest.mark.parametrize("depth_dtype,compression", [("float16", None), ("float32", "gzip"), ("float16", "lzf")])
def test_frame_writer_add_many_equals_add(tmp_path, depth_dtype, compression):
    """``FrameWriter.add_many`` (one depth conversion per batch) writes the same bytes as ``add`` per frame."""
    from tsnav.data.writer import FrameWriter

    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (5, 8, 8, 3), dtype=np.uint8)
    depth = rng.uniform(0.0, 12.0, (5, 8, 8)).astype(np.float32)
    keys = np.array([state_key(x, 1.0, r, 30) for x, r in [(0.5, 0), (0.25, 45), (-1.0, 90), (2.0, 315), (0.0, 0)]])
    for d in ("one", "many"):
        (tmp_path / d).mkdir()
    with FrameWriter(tmp_path / "one", depth_dtype, compression) as w:
        for i in range(len(keys)):
            w.add(keys[i], rgb[i], depth[i])
    with FrameWriter(tmp_path / "many", depth_dtype, compression) as w:
        w.add_many(keys[:2], rgb[:2], depth[:2])
        w.add_many(keys[2:], rgb[2:], depth[2:])
        with pytest.raises(ValueError, match="3 keys, 2 RGB"):
            w.add_many(keys[:3], rgb[:2], depth[:2])
    for f in ("images.hdf5", "depth.hdf5"):
        assert filecmp.cmp(tmp_path / "one" / f, tmp_path / "many" / f, shallow=False), f
    with h5py.File(tmp_path / "many" / "depth.hdf5", "r") as f:
        assert f[keys[2]].dtype == np.dtype(depth_dtype)
        assert np.array_equal(f[keys[2]][()], depth[2].astype(depth_dtype))


def test_build_config_from_preset():
    """One preset -> BuildConfig mapping (``build_dataset`` without a config and ``tsnav world`` use it)."""
    from tsnav.world.build import BuildConfig
    from tsnav.world.presets import PRESETS

    for name, p in PRESETS.items():
        cfg = BuildConfig.from_preset(name)
        assert (cfg.image_size, cfg.compact, cfg.world) == (p["image_size"], p["compact"], p.get("world", "procedural"))
        assert cfg.store_images and cfg.seed == 0
    assert BuildConfig.from_preset("ithor-real").world == "ithor-real"
    assert BuildConfig.from_preset("tiny", image_size=32, seed=3) == BuildConfig(image_size=32, compact=True, seed=3)
    assert BuildConfig.from_preset(None) == BuildConfig.from_preset("custom") == BuildConfig()


def test_compressed_frames_equal_raw_and_stay_lineage_readable(tmp_path):
    """The default frame files (gzip, one chunk per frame) hold exactly the frames of a raw build
    (``--no-compression``), read with plain ``h5py`` one dataset per state key as the lineage reads them; the
    lineage layout check passes on both; bad settings are refused with one line."""
    from tsnav.cli import main
    from tsnav.data.thor_export import check_lineage_layout
    from tsnav.data.reader import read_stack, read_stack_reference
    from tsnav.data.writer import FrameWriter

    name = "FloorPlan201"
    assert main(["world", "--preset", "tiny", "--scenes", name, "--out", str(tmp_path / "gz"), "--workers", "1"]) == 0
    assert (
        main(
            [
                "world",
                "--preset",
                "tiny",
                "--scenes",
                name,
                "--out",
                str(tmp_path / "raw"),
                "--workers",
                "1",
                "--no-compression",
            ]
        )
        == 0
    )
    sizes = {}
    for kind in ("images.hdf5", "depth.hdf5"):
        with h5py.File(tmp_path / "gz" / name / kind, "r") as g, h5py.File(tmp_path / "raw" / name / kind, "r") as r:
            assert sorted(g.keys()) == sorted(r.keys()) and len(g) > 100
            for k in sorted(g.keys())[::7]:
                assert g[k].compression == "gzip" and g[k].chunks == g[k].shape
                assert r[k].compression is None
                assert g[k].dtype == r[k].dtype and np.array_equal(g[k][()], r[k][()])
        sizes[kind] = ((tmp_path / "gz" / name / kind).stat().st_size, (tmp_path / "raw" / name / kind).stat().st_size)
    assert all(gz < raw * 0.7 for gz, raw in sizes.values()), sizes  # (real rooms at 128 px: about 4.5x)
    for d in ("gz", "raw"):
        assert check_lineage_layout(tmp_path / d / name, image_size=64) == []
        for kind in ("images.hdf5", "depth.hdf5"):  # the consumers' fast reader equals plain h5py reads
            with h5py.File(tmp_path / d / name / kind, "r") as f:
                keys = sorted(f.keys())[::-3]
                fast, ref = read_stack(f, keys), read_stack_reference(f, keys)
                assert fast.dtype == ref.dtype and np.array_equal(fast, ref)
                with pytest.raises(KeyError, match="no dataset '1.00"):
                    read_stack(f, keys[:2] + ["1.00|1.00|0|99"])
    with pytest.raises(ValueError, match="unknown frame compression"):
        FrameWriter(tmp_path, compression="szip")
    with pytest.raises(ValueError, match="gzip level"):
        FrameWriter(tmp_path, compression="gzip", level=12)
