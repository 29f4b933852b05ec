"""The stage switch (paper III-B): the batched StageSwitch against the rule written out per recorded path."""

from __future__ import annotations

import numpy as np
import pytest

from sim_helpers import toy_scenes
from tsnav.constants import C_TARGET, NUM_ACTIONS, NUM_CATEGORIES
from tsnav.sim.batch import BatchEnv, SceneBank
from tsnav.sim.episodes import TrainingSampler
from tsnav.sim.stage import StageSwitch, above_threshold, switch_frame


def test_the_paper_threshold_and_a_strict_comparison():
    assert C_TARGET == 0.7
    assert above_threshold(np.array([0.69, 0.7, 0.71])).tolist() == [False, False, True]
    assert switch_frame(np.array([0.1, 0.8, 0.2])) == 1
    assert switch_frame(np.array([0.9, 0.1])) == 0  # the start frame counts
    assert switch_frame(np.array([0.1, 0.7])) == -1
    assert switch_frame(np.array([0.1, 0.5]), c_target=0.4) == 1


@pytest.mark.parametrize("c_target", [0.3, C_TARGET])
def test_batched_switch_matches_the_rule_on_recorded_paths(c_target):
    """Random walks with auto-reset; every finished episode's switch frame, step, length and state agree with
    :func:`switch_frame` applied to the frames it went through."""
    bank = SceneBank(toy_scenes(), cache=False)
    rng = np.random.default_rng(0)
    conf = rng.random((bank.num_states, NUM_CATEGORIES)).astype(np.float32) ** 4  # few frames above
    B = 6
    env = BatchEnv(bank, B, sampler=TrainingSampler(bank), max_steps=12, autoreset=True, seed=1)
    obs = env.reset(seed=1)
    sw = StageSwitch(bank, c_target, confidence=conf, num_envs=B)
    sw.reset(np.ones(B, bool), obs["state"], obs["target"])
    frames = [[int(s)] for s in obs["state"]]
    lengths = [[0] for _ in range(B)]
    checked = 0
    for _ in range(200):
        before = [(sw.entered[b], sw.switch_step[b], sw.switch_length[b], sw.switch_state[b]) for b in range(B)]
        obs, _, term, trunc, info = env.step(rng.integers(0, NUM_ACTIONS, B))
        sw.update(info["final_state"], info["steps"], info["path_length"], active=info["active"])
        for b in range(B):
            frames[b].append(int(info["final_state"][b]))
            lengths[b].append(int(info["path_length"][b]))
            g = int(sw.target[b])
            f = switch_frame(conf[frames[b], g], c_target)
            assert sw.entered[b] == (f >= 0)
            assert sw.switch_step[b] == f
            assert sw.switch_length[b] == (lengths[b][f] if f >= 0 else 0)
            assert sw.switch_state[b] == (frames[b][f] if f >= 0 else frames[b][0])
            if f >= 0 and before[b][0]:
                assert before[b][1:] == (sw.switch_step[b], sw.switch_length[b], sw.switch_state[b])  # for good
        fin = term | trunc
        if fin.any():
            checked += int(fin.sum())
            sw.reset(fin, obs["state"], obs["target"])
            for b in np.flatnonzero(fin):
                frames[b], lengths[b] = [int(obs["state"][b])], [0]
    assert checked > 50


def test_rejects_a_bad_threshold_or_table():
    bank = SceneBank(toy_scenes(), cache=False)
    with pytest.raises(ValueError, match="c_target"):
        StageSwitch(bank, 1.5)
    with pytest.raises(ValueError, match="shape"):
        StageSwitch(bank, confidence=np.zeros((3, NUM_CATEGORIES)))


