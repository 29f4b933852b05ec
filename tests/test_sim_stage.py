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
