"""Pose-graph distance fields of the distance reward: hand values, the Python BFS reference, bank layout."""

import numpy as np

from tsnav.constants import CATEGORY_INDEX, LOOK_DOWN, MOVE_AHEAD, NUM_CATEGORIES, ROTATE_RIGHT
from tsnav.data.toy import toy_scene
from tsnav.sim.batch import SceneBank
from tsnav.sim.paths import UNREACHABLE
from tsnav.tsrm.distance import (
    bank_pose_distance,
    distance_delta,
    pose_distance_fields,
    pose_distance_reference,
    pose_nodes,
    scene_pose_distance,
)

BOWL = CATEGORY_INDEX["Bowl"]


def test_hand_values_in_the_toy_room():
    # 2 x 1.5 m room, a bowl at the corner (2.0, 1.5); success = bowl in the 90-degree view within 1.0 m
    sc = toy_scene()
    d = scene_pose_distance(sc)[:, BOWL]
    for h in (0, 30):  # the horizon is projected away
        assert d[sc.index(f"1.00|1.50|90|{h}")] == 0  # 1.0 m away, straight ahead
        assert d[sc.index(f"0.75|1.50|90|{h}")] == 1  # MoveAhead
        # RotateRight twice (0 -> 45 -> 90), MoveAhead; MoveAhead at 0 or 45 hits the wall
        assert d[sc.index(f"0.75|1.50|0|{h}")] == 3
    # categories absent from the scene are unreachable everywhere
    assert (scene_pose_distance(sc)[:, CATEGORY_INDEX["Toaster"]] == UNREACHABLE).all()


def test_pose_counts_as_success_at_any_horizon():
    sc = toy_scene()
    far = sc.index("0.00|0.00|0|30")
    # make the bowl count as within reach only from this state, looking down
    sc.distance[:] = 5.0
    sc.distance[far] = 0.5
    sc.pixels[far] = 100
    d = scene_pose_distance(sc)[:, BOWL]
    assert d[far] == 0 and d[sc.index("0.00|0.00|0|0")] == 0
    assert d[sc.index("0.00|0.00|45|0")] == 1 and d[sc.index("0.00|0.00|315|30")] == 1
    assert d[sc.index("0.00|0.25|180|30")] == 5  # MoveAhead back to (0, 0), then four rotations


def test_matches_python_reference():
    sc = toy_scene(
        3.0,
        2.0,
        objects={"Bowl|1": (3.0, 2.0), "Chair|1": (0.25, 1.0), "Sink|1": (1.5, 0.0)},
        blocked=[(1.5, 1.0), (1.5, 0.75), (1.75, 1.0)],
    )
    fast = scene_pose_distance(sc)
    for name in ("Bowl", "Chair", "Sink"):
        g = CATEGORY_INDEX[name]
        ref = pose_distance_reference(sc.next_state, sc.x, sc.z, sc.rotation, sc.success_mask(g))
        np.testing.assert_array_equal(fast[:, g], ref)
    # and every state of a pose has the same distance
    node_of, n = pose_nodes(sc.x, sc.z, sc.rotation)
    for g in (CATEGORY_INDEX["Bowl"], CATEGORY_INDEX["Chair"]):
        lo = np.full(n, np.iinfo(np.int64).max)
        hi = np.full(n, -1)
        np.minimum.at(lo, node_of, fast[:, g].astype(np.int64))
        np.maximum.at(hi, node_of, fast[:, g].astype(np.int64))
        assert (lo == hi).all()


def test_bank_layout_matches_scenes():
    a = toy_scene(name="A")
    b = toy_scene(3.0, 2.0, objects={"Chair|1": (0.0, 2.0)}, name="B")
    bank = SceneBank([a, b], cache=False)
    d = bank_pose_distance(bank)
    assert d.shape == (bank.num_states, NUM_CATEGORIES)
    np.testing.assert_array_equal(d[: a.num_states], scene_pose_distance(a))
    np.testing.assert_array_equal(d[a.num_states :], scene_pose_distance(b))


def test_delta_telescopes_and_ignores_looks():
    sc = toy_scene()
    d = pose_distance_fields(sc.next_state, sc.x, sc.z, sc.rotation, sc.horizon, sc.category_visible_within(1.0))
    s = sc.index("0.00|0.00|270|0")
    start = s
    total = 0.0
    for a in [ROTATE_RIGHT, LOOK_DOWN, ROTATE_RIGHT, MOVE_AHEAD, ROTATE_RIGHT, MOVE_AHEAD, MOVE_AHEAD, MOVE_AHEAD]:
        n = sc.next_state[s, a]
        step = distance_delta(d, np.array([s]), np.array([n]), np.array([BOWL]))[0]
        if a == LOOK_DOWN:
            assert step == 0
        assert abs(step) <= 1  # one pose-graph edge changes d by at most one
        total += step
        s = n
    assert total == d[start, BOWL] - d[s, BOWL]
    # unreachable ends give no reward
    assert distance_delta(d, np.array([start]), np.array([s]), np.array([CATEGORY_INDEX["Toaster"]]))[0] == 0