def test_bank_stage_mask_is_the_switch_rule():
    """``SceneBank.stage_mask`` (searching lengths, SSSPL) is the switch's own table: strictly above C_target."""
    for c_target in (0.5, C_TARGET):
        bank = SceneBank(toy_scenes(), cache=False, c_target=c_target)
        assert np.array_equal(bank.stage_mask, bank.in_frame)  # no detector: ground truth 1.0 / 0.0
        conf = np.random.default_rng(2).choice(
            np.float32([0.2, 0.5, 0.7, 0.71, 0.9]), (bank.num_states, NUM_CATEGORIES)
        )
        bank.set_confidence(conf)
        assert np.array_equal(bank.stage_mask, StageSwitch(bank).switches)
        assert np.array_equal(bank.stage_mask, conf > c_target)
        assert not bank.stage_mask[conf == np.float32(c_target)].any()


def test_one_stage_switch_per_env_shared_with_the_reward():
    """Training keeps one StageSwitch per env: the env's, whose stage the TSRM reward is handed (it keeps none).
    The stage the env reports in ``info`` (and the training statistics read) equals that of a separate switch
    driven by the env's steps, as rl/stats kept before; episodes finish with the same stage figures."""
    from tsnav.rl.stats import EpisodeStats
    from tsnav.tsrm.reward import TSRMReward

    bank = SceneBank(toy_scenes(), cache=False)
    rng = np.random.default_rng(5)
    bank.set_confidence(rng.random((bank.num_states, NUM_CATEGORIES)).astype(np.float32) ** 3)
    B = 5
    reward = TSRMReward(bank)
    env = BatchEnv(bank, B, sampler=TrainingSampler(bank), reward_fn=reward, max_steps=10, seed=3)
    assert not any(isinstance(v, StageSwitch) for v in vars(reward).values())  # the env's is the only one
    stats = EpisodeStats(bank, B)
    ref = StageSwitch(bank, num_envs=B)
    obs = env.reset(seed=3)
    stats.start_rows(np.ones(B, bool), obs)
    ref.reset(np.ones(B, bool), obs["state"], obs["target"])
    entered = finished = 0
    for _ in range(150):
        obs, rew, term, trunc, info = env.step(rng.integers(0, NUM_ACTIONS, B))
        ref.update(info["final_state"], info["steps"], info["path_length"], active=info["active"])
        assert np.array_equal(info["entered"], ref.entered)
        assert np.array_equal(info["switch_length"], ref.switch_length)
        assert np.array_equal(info["switch_state"], ref.switch_state)
        n = stats.step(rew, term, trunc, info, obs)
        fin = term | trunc
        if n:
            ep = stats.pop()
            r = np.flatnonzero(fin)
            assert np.array_equal(ep["entered"], ref.entered[r])
            assert np.array_equal(
                ep["search_length"], np.where(ref.entered[r], ref.switch_length[r], info["path_length"][r])
            )
            entered += int(ref.entered[r].sum())
            finished += len(r)
            ref.reset(fin, obs["state"], obs["target"])
    assert finished > 40 and 0 < entered < finished


def test_env_keeps_the_stage_with_or_without_a_stage_reward():
    """The env keeps the one stage switch (the bank's rule, or the one passed as ``stage``, e.g. an evaluation's
    own C_target), also with a reward that reads the stage."""
    from tsnav.tsrm.reward import TSRMReward

    bank = SceneBank(toy_scenes(), cache=False)
    env = BatchEnv(bank, 3, sampler=TrainingSampler(bank), seed=0)
    assert np.array_equal(env.stage.switches, bank.stage_mask)
    mine = StageSwitch(bank, 0.4)
    env = BatchEnv(bank, 3, sampler=TrainingSampler(bank), seed=0, stage=mine)
    obs = env.reset(seed=0)
    assert env.stage is mine and np.array_equal(mine.target, obs["target"])
    env = BatchEnv(bank, 3, sampler=TrainingSampler(bank), reward_fn=TSRMReward(bank), seed=0, stage=mine)
    obs = env.reset(seed=0)
    assert env.stage is mine and np.array_equal(mine.target, obs["target"])
