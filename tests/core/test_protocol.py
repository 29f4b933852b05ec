"""Success protocols (tsnav.protocol): the masks against a slow reading of the visibility map, the episodes and
metrics each protocol keeps, and the protocol carried through episode lists, runs and evaluations (issue 23)."""

import json

import numpy as np
import pytest

from tsnav.cli import main
from tsnav.data.lineage import visibility_map_success_reference
from tsnav.data.reader import list_scenes
from tsnav.errors import CommandError
from tsnav.eval.policies import OraclePolicy
from tsnav.eval.runner import evaluate, resolve_protocol
from tsnav.metrics import EpisodeRecord, metric_values, summarize
from tsnav.protocol import check_protocol, protocol_line
from tsnav.rl.config import TrainConfig
from tsnav.sim.batch import SceneBank, SimConfig, SparseReward
from tsnav.sim.episodes import EpisodeConfig, allowed_targets, make_env, make_episodes, read_episodes, valid_starts
from tsnav.sim.paths import UNREACHABLE


@pytest.fixture(scope="module")
def banks(tiny_scenes):
    return {p: SceneBank(tiny_scenes, cache=False, protocol=p) for p in ("paper", "lineage")}


def test_lineage_mask_is_the_visibility_map_read_per_state(tiny_world, tiny_scenes):
    """The array mask equals the lineage's judge done by hand: per state key, any id of the type listed."""
    for path, scene in zip(list_scenes(tiny_world), tiny_scenes):
        ref = visibility_map_success_reference(path, scene.keys)
        got = scene.success_table("lineage")
        assert got.shape == ref.shape and got.any()
        np.testing.assert_array_equal(got, ref)


def test_paper_mask_and_how_the_protocols_relate_in_built_worlds(tiny_scenes):
    for scene in tiny_scenes:
        paper, lineage = scene.success_table("paper"), scene.success_table("lineage")
        np.testing.assert_array_equal(paper, scene.category_visible_within(1.0))
        # tsnav's writer lists an object when it shows min_pixels within 1.5 m (floor plane): the map is the
        # paper rule at 1.5 m, so every paper success state is a lineage one
        np.testing.assert_array_equal(lineage, scene.category_visible_within(1.5))
        assert not (paper & ~lineage).any()
    assert any((s.success_table("lineage") & ~s.success_table("paper")).any() for s in tiny_scenes)


def test_bank_success_and_distances_follow_the_protocol(banks):
    paper, lineage = banks["paper"], banks["lineage"]
    assert paper.protocol == "paper" and lineage.protocol == "lineage"
    assert lineage.success.sum() > paper.success.sum()
    for bank in (paper, lineage):  # L* = 0 exactly at the success states
        reach = bank.dist < UNREACHABLE
        np.testing.assert_array_equal((bank.dist == 0) & reach, bank.success & reach)
    assert (lineage.dist <= paper.dist).all()  # more success states, never longer paths


def test_lineage_keeps_start_success_episodes(banks):
    for name, bank in banks.items():
        t = valid_starts(bank)
        starts_succeed = bank.success[t.starts, np.repeat(t.pair_target, t.counts)]
        ok = bank.success & (bank.dist < UNREACHABLE) & allowed_targets(bank, EpisodeConfig())[bank.scene_of]
        if name == "paper":
            assert not starts_succeed.any()
        else:
            assert starts_succeed.sum() == ok.sum() > 0  # every start-success (state, target) is a valid start
    # asked explicitly, either protocol does either
    assert bank_starts(banks["paper"], True) > bank_starts(banks["paper"], False)
    eps = make_episodes(banks["lineage"], per_room_type=400, seed=0)
    assert any(e.optimal_length == 0 for e in eps)


def bank_starts(bank, keep):
    return len(valid_starts(bank, EpisodeConfig(keep_start_success=keep)).starts)


def rec(success, L, Lstar, steps=None):
    return EpisodeRecord(success=success, path_length=L, optimal_length=Lstar, steps=steps or L + 1)


