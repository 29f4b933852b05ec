"""Issue 24: the ithor-real rules of version 2 on hand-made layouts, and the fidelity report against real
trajectories (tiny synthetic file, one-line errors)."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from tsnav.cli import main
from tsnav.world.build import BuildConfig, build_dataset
from tsnav.world.fidelity import (
    DRIFT_SHIFTS,
    TrajectoriesError,
    drift_whatifs,
    keeps_all,
    load_trajectories,
    markdown_drift,
    measure,
    parse_trajectories,
    relaid,
    scene_moves,
)
from tsnav.world.layouts import parse_layout
from tsnav.world.navgrid import reachable_positions
from tsnav.world.spec import SceneSpec
from tsnav.world.real import (
    CAPSULE_BOTTOM,
    CLEARANCE,
    SEAT_CLEARANCE,
    TOILET_SIZE,
    WALL_INSET,
    blocks,
    counter_boxes,
    footprints,
    low_clearance,
    outer_rect,
    real_spec,
    spec_from_layout,
)

from test_real_world import obj

FLOOR_ID = "Floor|+00.00|+00.00|+00.00"


def floor(cx=1.5, cz=1.5, sx=3.0, sz=3.0):
    return obj(FLOOR_ID, (cx, -0.05, cz), (sx, 0.1, sz))


SWITCH = obj("LightSwitch|+00.02|+01.30|+01.50", (0.02, 1.3, 1.5), (0.04, 0.15, 0.1), None, ry=90)


def layout(*objects, scene="FloorPlan401"):
    """A 3 x 3 m floor box holding ``objects`` (a light switch on the x = 0 wall when there are none)."""
    return parse_layout({"scene": scene, "objects": [floor(), *(objects or [SWITCH])]}, "hand-made")


# ------------------------------------------------------------------------------------------------ rules
def test_walls_inset_from_the_floor_box():
    """Version 2 puts every wall at least WALL_INSET inside the floor box (the box runs under the walls); a wall
    shown by an object deeper inside stays at the object; version 1 keeps the box's edge."""
    cab = obj("Cabinet|+00.55|+00.40|+01.00", (0.55, 0.4, 1.0), (0.5, 0.8, 0.5))  # its -x face 0.3 m inside
    lay = layout(cab)
    assert outer_rect(lay, 1) == pytest.approx([0.3, 0.0, 3.0, 3.0])
    assert outer_rect(lay, 2) == pytest.approx([0.3, WALL_INSET, 3.0 - WALL_INSET, 3.0 - WALL_INSET])


def test_clearance_by_hand():
    """Empty 3 x 3 m room, version 2: grid points at least CLEARANCE from the walls (inset 0.1) are reachable:
    0.1 + 0.19 = 0.29 <= x <= 2.71, so x in 0.50 .. 2.50 (9 per side); version 1: 0.25 .. 2.75 (11)."""
    lay = layout()
    v1 = spec_from_layout(lay, "bathroom", "train", version=1)
    v2 = spec_from_layout(lay, "bathroom", "train", version=2)
    assert len(reachable_positions(v1)[0]) == 11 * 11
    pos, _ = reachable_positions(v2)
    assert len(pos) == 9 * 9 and pos.min() == 0.5 and pos.max() == 2.5
    assert v2.navigation == {"clearance": CLEARANCE, "sweep_clearance": pytest.approx(0.05)}
    assert v2.generator == {"world": "ithor-real", "version": 2} and v1.navigation is None


