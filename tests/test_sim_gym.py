"""Gymnasium env and vector env: check_env, registration, seeding, observations from HDF5, auto-reset."""

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import tsnav.sim  # noqa: F401  (registers the env id)
from sim_helpers import toy_scenes, write_scene_folder
from tsnav.constants import DONE, ROTATE_LEFT
from tsnav.sim.batch import SceneBank
from tsnav.sim.gym_env import ENV_ID, ObjectNavEnv, ObjectNavVectorEnv


@pytest.fixture(scope="module")
def bank():
    return SceneBank(toy_scenes(), cache=False)


def test_check_env_passes(bank):
    env = ObjectNavEnv(bank=bank, max_steps=20)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the checker's warnings are failures too
        check_env(env, skip_render_check=True)
    check_env(ObjectNavEnv(), skip_render_check=True)  # default toy room


def test_registered_and_seeded(bank):
    env = gym.make(ENV_ID, bank=bank, max_steps=10)
    o1, i1 = env.reset(seed=11)
    o2, i2 = env.reset(seed=11)
    assert i1 == i2 and o1["target"] == o2["target"]
    assert env.observation_space.contains(o1)
    assert o1["rgb"].shape == (64, 64, 3) and not o1["rgb"].any() and not o1["detections"].any()
    seq = []
    for seed in (3, 3):
        env.reset(seed=seed)
        rs = [env.step(int(a))[:4] for a in np.random.default_rng(0).integers(0, 5, 10)]
        seq.append([(r, t, u) for _, r, t, u in rs])
    assert seq[0] == seq[1]


def test_truncation_and_termination_single(bank):
    env = ObjectNavEnv(bank=bank, max_steps=3)
    env.reset(seed=0, options={"episode": ("ToyB", "GarbageCan", "0.00|0.00|225|0")})
    _, r, term, trunc, info = env.step(DONE)
    assert term and not trunc and info["success"] and r == pytest.approx(4.99)
    env.reset(options={"episode": ("ToyB", "Sink", "0.00|0.00|0|0")})
    flags = [env.step(ROTATE_LEFT)[2:4] for _ in range(3)]
    assert flags == [(False, False), (False, False), (False, True)]
    with pytest.raises(ValueError):
        env.step(7)


def test_observations_from_hdf5(tmp_path):
    root = tmp_path / "data"
    write_scene_folder(toy_scenes()[2], root / "ToyC", images=8)  # the smallest scene: HDF5 writes are slow
    with pytest.raises(ValueError, match="name the detection table"):
        gym.make(ENV_ID, data=str(root), split="test")  # no silent fallback to ground truth
    env = gym.make(ENV_ID, bank=SceneBank.from_root(root, "test"))
    obs, info = env.reset(seed=1)
    s = int(env.unwrapped.bank.local_state(info["state"]))  # the pattern follows the scene-local index
    assert obs["rgb"].shape == (8, 8, 3) and (obs["rgb"] == s % 251).all()
    assert obs["depth"].shape == (8, 8) and (obs["depth"] == 0.5 + s % 7).all()
    b = env.unwrapped.bank
    det = np.zeros((b.num_states, 22, 6), np.float32)
    det[:, :, 0] = np.arange(b.num_states)[:, None]
    b.set_detections(det)
    obs, _, _, _, info = env.step(0)
    assert (obs["detections"][:, 0] == info["state"]).all()
    env.close()


def test_vector_env(bank):
    envs = gym.make_vec(ENV_ID, num_envs=8, bank=bank, max_steps=6)
    assert isinstance(envs.unwrapped, ObjectNavVectorEnv)
    assert envs.num_envs == 8 and envs.single_action_space == gym.spaces.Discrete(6)
    assert envs.single_observation_space["target"] == gym.spaces.Discrete(22)
    obs, info = envs.reset(seed=5)
    assert envs.observation_space.contains(obs)
    obs_again, _ = envs.reset(seed=5)
    assert np.array_equal(obs["target"], obs_again["target"])
    envs.action_space.seed(0)
    ended = 0
    for _ in range(30):
        prev_target = obs["target"].copy()
        obs, r, term, trunc, info = envs.step(envs.action_space.sample())
        assert envs.observation_space.contains(obs)
        assert not (term & trunc).any()
        assert (info["steps"][trunc] == 6).all() and (info["steps"] <= 6).all()
        fin = term | trunc
        ended += fin.sum()
        if fin.any():
            assert np.array_equal(info["_final_obs"], fin)
            for j in np.flatnonzero(fin):
                assert info["final_obs"][j]["target"] == prev_target[j]
            assert (info["final_info"]["success"] <= term).all()
    assert ended > 8
    envs.close()
