"""Evaluation runner and policies: oracle optimality, stage bookkeeping against a per-episode reference,
detector confidences, determinism, chunking and the ``tsnav eval`` command."""

import json

import numpy as np
import pytest

from sim_helpers import toy_scenes, write_toy_dataset
from tsnav.cli import main
from tsnav.constants import CATEGORY_INDEX
from tsnav.metrics import read_records, summarize
from tsnav.eval.policies import ExplorerPolicy, OraclePolicy, Policy, RandomPolicy, make_policy, scene_waypoints
from tsnav.eval.runner import EvalConfig, evaluate
from tsnav.sim.batch import SceneBank
from tsnav.sim.episodes import make_episodes
from tsnav.sim.paths import UNREACHABLE, bfs_reference
from tsnav.sim.reference import ReferenceController


@pytest.fixture(scope="module")
def bank():
    return SceneBank(toy_scenes(), cache=False)


@pytest.fixture(scope="module")
def episodes(bank):
    return make_episodes(bank, per_room_type=60, seed=3)


def test_oracle_is_optimal(bank, episodes):
    recs = evaluate(bank, episodes, OraclePolicy(bank))
    s = summarize(recs)
    assert s["ALL"]["SR"] == 1.0 and s["ALL"]["SPL"] == 1.0 and s["ALL"]["NSNPL"] == 1.0
    assert s["L>=5"]["episodes"] > 0 and s["L>=5"]["SPL"] == 1.0
    for r in recs:
        assert r.path_length == r.optimal_length and r.steps == r.optimal_length + 1
        assert r.search_path_length + r.pathfinding_path_length == r.path_length
        assert r.optimal_search_length <= r.search_path_length


class Scripted:
    """Plays a fixed (T, B) action table."""

    def __init__(self, table):
        self.table, self.t = table, 0

    def reset(self, mask):
        self.t = 0

    def act(self, obs):
        a = self.table[self.t]
        self.t += 1
        return a


def _reference_records(bank, episodes, table, max_steps, stage):
    """One episode at a time with the lineage-style controller: the slow reference of the runner."""
    out, controllers, searches = [], {}, {}
    for j, e in enumerate(episodes):
        i = bank.scene_index(e.scene)
        c = CATEGORY_INDEX[e.target]
        if i not in controllers:
            controllers[i] = ReferenceController(bank.scenes[i], bank.success_distance)
        if c not in searches:
            searches[c] = bfs_reference(bank.next_state, stage[:, c])
        ctl = controllers[i]
        ctl.reset(e.start, e.target)
        g = lambda key: bank.global_state(i, key)
        entered, sw_step, sw_len, sw_state = bool(stage[g(e.start), c]), 0, 0, g(e.start)
        out_ = None
        for t in range(max_steps):
            out_ = ctl.step(int(table[t, j]), max_steps)
            if not entered and stage[g(out_["state"]), c]:
                entered, sw_step, sw_len, sw_state = True, out_["steps"], out_["path_length"], g(out_["state"])
            if ctl.done:
                break
        search = searches[c][g(e.start)]
        out.append(
            dict(
                success=out_["success"],
                path_length=out_["path_length"],
                steps=out_["steps"],
                entered_pathfinding=entered,
                pathfinding_start_step=sw_step if entered else None,
                search_path_length=sw_len if entered else out_["path_length"],
                optimal_search_length=-1 if search == UNREACHABLE else int(search),
                pathfinding_path_length=out_["path_length"] - sw_len if entered else None,
                optimal_pathfinding_length=int(bank.dist[sw_state, c]) if entered else None,
            )
        )
    return out


def test_stage_bookkeeping_matches_reference(bank, episodes):
    rng = np.random.default_rng(4)
    table = rng.choice(6, size=(25, len(episodes)), p=[0.45, 0.2, 0.2, 0.05, 0.05, 0.05])
    recs = evaluate(bank, episodes, Scripted(table), EvalConfig(max_steps=25))
    ref = _reference_records(bank, episodes, table, 25, bank.stage_mask)
    for r, x in zip(recs, ref):
        for k, v in x.items():
            assert getattr(r, k) == v, k
    assert 0 < sum(r.entered_pathfinding for r in recs) < len(recs)


def test_stage_lengths_one_function_two_ways_for_unreachable_starts():
    """The searching / pathfinding lengths of training statistics and evaluation records come from one function
    (rl/stats.py); the two differ only in what an unreachable optimal search length becomes (kept as
    UNREACHABLE for the statistics, -1 in records), named by ``unreachable``. Values by hand."""
    from tsnav.rl.stats import stage_lengths

    dist = np.array([[3, 0], [1, 2], [0, 5]])  # state x target
    search_dist = np.array([[2, 0], [UNREACHABLE, 1], [0, 4]])
    start, target = np.array([0, 1, 2]), np.array([0, 0, 1])
    L, entered = np.array([7, 4, 6]), np.array([True, False, True])
    switch_length, switch_state = np.array([3, 0, 0]), np.array([1, 1, 2])
    kept = stage_lengths(dist, search_dist, start, target, L, entered, switch_length, switch_state)
    assert kept["search_length"].tolist() == [3, 4, 0]
    assert kept["optimal_search_length"].tolist() == [2, UNREACHABLE, 4]
    assert kept["nav_length"].tolist() == [4, 0, 6]
    assert kept["optimal_nav_length"].tolist() == [1, 0, 5]
    written = stage_lengths(dist, search_dist, start, target, L, entered, switch_length, switch_state, unreachable=-1)
    assert written["optimal_search_length"].tolist() == [2, -1, 4]
    for k in ("search_length", "nav_length", "optimal_nav_length"):
        assert np.array_equal(written[k], kept[k])
    assert all(v.dtype == np.int64 for v in (*kept.values(), *written.values()))


