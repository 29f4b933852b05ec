"""The ``ithor-real`` world (issue 12): layout reader, reachability rule, room outline, determinism."""

from __future__ import annotations

import filecmp
import json
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from tsnav.constants import GRID_SIZE, TARGET_CATEGORIES
from tsnav.world.layouts import LayoutError, layout_names, load_layout, pack_layouts, parse_layout, read_layout_file
from tsnav.world.navgrid import AGENT_RADIUS, SIGHT_DISTANCE, reachable_positions, targets_in_sight
from tsnav.world.real import alcoves, blocks, outer_rect, real_spec, spec_from_layout
from tsnav.world.spec import ObjectInstance, SceneSpec


def obj(oid: str, center, size, parents=None, ry: float = 0.0, **flags) -> dict:
    """One object in the recorded layout format (no oriented box: the axis-aligned one is used)."""
    otype = oid.split("|")[0]
    return {
        "objectId": oid,
        "objectType": otype,
        "position": dict(zip("xyz", center)),
        "rotation": {"x": 0, "y": ry, "z": 0},
        "aabb": {"center": dict(zip("xyz", center)), "size": dict(zip("xyz", size))},
        "oobbCorners": None,
        "parentReceptacles": parents,
        **flags,
    }


FLOOR = obj("Floor|+00.00|+00.00|+00.00", (1.5, -0.05, 1.5), (3.0, 0.1, 3.0))
ROOM = {
    "scene": "FloorPlan401",
    "objects": [
        FLOOR,
        obj("Chair|+01.50|+00.00|+01.50", (1.5, 0.45, 1.5), (0.5, 0.9, 0.5), ["Floor|+00.00|+00.00|+00.00"]),
        obj("Plate|+00.50|+00.80|+00.50", (0.5, 0.8, 0.5), (0.25, 0.02, 0.25), ["DiningTable|+00.50|+00.70|+00.50"]),
        obj("LightSwitch|+00.02|+01.30|+02.00", (0.02, 1.3, 2.0), (0.04, 0.15, 0.09), None, ry=90),
        obj("Cabinet|+02.75|+02.20|+00.25", (2.75, 2.2, 0.25), (0.5, 0.6, 0.5)),  # hangs above the capsule
        obj("Cabinet|+02.75|+00.40|+02.75", (2.75, 0.4, 2.75), (0.5, 0.8, 0.5)),  # stands on the floor
    ],
}


def box_dist(p, center, size) -> float:
    dx = max(abs(p[0] - center[0]) - size[0] / 2, 0.0)
    dz = max(abs(p[1] - center[2]) - size[2] / 2, 0.0)
    return float(np.hypot(dx, dz))


def test_blocking_rule_and_reachable_positions():
    layout = parse_layout(ROOM, "room")
    kinds = {o.object_id.split("|")[0] + ("-high" if o.aabb_center[1] > 2 else ""): blocks(o) for o in layout.objects}
    assert kinds == {
        "Floor": False,
        "Chair": True,
        "Plate": False,
        "LightSwitch": False,
        "Cabinet-high": False,
        "Cabinet": True,
    }
    # Version 1's rules (walls at the floor box, the full capsule radius); version 2 below (test_version_2_*).
    assert outer_rect(layout, 1) == [0.0, 0.0, 3.0, 3.0] and alcoves(layout, [0.0, 0.0, 3.0, 3.0]) == []
    spec = spec_from_layout(layout, "bathroom", "train", version=1)
    pos, move = reachable_positions(spec)
    # By hand: grid points at least the agent's radius from the walls and from the two blocking boxes.
    blockers = [((1.5, 0, 1.5), (0.5, 0, 0.5)), ((2.75, 0, 2.75), (0.5, 0, 0.5))]
    g = np.arange(1, 12) * GRID_SIZE
    expect = {(x, z) for x in g for z in g if all(box_dist((x, z), c, s) > AGENT_RADIUS for c, s in blockers)}
    got = {(float(x), float(z)) for x, z in pos}
    assert got == expect and len(got) == 121 - 9 - 4
    assert (0.5, 0.5) in got and (0.25, 2.0) in got  # under the plate, in front of the switch
    # Object ids are kept exactly; the chair (a target class) stands on the floor.
    chair = next(o for o in spec.objects if o.objectType == "Chair")
    assert chair.objectId == "Chair|+01.50|+00.00|+01.50" and chair.support == "floor"