def test_agent_stands_exactly_a_capsule_radius_from_a_box():
    """A cabinet whose face lies exactly 0.20 m from a grid point: version 1 (strict 0.20 clearance) loses the
    point, version 2 (0.19: touching is no hit) keeps it, as real agents stand there."""
    # exactly 0.20: face at z = 1.95 from the point (1.5, 1.75)
    cab3 = obj("Cabinet|+01.50|+00.40|+02.15", (1.5, 0.4, 2.15), (0.5, 0.8, 0.4))
    lay3 = layout(cab3)
    pos1 = {tuple(p) for p in reachable_positions(spec_from_layout(lay3, "bathroom", "train", version=1))[0]}
    pos2 = {tuple(p) for p in reachable_positions(spec_from_layout(lay3, "bathroom", "train", version=2))[0]}
    assert (1.5, 1.75) not in pos1 and (1.5, 1.75) in pos2


def test_object_resting_on_a_receptacle_and_the_floor_does_not_block():
    pillow = obj(
        "Pillow|+01.00|+00.50|+01.00",
        (1.0, 0.5, 1.0),
        (0.4, 0.4, 0.4),
        [FLOOR_ID, "Sofa|+01.00|+00.40|+01.20"],
        pickupable=True,
    )
    chair = obj("Chair|+02.00|+00.45|+02.00", (2.0, 0.45, 2.0), (0.5, 0.9, 0.5), [FLOOR_ID])
    desk = obj("Desk|+02.00|+00.40|+00.50", (2.0, 0.4, 0.5), (1.0, 0.8, 0.5), ["Chair|+02.00|+00.45|+02.00", FLOOR_ID])
    lay = layout(pillow, chair, desk)
    p, c, d = lay.objects[1], lay.objects[2], lay.objects[3]
    assert blocks(p, version=1) and not blocks(p, version=2)
    assert blocks(c, version=1) and blocks(c, version=2)
    assert blocks(d, version=1) and blocks(d, version=2)  # not pickupable: a chair touching it carries no desk


def test_low_objects_and_upholstered_seats_keep_a_smaller_clearance():
    """The capsule's rounded bottom: by hand, an object whose top is 0.03 + 0.1 m high is kept
    sqrt(0.19^2 - 0.09^2) = 0.1673 m away; one lower than the capsule's bottom does not block; sofas keep
    SEAT_CLEARANCE. Positions follow: a point 0.17 m from a sofa's face (or from a lying bat) is reachable in
    version 2, not beside a cabinet."""
    assert low_clearance(CAPSULE_BOTTOM + 0.1) == pytest.approx(math.sqrt(0.19**2 - 0.09**2))
    assert low_clearance(0.02) == 0.0 and low_clearance(0.5) == CLEARANCE
    cloth = obj("Cloth|+01.00|+00.01|+01.00", (1.0, 0.01, 1.0), (0.3, 0.02, 0.3), [FLOOR_ID])
    lay = layout(cloth)
    assert blocks(lay.objects[1], version=1) and not blocks(lay.objects[1], version=2)

    def reach(kind, top):
        # a box whose z face lies 0.17 m from the grid point (1.5, 1.75)
        o = obj(f"{kind}|x", (1.5, top / 2, 1.92 + 0.2), (0.6, top, 0.4), [FLOOR_ID])
        spec = spec_from_layout(layout(o), "living_room", "train", version=2)
        pos = {tuple(p) for p in reachable_positions(spec)[0]}
        return (1.5, 1.75) in pos, spec.navigation.get("clearances", {})

    assert reach("Sofa", 0.8) == (True, {"Sofa|x": SEAT_CLEARANCE})
    assert reach("Cabinet", 0.8) == (False, {})
    ok, own = reach("BaseballBat", 0.1)  # top 0.1 m: clearance sqrt(0.19^2 - 0.12^2) = 0.147
    assert ok and own["BaseballBat|x"] == pytest.approx(round(math.sqrt(0.19**2 - 0.12**2), 4))


