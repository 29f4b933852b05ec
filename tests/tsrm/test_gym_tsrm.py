"""The Gymnasium env trains with the paper's reward (issue 16, section 6).

``third_party_training`` is what a user's own RL code would be: it knows the env id string and the Gymnasium
API, nothing of tsnav. It must receive the TSRM terms in ``info`` and exactly the rewards that tsnav's batched
trainer computes for the same episodes and actions.
"""

from __future__ import annotations

import shutil

import gymnasium as gym
import numpy as np
import pytest

ENV_ID = "tsnav.sim:tsnav/ObjectNav-v1"  # "module:id": Gymnasium imports the module, which registers the id


def third_party_training(env_id: str, num_envs: int, updates: int, horizon: int, seed: int, **env_kwargs):
    """A small REINFORCE-style loop over the vector env using only gymnasium and numpy: a softmax policy over
    actions per target category, updated from discounted returns. Returns the actions taken, the rewards
    received and the per-step ``info`` dicts."""
    envs = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", **env_kwargs)
    n_actions = int(envs.single_action_space.n)
    n_targets = int(envs.single_observation_space["target"].n)
    logits = np.zeros((n_targets, n_actions))
    rng = np.random.default_rng(seed)
    obs, _ = envs.reset(seed=seed)
    actions, rewards, infos = [], [], []
    for _ in range(updates):
        batch = []
        for _ in range(horizon):
            p = np.exp(logits[obs["target"]] - logits[obs["target"]].max(1, keepdims=True))
            p /= p.sum(1, keepdims=True)
            a = np.array([rng.choice(n_actions, p=row) for row in p])
            target = obs["target"].copy()
            obs, r, term, trunc, info = envs.step(a)
            actions.append(a)
            rewards.append(r)
            infos.append(info)
            batch.append((target, a, r, term | trunc))
        ret = np.zeros(num_envs)
        for target, a, r, done in reversed(batch):  # discounted return, cut at episode ends
            ret = r + 0.99 * ret * ~done
            grad = -np.exp(logits[target]) / np.exp(logits[target]).sum(1, keepdims=True)
            grad[np.arange(num_envs), a] += 1.0
            np.add.at(logits, target, 0.01 * ret[:, None] * grad)
    envs.close()
    return np.array(actions), np.array(rewards), infos


@pytest.fixture(scope="module")
def world_with_detections(tiny_world, tmp_path_factory):
    """Two train rooms of the tiny world with the oracle detector's tables (a copy: the shared world stays as
    it is)."""
    from tsnav.data.detections import write_detections
    from tsnav.data.reader import list_scenes, load_scene
    from tsnav.detect.oracle import oracle_detections

    root = tmp_path_factory.mktemp("gym_world")
    for p in list_scenes(tiny_world, "train")[:2]:
        shutil.copytree(p, root / p.name)
        write_detections(root / p.name, "oracle", oracle_detections(load_scene(root / p.name)))
    return root


def batched_trainer_rewards(root, actions, num_envs: int, seed: int, max_steps: int, reward: str):
    """The rewards tsnav's batched trainer gets for the same actions: its own bank, reward and training env."""
    from tsnav.rl.assemble import load_bank, make_train_env
    from tsnav.rl.config import TrainConfig

    cfg = TrainConfig(data=str(root), split="train", detections="oracle", reward=reward, max_steps=max_steps)
    bank, _ = load_bank(cfg)
    env = make_train_env(bank, cfg, num_envs, seed)
    env.reset()
    out = []
    for a in actions:
        _, r, _, _, info = env.step(a)
        out.append((r, info["reward_terms"]))
    return out


@pytest.mark.parametrize("reward", ["tsrm", "baseline"])
def test_gymnasium_loop_gets_the_trainers_rewards(world_with_detections, reward):
    num_envs, seed, max_steps = 4, 7, 12
    actions, rewards, infos = third_party_training(
        ENV_ID,
        num_envs,
        updates=3,
        horizon=10,
        seed=seed,
        data=str(world_with_detections),
        split="train",
        reward=reward,
        detections="oracle",
        max_steps=max_steps,
    )
    expected = batched_trainer_rewards(world_with_detections, actions, num_envs, seed, max_steps, reward)
    terms = ("explore", "distance", "collision", "slack", "success")
    for t, (r, info) in enumerate(zip(rewards, infos)):
        exp_r, exp_terms = expected[t]
        np.testing.assert_array_equal(r, exp_r.astype(np.float64))
        for k in terms:
            np.testing.assert_array_equal(info[f"reward/{k}"], exp_terms[k])
        np.testing.assert_allclose(sum(info[f"reward/{k}"] for k in terms), r, rtol=1e-5, atol=1e-6)
    got = {k: np.concatenate([i[f"reward/{k}"] for i in infos]) for k in terms}
    assert (got["slack"] == np.float32(-0.01)).all()
    if reward == "tsrm":  # the TSRM terms are really there and paid
        assert (got["explore"] > 0).any() and (got["distance"] != 0).any()
    else:
        assert not got["explore"].any() and not got["distance"].any()


def test_single_env_reward_and_detections(world_with_detections):
    env = gym.make(ENV_ID, data=str(world_with_detections), split="train", reward="explore", detections="oracle")
    obs, _ = env.reset(seed=0)
    assert obs["detections"].any()  # the detector's table fills the observation
    total, rng = 0.0, np.random.default_rng(0)
    for episode in range(5):  # an episode whose start frame shows the target earns no exploration reward
        for a in rng.integers(0, 5, 20):
            obs, r, term, trunc, info = env.step(int(a))
            assert {f"reward/{k}" for k in ("explore", "distance", "collision", "slack", "success")} <= set(info)
            assert info["reward/distance"] == 0.0 and isinstance(info["success"], bool)
            total += info["reward/explore"]
            if term or trunc:
                break
        env.reset()
    assert total > 0
    with pytest.raises(ValueError, match="unknown reward"):
        gym.make(ENV_ID, reward="dense")