def test_lineage_spl_and_long_subset_by_hand():
    # start already sees the target: Done at once, and after two steps; a normal success; a failure
    records = [rec(True, 0, 0), rec(True, 2, 0), rec(True, 9, 4), rec(False, 100, 6, 100)]
    paper = summarize(records, protocol="paper")
    lineage = summarize(records, protocol="lineage")
    assert paper["ALL"]["SR"] == lineage["ALL"]["SR"] == 0.75
    # paper: L*/max(L, L*): 1 (0/0), 0, 4/9, 0
    assert paper["ALL"]["SPL"] == pytest.approx((1 + 0 + 4 / 9) / 4)
    # lineage's compute_spl: best_path_len / eps_len = (L*+1)/(L+1): 1/1, 1/3, 5/10, 0
    assert lineage["ALL"]["SPL"] == pytest.approx((1 + 1 / 3 + 0.5) / 4)
    # L>=5: paper L* >= 5 -> only the failure; lineage best_path_len = L*+1 >= 5 -> L* = 4 and 6
    assert paper["L>=5"]["episodes"] == 1 and lineage["L>=5"]["episodes"] == 2
    assert lineage["L>=5"]["SR"] == 0.5 and lineage["L>=5"]["SPL"] == pytest.approx(0.25)
    assert lineage["protocol"] == "lineage" and paper["protocol"] == "paper"
    v = metric_values([1], [0], [3], [3], [0], [0], [0], [0], protocol="lineage")
    assert v["SPL"] == 1.0


def test_oracle_on_lineage_episodes_counts_start_success(banks):
    bank = banks["lineage"]
    eps = make_episodes(bank, per_room_type=400, seed=0)
    recs = evaluate(bank, eps, OraclePolicy(bank))
    s = summarize(recs, protocol="lineage")
    assert s["ALL"]["SR"] == 1.0 and s["ALL"]["SPL"] == pytest.approx(1.0)
    zero = [r for r in recs if r.optimal_length == 0]
    assert zero and all(r.success and r.path_length == 0 and r.steps == 1 for r in zero)
    assert all(r.optimal_length >= 4 for r in eps_long(recs))


def eps_long(recs):
    from tsnav.metrics import long_episode

    return [r for r in recs if long_episode(r.optimal_length, 5, "lineage")]


def test_done_success_and_reward_use_the_protocol_mask(banks):
    """Done at a state that succeeds under lineage but not under paper: success (and the +5) only under lineage."""
    paper, lineage = banks["paper"], banks["lineage"]
    s, c = np.argwhere(lineage.success & ~paper.success & (paper.dist < UNREACHABLE))[0]
    for bank, want in ((paper, False), (lineage, True)):
        env = make_env(bank, 1, SimConfig(protocol=bank.protocol, autoreset=False), reward_fn=SparseReward())
        env.reset(episodes=(np.array([bank.scene_of[s]]), np.array([c]), np.array([s])))
        _, reward, _, _, info = env.step(np.array([5]))
        assert bool(info["success"][0]) == want
        assert reward[0] == pytest.approx(-0.01 + (5.0 if want else 0.0))
    with pytest.raises(ValueError, match="protocol"):
        make_env(lineage, 1, SimConfig(protocol="paper"))


def test_protocol_names_and_header():
    assert check_protocol(None) == "paper"
    with pytest.raises(ValueError, match="unknown success protocol 'bogus'"):
        check_protocol("bogus")
    with pytest.raises(ValueError, match="protocol"):
        TrainConfig(protocol="Lineage")
    assert protocol_line("lineage", "paper").startswith("protocol: lineage (agent trained under paper)")
    assert TrainConfig(protocol="lineage").to_dict()["protocol"] == "lineage"