def test_oversized_toilet_box_is_replaced_by_a_toilet():
    """A toilet box 1.12 m wide across its facing direction (rotation 90: faces +x) becomes a TOILET_SIZE box,
    back on the box's back face (x min), centred across on the pivot from its objectId; a toilet box of a
    toilet's width is kept."""
    big = obj("Toilet|+01.10|+00.00|+01.50", (0.9, 0.47, 1.5), (1.17, 0.95, 1.12), [FLOOR_ID], ry=90)
    small = obj("Toilet|+01.50|+00.00|+00.60", (1.5, 0.5, 0.6), (0.53, 1.04, 0.97), [FLOOR_ID], ry=0)
    lay = layout(big, small)
    t_big, t_small = lay.objects[1], lay.objects[2]
    (cx, cz), (sx, sz), yaw = footprints(lay, t_big, 2)[0]
    back = 0.9 - 1.17 / 2
    assert (sx, sz) == TOILET_SIZE and yaw == 90.0
    assert cx == pytest.approx(back + TOILET_SIZE[1] / 2) and cz == pytest.approx(1.5)
    assert footprints(lay, t_big, 1)[0] == ((0.9, 1.5), (1.12, 1.17), 90.0)
    assert footprints(lay, t_small, 2) == footprints(lay, t_small, 1)


def test_island_turned_off_grid_takes_its_depth_across_the_objects_row():
    """A 45-degree island whose objects stand along its local z axis: version 2 puts the depth along local x
    (the axis the objects spread less over); version 1 took it along local z whatever the objects."""
    counter = obj("CounterTop|+01.50|+00.90|+01.50", (1.5, 0.9, 1.5), (2.0, 0.02, 2.0), None, ry=315)
    cid = counter["objectId"]
    # local z of yaw 315 runs along (x, z) = (-0.707, 0.707): objects on that line through the centre
    things = [
        obj(f"Apple|{i}", (1.5 - d, 1.0, 1.5 + d), (0.1, 0.1, 0.1), [cid]) for i, d in enumerate((-0.5, 0.0, 0.5))
    ]
    lay = layout(counter, *things)
    c = lay.objects[1]
    ((_, (sx1, sz1), _),) = counter_boxes(lay, c, 1)
    ((_, (sx2, sz2), yaw),) = counter_boxes(lay, c, 2)
    diag = 2.0 * math.sqrt(2)
    assert sx2 + sz2 == pytest.approx(diag) and sx2 == pytest.approx(0.6) and yaw == 315
    assert sx1 + sz1 == pytest.approx(diag) and sz1 == pytest.approx(diag / 2)  # version 1: depth along z, capped


def test_diagonal_move_between_reachable_neighbours():
    """Two positions both clear of a thin box's corner, the diagonal between them passing 0.15 m from it:
    version 1 (the path keeps the full clearance) blocks the move, version 2 (0.05 m) lets it through."""
    # a 0.1 x 0.1 post with its corner 0.15 m from the diagonal (1.25, 1.25) -> (1.5, 1.5)
    off = 0.15 / math.sqrt(2)  # the corner sits 0.15 m from the diagonal's midpoint (1.375, 1.375), towards (+x, -z)
    post = obj("Box|post", (1.375 + off + 0.05, 0.4, 1.375 - off - 0.05), (0.1, 0.8, 0.1), [FLOOR_ID])
    lay = layout(post)
    for v, expect in ((1, False), (2, True)):
        spec = spec_from_layout(lay, "bathroom", "train", version=v)
        pos, move = reachable_positions(spec)
        index = {(round(x, 2), round(z, 2)): i for i, (x, z) in enumerate(pos)}
        a, b = index.get((1.25, 1.25)), index.get((1.5, 1.5))
        assert a is not None and b is not None  # both ends 0.23 m from the post
        assert bool(move[a, 1] == b) is expect  # rotation index 1 = heading 45 (+x, +z)


def test_version_1_rebuilds_main_scenes_and_unknown_version_is_refused():
    # Version 1 is the rules of worlds built before issue 24 (FloorPlan409's kept set of 52 positions).
    assert len(reachable_positions(real_spec("FloorPlan409", 1))[0]) == 52
    with pytest.raises(ValueError, match="unknown ithor-real version 7"):
        real_spec("FloorPlan409", 7)