def test_kept_connected_set_sees_the_rooms_targets():
    """FloorPlan409's shower stall (behind ShowerDoor/ShowerGlass) holds 54 grid positions, the bathroom 52:
    the stall, from which no target is in sight, is left out. Rooms whose largest set sees a target keep it."""
    spec = real_spec("FloorPlan409", version=1)
    pos, _ = reachable_positions(spec)
    assert len(pos) == 52
    seen = targets_in_sight(spec, pos)
    assert len(seen) >= 2 and seen <= set(TARGET_CATEGORIES)
    # every category in sight has an object within SIGHT_DISTANCE of a kept position (the slow, direct check)
    for cat in seen:
        centres = [(o.center[0], o.center[2]) for o in spec.objects if o.objectType == cat]
        assert min(np.hypot(*(p - c)) for p in pos for c in np.asarray(centres)) < SIGHT_DISTANCE
    # FloorPlan408 also has two sets (56 and 55 positions); the larger sees targets and is kept
    spec = real_spec("FloorPlan408", version=1)
    pos, _ = reachable_positions(spec)
    assert len(pos) == 56 and targets_in_sight(spec, pos)


def test_kept_connected_set_rule_on_small_floors():
    """Two floor squares, 49 grid positions and 9: with no objects (or a target seen from the large one) the
    large set is kept; with the only target by the small one, the small one; a set of fewer than MIN_COMPONENT
    positions is never kept; one set is kept as it is."""

    def square(x0, z0, x1, z1):
        return [[x0, z0], [x1, z0], [x1, z1], [x0, z1]]

    def spec(*floor, objects=()):
        return SceneSpec(
            name="t", room_type="bathroom", split="train", seed=0, rooms=[], floor=list(floor), objects=list(objects)
        )

    def sink(x, z):
        return ObjectInstance(f"Sink|{x}|{z}", "Sink", (x, 0.8, z), (0.3, 0.2, 0.1), 0.0, "wall")

    big, small, tiny = square(0, 0, 2, 2), square(3, 0, 4, 1), square(3, 0, 3.75, 0.5)
    assert len(reachable_positions(spec(big))[0]) == 49
    assert len(reachable_positions(spec(big, small))[0]) == 49
    pos, move = reachable_positions(spec(big, small, objects=[sink(3.5, 0.95)]))
    assert len(pos) == 9 and pos[:, 0].min() == 3.25 and move.max() < 9
    assert len(reachable_positions(spec(big, small, objects=[sink(3.5, 0.95), sink(1.0, 1.95)]))[0]) == 49
    assert len(reachable_positions(spec(big, tiny, objects=[sink(3.5, 0.45)]))[0]) == 49
    assert len(reachable_positions(spec(small, objects=[sink(1.0, 1.95)]))[0]) == 9


def test_outer_walls_snap_to_objects_and_alcove_from_a_wall_fixture():
    floor = obj("Floor|+00.00|+00.00|+00.00", (2.0, -0.05, 2.0), (4.0, 0.1, 4.0))
    # A light switch deep in the room facing -z (rotation 180): a wall behind it, the empty corner cut.
    switch = obj("LightSwitch|+02.00|+01.30|+02.50", (2.0, 1.3, 2.5), (0.15, 0.15, 0.09), None, ry=180)
    chair = obj("Chair|+03.00|+00.00|+03.75", (3.0, 0.45, 3.75), (0.5, 0.9, 0.5), ["Floor|+00.00|+00.00|+00.00"])
    layout = parse_layout({"scene": "FloorPlan1", "objects": [floor, switch, chair]}, "alcove")
    rect = outer_rect(layout, 1)
    assert rect == [0.0, 0.0, 4.0, 4.0]
    assert alcoves(layout, rect) == [[0.0, 2.545, 2.75, 4.0]]
    spec = spec_from_layout(layout, "kitchen", "train", version=1)
    pos, _ = reachable_positions(spec)
    assert not any(x < 2.75 and z > 2.5 for x, z in pos)  # nothing in the alcove
    assert any(x >= 3.5 and z >= 3.0 for x, z in pos) and any(x < 2.5 and z < 2.25 for x, z in pos)
    # The floor box reaching 0.3 m past the objects along a side: the wall is put at the objects.
    cab = obj("Cabinet|+00.55|+00.40|+01.00", (0.55, 0.4, 1.0), (0.5, 0.8, 0.5))
    wide = obj("Floor|+00.00|+00.00|+00.00", (2.0, -0.05, 2.0), (4.0, 0.1, 4.0))
    lay2 = parse_layout({"scene": "FloorPlan2", "objects": [wide, cab]}, "snap")
    assert outer_rect(lay2, 1)[0] == pytest.approx(0.3)