def test_run_protocol_mismatch_is_refused_unless_asked(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"train": {"protocol": "paper"}}))
    old = tmp_path / "old"
    old.mkdir()
    (old / "config.json").write_text(json.dumps({"train": {}}))  # a run from before protocols: paper
    lineage_meta = {"protocol": "lineage"}
    with pytest.raises(CommandError, match="trained under the paper protocol.*--protocol lineage"):
        resolve_protocol(lineage_meta, "val.json", run)
    assert resolve_protocol(lineage_meta, "val.json", run, "lineage") == ("lineage", "paper")
    assert resolve_protocol({}, "val.json", old) == ("paper", "paper")
    with pytest.raises(CommandError, match="drawn under the lineage protocol"):
        resolve_protocol(lineage_meta, "val.json", run, "paper")
    assert resolve_protocol(lineage_meta, "val.json") == ("lineage", None)


def test_commands_record_and_print_the_protocol(tiny_world, tmp_path, capsys):
    splits = {json.loads((p / "scene.json").read_text()).get("split") for p in list_scenes(tiny_world)}
    split = "test" if "test" in splits else sorted(splits)[0]
    eps = tmp_path / "lineage.json"
    assert (
        main(
            [
                "episodes",
                "--data",
                str(tiny_world),
                "--split",
                split,
                "--per-room-type",
                "200",
                "--protocol",
                "lineage",
                "--out",
                str(eps),
            ]
        )
        == 0
    )
    episodes, meta = read_episodes(eps)
    assert meta["protocol"] == "lineage" and any(e.optimal_length == 0 for e in episodes)
    assert "start already succeeds" in capsys.readouterr().out
    out = tmp_path / "ev"
    assert (
        main(["eval", "--data", str(tiny_world), "--episodes", str(eps), "--policy", "oracle", "--out", str(out)]) == 0
    )
    printed = capsys.readouterr().out
    assert "protocol: lineage" in printed
    m = json.loads((out / "metrics.json").read_text())
    assert m["protocol"] == "lineage" and m["metrics"]["protocol"] == "lineage" and m["trained_protocol"] is None
    # a bad name: one line, nothing written
    bad = tmp_path / "bad.json"
    assert (
        main(["episodes", "--data", str(tiny_world), "--split", split, "--protocol", "bogus", "--out", str(bad)]) == 2
    )
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "unknown success protocol 'bogus'" in err and not bad.exists()
    assert (
        main(
            [
                "eval",
                "--data",
                str(tiny_world),
                "--episodes",
                str(eps),
                "--policy",
                "oracle",
                "--protocol",
                "paper",
                "--out",
                str(tmp_path / "x"),
            ]
        )
        == 2
    )
    assert "drawn under the lineage protocol" in capsys.readouterr().err


def test_tsrm_distance_term_follows_the_protocol(banks, tiny_scenes):
    """The TSRM reward's distance fields come from the bank's success mask: under lineage they equal the slow
    reference's BFS towards the visibility map's states, and the distance term matches the reference's."""
    from tsnav.tsrm.distance import bank_pose_distance
    from sim_helpers import StagedReward
    from tsnav.tsrm.reward import RewardConfig, TSRMReward, TSRMRewardReference

    bank = banks["lineage"]
    d = bank_pose_distance(bank)
    sc = tiny_scenes[0]
    lo = bank.offsets[0]
    cfg = RewardConfig(variant="distance")
    fast = StagedReward(TSRMReward(bank, cfg))
    targets = np.flatnonzero(sc.success_table("lineage").any(axis=0))[:3]
    rng = np.random.default_rng(0)
    for c in targets:
        ref = TSRMRewardReference(sc, cfg, protocol="lineage")
        start = int(rng.integers(sc.num_states))
        ref.reset(int(c), start)
        np.testing.assert_array_equal(ref.term["distance"]._dist_cache[int(c)], d[lo : lo + sc.num_states, c])
        fast.reset(np.ones(1, bool), np.zeros(1, np.int64), np.array([c]), np.array([start + lo]))
        s = start
        for a in rng.choice(5, 15):
            new = int(sc.next_state[s, a])
            _, tf = fast.step(
                np.array([s + lo]),
                np.array([a]),
                np.array([new + lo]),
                np.zeros(1, bool),
                np.zeros(1, bool),
                np.zeros(1, bool),
            )
            _, tr = ref.step(s, int(a), new, False, False, False)
            assert tf["distance"][0] == pytest.approx(tr["distance"], abs=1e-6)
            s = new