def test_detector_confidence_drives_the_switch(episodes):
    b = SceneBank(toy_scenes(), cache=False)
    conf = np.where(b.in_frame, 0.9, 0.1).astype(np.float32)
    b.set_confidence(conf)
    e = episodes[:40]
    base = evaluate(b, e, OraclePolicy(b))
    assert [r.pathfinding_start_step for r in base] == [
        r.pathfinding_start_step for r in evaluate(SceneBank(toy_scenes(), cache=False), e, OraclePolicy(b))
    ]
    # Exactly C_target does not switch (strictly greater).
    b.set_confidence(np.where(b.in_frame, 0.7, 0.1).astype(np.float32))
    recs = evaluate(b, e, OraclePolicy(b))
    assert not any(r.entered_pathfinding for r in recs) and all(r.optimal_search_length == -1 for r in recs)
    recs = evaluate(b, e, OraclePolicy(b), EvalConfig(c_target=0.65))
    assert [r.pathfinding_start_step for r in recs] == [r.pathfinding_start_step for r in base]


def test_random_policy_determinism_and_chunking(bank, episodes):
    a = evaluate(bank, episodes, RandomPolicy(7))
    b = evaluate(bank, episodes, RandomPolicy(7))
    assert a == b
    ex = ExplorerPolicy(bank)
    assert evaluate(bank, episodes, ex, EvalConfig(batch_size=17)) == evaluate(bank, episodes, ex)
    s = summarize(a)["ALL"]
    assert s["SR"] < 0.5 and s["SPL"] <= s["SR"]


def test_explorer_finds_targets(bank, episodes):
    recs = evaluate(bank, episodes, ExplorerPolicy(bank))
    s = summarize(recs)["ALL"]
    assert s["SR"] >= 0.95 and s["SSR"] >= 0.95
    assert s["SPL"] < 1.0  # it searches first
    assert isinstance(ExplorerPolicy(bank), Policy) and isinstance(RandomPolicy(), Policy)


def test_waypoints_cover():
    rng = np.random.default_rng(0)
    x, z = rng.uniform(0, 5, 300), rng.uniform(0, 4, 300)
    wp = scene_waypoints(x, z, 1.0)
    d = np.hypot(x[:, None] - x[wp][None], z[:, None] - z[wp][None]).min(axis=1)
    assert d.max() <= 1.0 and len(wp) < 40


def test_make_policy_errors(bank):
    with pytest.raises(ValueError, match="unknown policy"):
        make_policy("greedy", bank)
    with pytest.raises(ValueError, match="cannot import"):
        make_policy("no_such_module:f", bank)


def test_eval_command(tmp_path, capsys):
    root = write_toy_dataset(tmp_path / "data")
    eps = tmp_path / "test.json"
    assert main(["episodes", "--data", str(root), "--per-room-type", "20", "--out", str(eps)]) == 0
    out = tmp_path / "run"
    assert main(["eval", "--data", str(root), "--episodes", str(eps), "--policy", "oracle", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "SSSPL" in text and "100.00" in text
    recs = read_records(out / "records.jsonl")
    m = json.loads((out / "metrics.json").read_text())
    assert len(recs) == 40 and m["metrics"]["ALL"]["SPL"] == 1.0 and m["config"]["max_steps"] == 100
    # the learned-agent hook: module:factory
    out2 = tmp_path / "run2"
    assert (
        main(
            [
                "eval",
                "--data",
                str(root),
                "--episodes",
                str(eps),
                "--policy",
                "sim_helpers:oracle_factory",
                "--out",
                str(out2),
            ]
        )
        == 0
    )
    assert read_records(out2 / "records.jsonl") == recs
    assert main(["eval", "--data", str(root), "--episodes", str(eps), "--policy", "nope", "--out", str(out)]) == 2
    assert "unknown policy" in capsys.readouterr().err
    assert read_records(out / "records.jsonl") == recs  # outputs kept on error
    assert main(["eval", "--data", str(root), "--episodes", str(tmp_path / "missing.json"), "--out", str(out)]) == 2
    # the command is evaluate_to_folder: same records, trajectories and metadata (the time apart)
    from tsnav.eval.runner import evaluate_to_folder

    summary = evaluate_to_folder(tmp_path / "direct", root, eps, policy="oracle")
    assert summary == m["metrics"]
    for f in ("records.jsonl", "trajectories.jsonl"):
        assert (tmp_path / "direct" / f).read_bytes() == (out / f).read_bytes(), f
    direct = json.loads((tmp_path / "direct" / "metrics.json").read_text())
    assert {k: v for k, v in direct.items() if k != "seconds"} == {k: v for k, v in m.items() if k != "seconds"}
    assert m["policy"] == "oracle" and m["episodes_file"] == str(eps.resolve()) and m["detections"] is None