def test_layout_reader_one_line_errors(tmp_path):
    def bad(content, match: str, name: str = "FloorPlan5.json"):
        p = tmp_path / name
        p.write_text(content if isinstance(content, str) else json.dumps(content))
        with pytest.raises(LayoutError, match=match) as e:
            read_layout_file(p)
        assert "\n" not in str(e.value) and name in str(e.value)

    good = {"scene": "FloorPlan5", "objects": [FLOOR]}
    bad('{"scene": "FloorPlan5", "objects": [', "not valid JSON")
    bad({"scene": "FloorPlan5"}, "expected")
    bad({"scene": "FloorPlan6", "objects": [FLOOR]}, "expected 'FloorPlan5'")
    bad({"scene": "FloorPlan5", "objects": []}, "exactly one Floor")
    no_box = dict(ROOM["objects"][1])
    del no_box["aabb"]
    bad({"scene": "FloorPlan5", "objects": [FLOOR, no_box]}, r"object 1: missing field 'aabb'")
    nan = json.loads(json.dumps(ROOM["objects"][1]))
    nan["aabb"]["size"]["x"] = "wide"
    bad({"scene": "FloorPlan5", "objects": [FLOOR, nan]}, r"Chair\|\+01.50\|\+00.00\|\+01.50\): aabb.size")
    bad({"scene": "FloorPlan5", "objects": [FLOOR, FLOOR]}, "exactly one Floor")
    bad({"scene": "FloorPlan5", "objects": [FLOOR, dict(ROOM["objects"][1], oobbCorners=[[0, 0, 0]])]}, "8 corners")
    with pytest.raises(LayoutError, match="no such layout file"):
        read_layout_file(tmp_path / "FloorPlan7.json")
    (tmp_path / "FloorPlan5.json").write_text(json.dumps(good))
    assert read_layout_file(tmp_path / "FloorPlan5.json").scene == "FloorPlan5"
    with pytest.raises(LayoutError, match="no recorded layout"):
        load_layout("FloorPlan31")


def test_pack_round_trip(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    (src / "FloorPlan401.json").write_text(json.dumps(ROOM))
    assert pack_layouts(src, tmp_path / "packed.json.gz") == 1
    import gzip

    rows = json.loads(gzip.decompress((tmp_path / "packed.json.gz").read_bytes()))["scenes"]["FloorPlan401"]
    from tsnav.world.layouts import from_row

    assert tuple(from_row(r, "t") for r in rows) == parse_layout(ROOM, "room").objects


def test_packaged_layouts_and_notice():
    assert len(layout_names()) == 120
    data = resources.files("tsnav.world") / "data"
    notice = (data / "NOTICE").read_text()
    assert "MIT License" in notice and "Apache License" in notice and "Kajiih/rl_ai2thor" in notice
    lay = load_layout("FloorPlan22")
    spec = real_spec("FloorPlan22")
    recorded = {o.object_id for o in lay.objects if o.object_type in TARGET_CATEGORIES}
    assert {o.objectId for o in spec.objects} == recorded and len(recorded) >= 10
    assert spec.split == "test" and spec.room_type == "kitchen"


def test_real_scene_build_is_deterministic(tmp_path):
    from tsnav.data.reader import load_scene
    from tsnav.world.build import BuildConfig, build_dataset

    cfg = BuildConfig(image_size=32, world="ithor-real")
    for d in ("a", "b"):
        build_dataset(tmp_path / d, "ithor-real", ["FloorPlan405"], cfg, workers=1, progress=False)
    a, b = tmp_path / "a" / "FloorPlan405", tmp_path / "b" / "FloorPlan405"
    names = sorted(p.name for p in a.iterdir())
    assert {
        "graph.json",
        "grid.json",
        "visible_object_map_1.5.json",
        "images.hdf5",
        "depth.hdf5",
        "states.hdf5",
        "scene.json",
    } <= set(names)
    match, mismatch, errors = filecmp.cmpfiles(a, b, names, shallow=False)
    assert not mismatch and not errors
    scene = load_scene(a)
    assert scene.room_type == "bathroom" and scene.num_states > 0
    assert set(json.loads((a / "visible_object_map_1.5.json").read_text())) <= {
        o.object_id for o in load_layout("FloorPlan405").objects
    }
    assert Path(a / "scene.json").stat().st_size > 0


def test_paper_scale_runs_on_ithor_real(tmp_path, tiny_world, capsys):
    from tsnav.cli import main
    from tsnav.pipeline.config import SCALES
    from tsnav.pipeline.steps import ensure_world

    assert SCALES["paper"].world == "ithor-real" and SCALES["small"].world == "demo"
    # A missing --data folder: the one-line error names the scale's world and --build-world.
    assert (
        main(
            [
                "experiment",
                "ablation",
                "--scale",
                "paper",
                "--data",
                str(tmp_path / "none"),
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "no such dataset folder" in err and "ithor-real" in err and len(err.strip().splitlines()) == 1
    # An existing dataset of another world is used as it is, with a note.
    assert ensure_world(tiny_world, "ithor-real") == "tiny"
    assert "holds the 'tiny' world" in capsys.readouterr().out
    # With build=True a missing folder is built with the given preset first.
    assert ensure_world(tmp_path / "built", "tiny", build=True, workers=1) == "tiny"
    assert (tmp_path / "built" / "FloorPlan1" / "COMPLETE").exists()