# ------------------------------------------------------------------------------------------------ report
def test_measure_by_hand():
    """Three positions in a row (x = 0, 0.25, 0.5 at z = 0) and moves along +x only; triples by hand."""
    pos = np.array([[0.0, 0.0], [0.25, 0.0], [0.5, 0.0]])
    move = np.full((3, 8), -1)
    move[0, 2], move[1, 2] = 1, 2  # heading 90 (+x)
    triples = [
        ("0.00|0.00|90|0", "MoveAhead", "0.25|0.00|90|0"),  # kept
        ("0.25|0.00|90|0", "MoveAhead", "0.50|0.00|90|0"),  # kept
        ("0.50|0.00|90|0", "MoveAhead", "0.75|0.00|90|0"),  # lost: tsnav lacks 0.75
        ("0.50|0.00|90|30", "MoveAhead", "0.50|0.00|90|30"),  # blocked and blocked (no move from 0.5 at 90)
        ("0.25|0.00|90|0", "RotateLeft", "0.25|0.00|45|0"),
        ("0.00|0.00|90|0", "MoveAhead", "0.00|0.00|90|0"),  # blocked in the real room, tsnav lets it through
    ]
    f = measure("t", pos, move, triples)
    assert (f.positions, f.positions_kept) == (4, 3)
    assert (f.moves, f.moves_kept, f.blocked, f.blocked_kept) == (3, 2, 2, 1)
    assert f.missing == [(3, 0)] and f.lost_moves == [((2, 0), (3, 0))] and f.leaks == [((0, 0), 90)]
    assert f.unvisited == []
    s = f.shares()
    assert s["positions"] == pytest.approx(75.0) and s["blocked_blocked"] == pytest.approx(50.0)


def test_scene_spec_from_json_lays_out_again():
    """A spec written to scene.json and read back (:meth:`SceneSpec.from_json`) gives the same JSON and the same
    reachable positions and moves (the fidelity report's what-ifs start from it)."""
    spec = real_spec("FloorPlan408")
    meta = json.loads(json.dumps({**spec.to_json(), "num_states": 1, "figures": {}}))
    back = SceneSpec.from_json(meta)
    assert json.loads(json.dumps(back.to_json())) == json.loads(json.dumps(spec.to_json()))
    (p0, m0), (p1, m1) = reachable_positions(spec), reachable_positions(back)
    assert np.array_equal(p0, p1) and np.array_equal(m0, m1)


def drift_room():
    """A hand-made bedroom (3 x 3 m floor box, walls inset to 0.1 .. 2.9 except z = 2.765 at the cabinet's back):
    a moveable chair whose box (0.85 .. 1.15) covers real positions, a fixed cabinet whose face (z = 2.465) lies
    0.215 m from the target of a real blocked move, with a drawer inside its box, a ball (pickupable) lying 0.58 m
    from another leak's target."""
    chair = obj("Chair|+01.00|+00.00|+01.00", (1.0, 0.45, 1.0), (0.3, 0.9, 0.3), [FLOOR_ID], moveable=True)
    cab = obj("Cabinet|+02.00|+00.40|+02.61", (2.0, 0.4, 2.615), (0.6, 0.8, 0.3))
    drawer = obj("Drawer|+02.00|+00.60|+02.54", (2.0, 0.6, 2.54), (0.5, 0.2, 0.15))  # inside the cabinet's box
    ball = obj("BasketBall|+01.20|+00.12|+02.25", (1.2, 0.12, 2.25), (0.24, 0.24, 0.24), [FLOOR_ID], pickupable=True)
    lay = layout(chair, cab, drawer, ball, scene="FloorPlan301")
    flags = {o.object_id: {"pickupable": o.pickupable, "moveable": o.moveable} for o in lay.objects}
    triples = [(f"{x:.2f}|1.00|90|0", "MoveAhead", f"{x + 0.25:.2f}|1.00|90|0") for x in (0.5, 0.75, 1.0, 1.25)]
    triples += [
        ("2.00|2.00|0|0", "MoveAhead", "2.00|2.00|0|0"),  # blocked by the cabinet in the real room
        ("0.50|2.00|0|0", "MoveAhead", "0.50|2.00|0|0"),
    ]  # blocked by nothing recorded
    return spec_from_layout(lay, "bedroom", "train"), triples, flags


