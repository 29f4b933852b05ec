"""BatchEnv: hand-worked episodes, agreement with the lineage-style reference controller, the reward
protocol, auto-reset and determinism."""

import numpy as np
import pytest

from sim_helpers import toy_scenes
from tsnav.constants import (
    CATEGORY_INDEX,
    DONE,
    LOOK_DOWN,
    LOOK_UP,
    MOVE_AHEAD,
    ROTATE_LEFT,
    ROTATE_RIGHT,
    TARGET_CATEGORIES,
)
from tsnav.sim.batch import BatchEnv, RewardFn, SceneBank, SparseReward
from tsnav.sim.episodes import TrainingSampler
from tsnav.sim.reference import ReferenceController


@pytest.fixture(scope="module")
def bank():
    return SceneBank(toy_scenes(), cache=False)


def _one(bank, scene, key, target, max_steps=100, reward_fn=None):
    i = bank.scene_index(scene)
    env = BatchEnv(bank, 1, reward_fn=reward_fn, max_steps=max_steps, autoreset=False)
    env.reset(episodes=([i], [CATEGORY_INDEX[target]], [bank.global_state(i, key)]))
    return env


def test_bank_offsets_and_global_graph(bank):
    assert bank.offsets.tolist() == [0, 960, 960 + 784, 960 + 784 + 624]
    for i, s in enumerate(bank.scenes):
        o = bank.offsets[i]
        sl = slice(o, bank.offsets[i + 1])
        assert np.array_equal(bank.next_state[sl] - o, s.next_state)
        assert (bank.scene_of[sl] == i).all()
        assert np.array_equal(bank.success[sl], s.category_visible_within(1.0))
    # positions: 16 states (8 rotations x 2 horizons) per grid cell
    assert np.bincount(bank.position).tolist() == [16] * (bank.num_states // 16)
    assert bank.global_state(1, "0.00|0.00|180|0") == 960 + bank.scenes[1].index("0.00|0.00|180|0")


def test_hand_worked_episode(bank):
    env = _one(bank, "ToyB", "0.00|0.00|180|0", "GarbageCan", reward_fn=SparseReward())
    # (action, failed = lastActionSuccess False, collided, state after)
    seq = [
        (MOVE_AHEAD, True, True, "0.00|0.00|180|0"),  # faces -z at the wall: a collision
        (ROTATE_RIGHT, False, False, "0.00|0.00|225|0"),
        (LOOK_UP, True, False, "0.00|0.00|225|0"),  # already level: fails, but bumps into nothing
        (LOOK_DOWN, False, False, "0.00|0.00|225|30"),
        (LOOK_DOWN, True, False, "0.00|0.00|225|30"),  # already looking down: the same
        (LOOK_UP, False, False, "0.00|0.00|225|0"),
    ]
    for a, failed, coll, key in seq:
        obs, r, term, trunc, info = env.step(np.array([a]))
        assert info["failed"][0] == failed and info["collided"][0] == coll and bank.keys[obs["state"][0]] == key
        assert not term[0] and not trunc[0] and r[0] == pytest.approx(-0.01)
    obs, r, term, trunc, info = env.step(np.array([DONE]))
    # GarbageCan|1 stands at (0, 0): in view and within 1 m
    assert term[0] and not trunc[0] and info["success"][0]
    assert info["steps"][0] == 7 and info["path_length"][0] == 6  # Done not counted
    assert r[0] == pytest.approx(5 - 0.01)
    assert info["reward_terms"]["success"][0] == 5.0
    # Frozen afterwards: no reward, no movement, no new flags.
    obs, r, term, trunc, info = env.step(np.array([MOVE_AHEAD]))
    assert not info["active"][0] and r[0] == 0 and not term[0] and not trunc[0]
    assert info["steps"][0] == 7


def test_done_elsewhere_fails_and_truncation_is_not_termination(bank):
    env = _one(bank, "ToyB", "0.00|0.00|0|0", "Sink", max_steps=3)
    for _ in range(2):
        _, _, term, trunc, _ = env.step(np.array([ROTATE_LEFT]))
        assert not term[0] and not trunc[0]
    _, _, term, trunc, info = env.step(np.array([ROTATE_LEFT]))
    assert trunc[0] and not term[0] and not info["success"][0] and info["steps"][0] == 3
    # Done as the last allowed action terminates (and is not a truncation).
    env = _one(bank, "ToyB", "0.00|0.00|0|0", "Sink", max_steps=3)
    env.step(np.array([ROTATE_LEFT]))
    env.step(np.array([ROTATE_LEFT]))
    _, _, term, trunc, info = env.step(np.array([DONE]))
    assert term[0] and not trunc[0] and not info["success"][0]


def _random_actions(rng, n, t):
    return rng.choice(6, size=(t, n), p=[0.4, 0.2, 0.2, 0.07, 0.07, 0.06])


def test_agrees_with_reference_controller(bank):
    rng = np.random.default_rng(0)
    n, t = 48, 40
    sampler = TrainingSampler(bank)
    scene_idx, target, start = sampler.sample(n, rng)
    env = BatchEnv(bank, n, max_steps=30, autoreset=False)
    env.reset(episodes=(scene_idx, target, start))
    refs = []
    for i in range(n):
        c = ReferenceController(bank.scenes[scene_idx[i]], 1.0)
        c.reset(str(bank.keys[start[i]]), TARGET_CATEGORIES[target[i]])
        refs.append(c)
    acts = _random_actions(rng, n, t)
    for k in range(t):
        obs, _, term, trunc, info = env.step(acts[k])
        for i, c in enumerate(refs):
            if c.done:
                assert not info["active"][i]
                continue
            out = c.step(int(acts[k, i]), max_steps=30)
            assert bank.keys[obs["state"][i]] == out["state"]
            assert info["collided"][i] == out["collided"] and info["failed"][i] == out["failed"]
            assert term[i] == out["terminated"] and trunc[i] == out["truncated"]
            assert info["success"][i] == out["success"]
            assert info["steps"][i] == out["steps"] and info["path_length"][i] == out["path_length"]
            assert not (term[i] and trunc[i])
    assert sum(c.done for c in refs) > n // 2


class Recorder:
    def __init__(self):
        self.resets, self.steps = [], []

    def reset(self, mask, scene_idx, target, start_state):
        self.resets.append((mask.copy(), scene_idx.copy(), target.copy(), start_state.copy()))

    def step(self, prev_state, action, new_state, collided, done, success):
        self.steps.append((prev_state.copy(), action.copy(), new_state.copy(), done.copy()))
        n = len(prev_state)
        return np.ones(n, np.float32), {"one": np.ones(n, np.float32)}


def test_reward_protocol_and_autoreset(bank):
    assert isinstance(SparseReward(), RewardFn) and isinstance(Recorder(), RewardFn)
    rec = Recorder()
    n = 16
    env = BatchEnv(bank, n, sampler=TrainingSampler(bank), reward_fn=rec, max_steps=5, seed=3)
    obs = env.reset()
    assert rec.resets[0][0].all() and np.array_equal(rec.resets[0][3], obs["state"])
    rng = np.random.default_rng(1)
    for _ in range(12):
        prev = obs["state"]
        a = rng.integers(0, 6, n)
        obs, r, term, trunc, info = env.step(a)
        p, aa, new, done = rec.steps[-1]
        assert np.array_equal(p, prev) and np.array_equal(aa, a) and np.array_equal(new, info["final_state"])
        fin = term | trunc
        assert np.array_equal(done, fin)
        assert (r == 1).all()  # every row active with auto-reset
        if fin.any():
            mask, _, tgt, st = rec.resets[-1]
            assert np.array_equal(mask, fin)
            assert np.array_equal(st[fin], obs["state"][fin]) and (obs["step"][fin] == 0).all()
        assert (obs["step"][~fin] == info["steps"][~fin]).all()
        assert (info["steps"] <= 5).all()


def test_same_seed_same_rollout(bank):
    def rollout(seed):
        env = BatchEnv(bank, 32, sampler=TrainingSampler(bank), reward_fn=SparseReward(), max_steps=10, seed=seed)
        obs = env.reset()
        rng = np.random.default_rng(seed)
        out = [obs["state"].copy(), obs["target"].copy()]
        for _ in range(25):
            obs, r, term, trunc, info = env.step(rng.integers(0, 6, 32))
            out += [obs["state"], obs["target"], r, term, trunc]
        return out

    a, b, c = rollout(5), rollout(5), rollout(6)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not all(np.array_equal(x, y) for x, y in zip(a, c))


def test_bad_input(bank):
    env = BatchEnv(bank, 2, autoreset=False)
    with pytest.raises(ValueError, match="sampler"):
        env.reset()
    env.reset(episodes=([0, 1], [2, 18], [0, 960]))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.array([0]))
    with pytest.raises(ValueError, match="in \\[0, 6\\)"):
        env.step(np.array([0, 6]))
    with pytest.raises(ValueError, match="global state ids"):
        env.reset(episodes=([0, 1], [2, 18], [0, 5]))  # state 5 belongs to scene 0
    with pytest.raises(ValueError, match="confidence"):
        bank.set_confidence(np.zeros((3, 22)))


def test_make_env_from_config():
    from tsnav.sim.batch import SimConfig
    from tsnav.sim.episodes import make_env

    env = make_env(toy_scenes(), 4, SimConfig(success_distance=1.5, max_steps=30), seed=0)
    assert env.bank.success_distance == 1.5 and env.max_steps == 30 and env.autoreset
    obs = env.reset()
    assert np.isin(env.bank.horizon[obs["state"]], (0, 30)).all()  # starts at either horizon, as the lineage's
    # a larger success region: every 1.0 m success state is a 1.5 m one
    b1 = SceneBank(toy_scenes(), cache=False)
    assert (env.bank.success >= b1.success).all() and env.bank.success.sum() > b1.success.sum()


def test_make_env_refuses_a_config_the_bank_would_ignore():
    from tsnav.sim.batch import SceneBank, SimConfig
    from tsnav.sim.episodes import make_env

    bank = SceneBank(toy_scenes(), c_target=0.5)
    make_env(bank, 2, SimConfig(), seed=0)  # consistent: fine (C_target is the bank's alone)
    make_env(bank, 2, seed=0)  # no config: the bank's settings
    with pytest.raises(ValueError, match="success_distance"):
        make_env(bank, 2, SimConfig(success_distance=1.5), seed=0)
