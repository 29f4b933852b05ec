"""Shortest paths: batched distance fields vs networkx and the queue BFS; optimal actions; the cache."""

import networkx as nx
import numpy as np
import pytest

from sim_helpers import toy_scenes, write_scene_folder
from tsnav.constants import CATEGORY_INDEX, DONE
from tsnav.data.reader import load_scene
from tsnav.sim import paths
from tsnav.sim.paths import (
    UNREACHABLE,
    bfs_reference,
    cached_distance_fields,
    distance_fields,
    multi_source_bfs,
    optimal_action,
    optimal_action_targets,
    scene_distance_fields,
    shortest_path_actions,
)
from tsnav.sim.reference import scene_graph


@pytest.fixture(scope="module")
def scene():
    return toy_scenes()[0]


def test_distance_fields_match_single_bfs_and_reference(scene):
    succ = scene.category_visible_within(1.0)
    d = distance_fields(scene.next_state, succ)
    assert d.shape == succ.shape and d.dtype == np.int32
    for c in range(succ.shape[1]):
        ref = bfs_reference(scene.next_state, succ[:, c])
        assert np.array_equal(d[:, c], ref)
        assert np.array_equal(d[:, c], multi_source_bfs(scene.next_state, succ[:, c]))
    absent = [c for c in range(22) if c not in scene.categories_present()]
    assert (d[:, absent] == UNREACHABLE).all()


def test_bfs_equals_networkx_on_sampled_pairs(scene):
    g = scene_graph(scene)
    keys = scene.keys
    rng = np.random.default_rng(1)
    for t in rng.choice(scene.num_states, 15, replace=False):
        d = multi_source_bfs(scene.next_state, np.array([t]))
        to_t = nx.single_source_shortest_path_length(g.reverse(copy=False), keys[t])
        for s in rng.choice(scene.num_states, 40, replace=False):
            expect = to_t.get(keys[s], UNREACHABLE)
            assert d[s] == expect


def test_success_distance_equals_networkx_min_over_success_states(scene):
    c = CATEGORY_INDEX["Bowl"]
    succ = scene.success_mask(c)
    g = scene_graph(scene)
    d = scene_distance_fields(scene, 1.0, cache=False)[:, c]
    # Multi-source BFS == shortest path from a virtual sink fed by every success state.
    g.add_edges_from((k, "SINK") for k in scene.keys[succ])
    lengths = nx.single_source_shortest_path_length(g.reverse(copy=False), "SINK")
    expect = np.array([lengths.get(k, UNREACHABLE + 1) - 1 for k in scene.keys.tolist()])
    assert np.array_equal(d, expect)
    assert d.max() > 5  # a non-trivial room


def test_optimal_actions_walk_down_the_field(scene):
    c = CATEGORY_INDEX["Chair"]
    dist = scene_distance_fields(scene, 1.0, cache=False)
    rng = np.random.default_rng(2)
    starts = rng.choice(np.flatnonzero(dist[:, c] < UNREACHABLE), 50, replace=False)
    a = optimal_action(scene.next_state, dist[:, c], starts)
    a2 = optimal_action_targets(scene.next_state, dist, starts, np.full(50, c))
    assert np.array_equal(a, a2)
    for s in starts:
        acts = shortest_path_actions(scene.next_state, dist[:, c], int(s))
        assert len(acts) == dist[s, c] and DONE not in acts
        t = int(s)
        for x in acts:
            t = int(scene.next_state[t, x])
        assert scene.success_mask(c)[t]
    ok = dist[:, c] == 0
    assert (optimal_action(scene.next_state, dist[:, c], np.flatnonzero(ok)) == DONE).all()


def test_unreachable_is_reported():
    nxt = np.array([[0, 0], [0, 1], [2, 2]])  # 1 -> 0; 2 isolated
    d = multi_source_bfs(nxt, np.array([0]))
    assert d.tolist() == [0, 1, UNREACHABLE]
    assert optimal_action(nxt, d, np.array([2]), done_action=1)[0] == -1
    with pytest.raises(ValueError, match="cannot reach"):
        shortest_path_actions(nxt, d, 2)


def test_scene_cache_written_reused_and_invalidated(tmp_path, monkeypatch):
    folder = write_scene_folder(toy_scenes()[1], tmp_path / "ToyB")
    scene = load_scene(folder)
    d1 = scene_distance_fields(scene, 1.0)
    cache = folder / "shortest_paths_1.00m.npz"
    assert cache.exists()
    assert not list(folder.glob("*.tmp"))
    calls = []
    real = paths.distance_fields
    monkeypatch.setattr(paths, "distance_fields", lambda *a: calls.append(1) or real(*a))
    assert np.array_equal(scene_distance_fields(scene, 1.0), d1) and not calls  # read from the cache
    d15 = scene_distance_fields(scene, 1.5)
    assert len(calls) == 1 and (folder / "shortest_paths_1.50m.npz").exists()
    assert (d15 <= d1).all()  # a larger success region is never farther
    # A changed graph invalidates the cache.
    scene.next_state[0, 0] = 1 if scene.next_state[0, 0] != 1 else 2
    scene_distance_fields(scene, 1.0)
    assert len(calls) == 2
    # A corrupt cache is recomputed.
    cache.write_bytes(b"garbage")
    assert np.array_equal(
        cached_distance_fields(scene.next_state, scene.category_visible_within(1.0), cache),
        distance_fields(scene.next_state, scene.category_visible_within(1.0)),
    )