def test_drift_what_ifs_on_a_hand_made_layout():
    """By hand: the real agents walked (0.5, 1) -> (1.5, 1) through the chair's box: tsnav lacks (0.75, 1), (1, 1)
    and (1.25, 1) (0.1 m from the box, one inside it), so no real move is kept; no shift of at most 0.1 m clears
    them, its removal brings all back. (2, 2) -> (2, 2.25) was blocked in the real room: moving the cabinet 0.04 m
    towards it (0.175 < 0.19) blocks it, 0.02 m (0.195) does not; its drawer moves with it. Nothing recorded
    explains (0.5, 2) -> (0.5, 2.25): the ball, 0.58 m from its target, is named as the suspect."""
    spec, triples, flags = drift_room()
    pos, move = reachable_positions(spec)
    f0 = measure(spec.name, pos, move, triples)
    assert (f0.positions_kept, f0.positions, f0.moves_kept, f0.blocked_kept, f0.blocked) == (4, 7, 0, 0, 2)
    d = drift_whatifs(spec, triples, flags)
    chair, cab = d["objects"]
    assert chair["id"].startswith("Chair|") and chair["moveable"] is True and chair["real_inside"] == 1
    assert chair["missing_near"] == 3 and chair["without"]["positions"] == 100.0
    assert chair["best"]["what_if"] == "removed" and chair["best"]["shift"] is None
    assert chair["best"]["change"] == {"positions_kept": 3, "moves_kept": 4, "blocked_kept": 0}
    assert cab["id"].startswith("Cabinet|") and cab["moveable"] is False and cab["leaks_near"] == 1
    assert cab["parts"] == ["Drawer|+02.00|+00.60|+02.54"] and chair["parts"] == []  # the drawer goes with it
    assert cab["best"]["what_if"] == "moved" and cab["best"]["shift"] == [0.0, -0.04]
    assert cab["best"]["change"] == {"positions_kept": 0, "moves_kept": 0, "blocked_kept": 1}
    w = d["without_drift"]
    assert w["applied"] == [chair["id"], cab["id"]] and w["removed"] == [chair["id"]]
    assert w["shifted"] == {cab["id"]: [0.0, -0.04]}
    assert (w["positions"], w["moves_kept"], w["blocked_blocked"]) == (100.0, 100.0, 50.0)
    (leak,) = d["unexplained_leaks"]
    assert leak["from"] == [0.5, 2.0] and leak["heading"] == 0 and leak["to"] == [0.5, 2.25]
    assert [s["id"] for s in leak["suspects"]] == ["BasketBall|+01.20|+00.12|+02.25"]
    assert leak["suspects"][0]["distance"] == pytest.approx(0.58)
    # the what-ifs leave the spec as it was, and relaid() moves exactly the named object
    assert reachable_positions(spec)[0].shape == pos.shape
    moved = relaid(spec, remove={chair["id"]}, shifts={cab["id"]: (0.0, -DRIFT_SHIFTS[1])})
    assert [f.id for f in moved.furniture if f.id == chair["id"]] == []
    c0 = next(f for f in spec.furniture if f.id == cab["id"]).center
    c1 = next(f for f in moved.furniture if f.id == cab["id"]).center
    assert c1 == pytest.approx((c0[0], c0[1], c0[2] - 0.04))
    md = markdown_drift([{"scene": "FloorPlan301", **f0.to_json(), "drift": d}])
    assert "| FloorPlan301 | Chair|+01.00|+00.00|+01.00 | yes | 1 | 3 / 0 |" in md and "moved (+0.00, -0.04) m" in md
    assert "**without drift** (1 removed, 1 moved)" in md and "BasketBall|+01.20|+00.12|+02.25 (0.58 m)" in md


