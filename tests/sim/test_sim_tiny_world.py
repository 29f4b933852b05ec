"""The simulator, shortest paths, episodes, Gymnasium env and evaluation on the rendered `tiny` world."""

import json
import shutil

import gymnasium as gym
import networkx as nx
import numpy as np
import pytest
from networkx.readwrite import json_graph

import tsnav.sim  # noqa: F401
from tsnav.cli import main
from tsnav.data.reader import list_scenes, load_scene
from tsnav.metrics import read_records, summarize
from tsnav.eval.policies import ExplorerPolicy, OraclePolicy
from tsnav.eval.runner import evaluate
from tsnav.pipeline.steps import ensure_oracle_detections
from tsnav.sim.batch import BatchEnv, SceneBank
from tsnav.sim.episodes import TrainingSampler, make_episodes
from tsnav.sim.gym_env import ENV_ID
from tsnav.sim.paths import UNREACHABLE, scene_distance_fields


@pytest.fixture(scope="module")
def bank(tiny_scenes):
    return SceneBank(tiny_scenes, cache=False)


@pytest.fixture(scope="module")
def episodes(bank):
    return make_episodes(bank, per_room_type=40, seed=0)


def test_bfs_equals_networkx_on_graph_json(tiny_world, bank):
    rng = np.random.default_rng(0)
    for i, path in enumerate(list_scenes(tiny_world)[:2]):
        g = json_graph.node_link_graph(json.loads((path / "graph.json").read_text()), directed=True, edges="links")
        succ = bank.success[bank.offsets[i] : bank.offsets[i + 1]]
        dist = bank.dist[bank.offsets[i] : bank.offsets[i + 1]]
        keys = bank.scenes[i].keys
        for c in np.flatnonzero(succ.any(axis=0))[:3]:
            h = g.copy()
            h.add_edges_from((k, "SINK") for k in keys[succ[:, c]])
            lengths = nx.single_source_shortest_path_length(h.reverse(copy=False), "SINK")
            for s in rng.choice(len(keys), 100, replace=False):
                assert dist[s, c] == lengths.get(keys[s], UNREACHABLE + 1) - 1


def test_oracle_perfect_and_explorer_sane(bank, episodes):
    assert len({e.room_type for e in episodes}) >= 2
    recs = evaluate(bank, episodes, OraclePolicy(bank))
    s = summarize(recs)
    assert s["ALL"]["SR"] == 1.0 and s["ALL"]["SPL"] == 1.0
    assert all(r.path_length == r.optimal_length for r in recs)
    ex = summarize(evaluate(bank, episodes, ExplorerPolicy(bank)))["ALL"]
    assert ex["SR"] >= 0.5 and ex["SSR"] >= ex["SR"]


def test_training_rollout_is_deterministic(bank):
    def run():
        env = BatchEnv(bank, 64, sampler=TrainingSampler(bank), max_steps=30, seed=1)
        obs = env.reset()
        rng = np.random.default_rng(1)
        out = []
        for _ in range(40):
            obs, r, term, trunc, info = env.step(rng.integers(0, 6, 64))
            assert not (term & trunc).any()
            out.append(obs["state"])
        return np.stack(out)

    assert np.array_equal(run(), run())


def test_gym_env_on_rendered_scenes(tiny_world):
    ensure_oracle_detections(tiny_world, "oracle")
    env = gym.make(ENV_ID, data=str(tiny_world), split=None, max_steps=20, detections="oracle")
    obs, info = env.reset(seed=0)
    assert obs["rgb"].shape == (64, 64, 3) and obs["rgb"].any()  # real frames
    assert obs["depth"].dtype == np.float16 and (obs["depth"] > 0).any()  # as stored (standard layout)
    obs, *_ = env.step(2)
    assert env.observation_space.contains(obs)
    env.close()


def test_path_cache_in_scene_folder(tiny_world, tmp_path):
    src = list_scenes(tiny_world)[0]
    folder = shutil.copytree(src, tmp_path / src.name)
    scene = load_scene(folder)
    d = scene_distance_fields(scene)
    assert (folder / "shortest_paths_1.00m.npz").exists()
    assert np.array_equal(scene_distance_fields(load_scene(folder)), d)


def test_commands_on_tiny_world(tiny_world, tmp_path, capsys):
    eps = tmp_path / "eps.json"
    splits = {json.loads((p / "scene.json").read_text()).get("split") for p in list_scenes(tiny_world)}
    split = "test" if "test" in splits else sorted(splits)[0]
    assert (
        main(["episodes", "--data", str(tiny_world), "--split", split, "--per-room-type", "10", "--out", str(eps)]) == 0
    )
    out = tmp_path / "run"
    assert (
        main(["eval", "--data", str(tiny_world), "--episodes", str(eps), "--policy", "oracle", "--out", str(out)]) == 0
    )
    recs = read_records(out / "records.jsonl")
    assert recs and all(r.success for r in recs)