def test_drift_marks_name_the_objects_on_the_picture():
    """The picture marks what the what-ifs name: the chair (removed, a real position inside) at its own footprint,
    the cabinet with its drawer at theirs and moved 0.04 m to -z (dashed); both are kept together (``*``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from tsnav.world.fidelity import blockers, draw_fidelity, drift_marks

    spec, triples, flags = drift_room()
    pos, move = reachable_positions(spec)
    f0 = measure(spec.name, pos, move, triples)
    d = drift_whatifs(spec, triples, flags)
    bl = blockers(spec)
    chair, cab = drift_marks(d, spec)
    assert chair["label"] == "Chair*: removed, 1 real inside" and chair["moved"] is None
    assert chair["footprints"] == [list(p.exterior.coords)[:-1] for p in bl[chair["id"]][1]]
    assert cab["label"] == "Cabinet*: moved -0.04 z" and len(cab["footprints"]) == 2  # the drawer goes with it
    for fp, mv in zip(cab["footprints"], cab["moved"]):
        np.testing.assert_allclose(mv, [(x, z - 0.04) for x, z in fp], atol=1e-12)
    # an object with neither a gaining what-if nor real positions inside is not marked
    quiet = {**d, "objects": [{**d["objects"][1], "best": None, "real_inside": 0}]}
    assert drift_marks(quiet, spec) == []
    fig = Figure()
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    draw_fidelity(ax, spec.to_json(), f0, pos, triples, drift=d, spec=spec)
    texts = [t.get_text() for t in ax.texts]
    assert "Chair*: removed, 1 real inside" in texts and "Cabinet*: moved -0.04 z" in texts
    labels = ax.get_legend_handles_labels()[1]
    assert any(lab.startswith("object a drift what-if names (2)\n") for lab in labels)


def test_drift_what_if_that_swaps_a_position_is_not_lossless():
    """A what-if that brings one real position back and loses another keeps the counts but not the positions: it
    loses something (the what-ifs compare sets, not counts)."""
    triples = [
        ("0.00|0.00|90|0", "MoveAhead", "0.25|0.00|90|0"),
        ("0.50|0.00|0|0", "RotateLeft", "0.50|0.00|315|0"),
        ("0.75|0.00|0|0", "RotateLeft", "0.75|0.00|315|0"),
    ]

    def fid(*xs):
        move = np.full((len(xs), 8), -1)
        move[0, 2] = 1  # (0, 0) -> (0.25, 0) heading 90
        return measure("s", np.array([[x, 0.0] for x in xs]), move, triples)

    base, swapped, more = fid(0.0, 0.25, 0.5), fid(0.0, 0.25, 0.75), fid(0.0, 0.25, 0.5, 0.75)
    assert [(f.positions_kept, f.moves_kept) for f in (base, swapped, more)] == [(3, 1), (3, 1), (4, 1)]
    assert keeps_all(base, base) and not keeps_all(swapped, base) and not keeps_all(base, swapped)
    assert keeps_all(more, base) and not keeps_all(base, more)


def test_trajectories_one_line_errors(tmp_path):
    def bad(content, match):
        p = tmp_path / "t.json"
        p.write_text(content if isinstance(content, str) else json.dumps(content))
        with pytest.raises(TrajectoriesError, match=match) as e:
            load_trajectories(p)
        assert "\n" not in str(e.value) and "t.json" in str(e.value)

    bad("{", "not valid JSON")
    bad({"format": "x"}, "expected")
    bad({"scenes": {"FloorPlan1": "x"}}, "expected a list")
    bad({"scenes": {"FloorPlan1": [["0.00|0.00|0|0", "MoveAhead"]]}}, "expected \\[state, action, next_state\\]")
    bad({"scenes": {"FloorPlan1": [["0.00|0.00|0|0", "Jump", "0.00|0.00|0|0"]]}}, "unknown action 'Jump'")
    bad({"scenes": {"FloorPlan1": [["0.00|0.00|0", "MoveAhead", "0.00|0.00|0|0"]]}}, "not x\\|z\\|rotation")
    bad({"scenes": {"FloorPlan1": [["0.10|0.00|0|0", "MoveAhead", "0.10|0.00|0|0"]]}}, "off the 0.25 m grid")
    bad({"scenes": {"FloorPlan1": [["0.00|0.00|10|0", "MoveAhead", "0.00|0.00|10|0"]]}}, "rotation 10")
    bad({"scenes": {"FloorPlan1": [["0.00|0.00|0|0", "MoveAhead", "0.25|0.00|0|0"]]}}, "not one grid step ahead")
    with pytest.raises(TrajectoriesError, match="no such trajectories file"):
        load_trajectories(tmp_path / "none.json")
    ok = parse_trajectories({"scenes": {"FloorPlan1": [["0.00|0.00|45|0", "MoveAhead", "0.25|0.25|45|0"]]}}, "ok")
    assert ok == {"FloorPlan1": [("0.00|0.00|45|0", "MoveAhead", "0.25|0.25|45|0")]}


def test_fidelity_report_on_a_built_scene(tmp_path, capsys):
    """Build one small real bathroom without images, write a synthetic trajectories file from its own graph
    (every move kept, a blocked move at its edge, one position it lacks) and check the report against it."""
    cfg = BuildConfig.from_preset("ithor-real", store_images=False, image_size=32)
    build_dataset(tmp_path / "w", "ithor-real", ["FloorPlan408"], cfg, workers=1, progress=False)
    from tsnav.data.reader import load_scene

    scene = load_scene(tmp_path / "w" / "FloorPlan408")
    meta = scene.meta
    assert meta["generator"] == {"world": "ithor-real", "version": 2}
    fig = meta["figures"]
    assert fig["positions"] == meta["num_positions"] and fig["states"] == meta["num_states"] == scene.num_states
    assert fig["target_objects"] == len(meta["objects"]) and set(fig["targets_seen"]) <= set(fig["targets_present"])
    pos, move = scene_moves(scene)
    assert (pos, move) is not None and len(pos) == fig["positions"]
    ref_pos, ref_move = reachable_positions(real_spec("FloorPlan408"))
    assert np.array_equal(pos, ref_pos) and np.array_equal(move, ref_move)  # the graph read back = the navgrid's
    key = lambda p, r: f"{p[0]:.2f}|{p[1]:.2f}|{r}|0"  # noqa: E731
    p0 = next(i for i in range(len(pos)) if move[i, 2] >= 0)
    edge = next(i for i in range(len(pos)) if move[i, 0] < 0 and i not in (p0, move[p0, 2]))
    far = pos[:, 0].max() + 5.0
    triples = [
        [key(pos[p0], 90), "MoveAhead", key(pos[move[p0, 2]], 90)],
        [key(pos[edge], 0), "MoveAhead", key(pos[edge], 0)],
        [key((far, 0.0), 0), "RotateRight", key((far, 0.0), 45)],
    ]
    tfile = tmp_path / "traj.json"
    tfile.write_text(json.dumps({"scenes": {"FloorPlan408": triples, "FloorPlan999": []}}))
    assert (
        main(
            [
                "world",
                "fidelity",
                "--data",
                str(tmp_path / "w"),
                "--trajectories",
                str(tfile),
                "--out",
                str(tmp_path / "rep"),
            ]
        )
        == 0
    )
    doc = json.loads((tmp_path / "rep" / "fidelity.json").read_text())
    s = doc["scenes"][0]
    assert s["counts"]["positions"] == 4 and s["counts"]["positions_kept"] == 3
    assert s["moves_kept"] == 100.0 and s["blocked_blocked"] == 100.0
    assert s["missing_positions"] == [{"position": [far, 0.0], "causes": ["wall"]}]
    # the drift what-ifs: the missing position is off the floor (no object behind it), the blocked move is blocked
    assert s["drift"]["objects"] == [] and s["drift"]["unexplained_leaks"] == []
    assert s["drift"]["without_drift"]["applied"] == [] and doc["summary"]["without_drift"]["positions"] == 75.0
    md = (tmp_path / "rep" / "fidelity.md").read_text()
    assert "## Pose drift: what-ifs" in md and "fitted to these same trajectories" in md and "not a measurement" in md
    assert "fitted to these trajectories, not measured" in capsys.readouterr().out
    assert (
        main(
            [
                "world",
                "fidelity",
                "--data",
                str(tmp_path / "w"),
                "--trajectories",
                str(tfile),
                "--no-pictures",
                "--no-drift",
                "--out",
                str(tmp_path / "rep2"),
            ]
        )
        == 0
    )
    doc2 = json.loads((tmp_path / "rep2" / "fidelity.json").read_text())
    assert "drift" not in doc2["scenes"][0] and "without_drift" not in doc2["summary"]
    assert not (tmp_path / "rep2" / "FloorPlan408.png").exists()
    # a scene.json that does not give back its own graph (its furniture dropped) gets no what-ifs, and says why
    shutil.copytree(tmp_path / "w" / "FloorPlan408", tmp_path / "w3" / "FloorPlan408")
    sj = tmp_path / "w3" / "FloorPlan408" / "scene.json"
    sj.write_text(json.dumps({**json.loads(sj.read_text()), "furniture": []}))
    assert (
        main(["world", "fidelity", "--data", str(tmp_path / "w3"), "--trajectories", str(tfile), "--no-pictures"]) == 0
    )
    s3 = json.loads((tmp_path / "w3" / "fidelity" / "fidelity.json").read_text())["scenes"][0]
    assert s3["drift"] is None and "does not lay out again" in s3["drift_note"]
    assert doc["absent"] == ["FloorPlan999"]
    assert (tmp_path / "rep" / "FloorPlan408.png").stat().st_size > 1000
    assert "| FloorPlan408 | 75.0 (3/4)" in (tmp_path / "rep" / "fidelity.md").read_text()
    # one-line errors from the command
    capsys.readouterr()
    (tmp_path / "bad.json").write_text("[1, 2")
    assert main(["world", "fidelity", "--data", str(tmp_path / "w"), "--trajectories", str(tmp_path / "bad.json")]) == 2
    err = capsys.readouterr().err
    assert "not valid JSON" in err and err.count("\n") == 1
    (tmp_path / "other.json").write_text(json.dumps({"scenes": {"FloorPlan1": []}}))
    assert (
        main(["world", "fidelity", "--data", str(tmp_path / "w"), "--trajectories", str(tmp_path / "other.json")]) == 2
    )
    assert "none of its 1 scenes" in capsys.readouterr().err
    assert main(["world", "fidelity", "--data", str(tmp_path / "w")]) == 2
    assert main(["world", "--preset", "tiny", "--world-version", "1", "--out", str(tmp_path / "x")]) == 2
    # a version 2 room in the folder: building version 1 into it is refused (the world would mix versions)
    capsys.readouterr()
    assert (
        main(
            [
                "world",
                "--preset",
                "ithor-real",
                "--world-version",
                "1",
                "--scenes",
                "FloorPlan408",
                "--no-images",
                "--size",
                "32",
                "--out",
                str(tmp_path / "w"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "built with ithor-real version 2" in err and "--world-version 2" in err and err.count("\n") == 1
