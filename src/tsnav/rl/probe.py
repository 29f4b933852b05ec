"""A critic probe: a fixed set of recorded episodes and the value error of any network on them.

Training losses of actor-critic methods move with the policy and the sparse success reward, so they say
little about learning from one update to the next. The probe fixes the data: :func:`record_episodes` runs one
episode per row to its end and stores states, targets, actions and Monte-Carlo returns; :func:`critic_error`
replays those observations and actions through a network (no dropout) and returns the mean squared error
between its values and the returns. A trainer that learns lowers it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..agent.model import ActorCritic
from ..agent.observe import Observer
from ..sim.batch import BatchEnv


@dataclass
class EpisodeBatch:
    """``(T, B)`` arrays of ``B`` complete episodes; ``valid`` marks the steps inside an episode."""

    state: np.ndarray
    target: np.ndarray
    action: np.ndarray
    valid: np.ndarray
    returns: np.ndarray


@torch.no_grad()
def record_episodes(model: ActorCritic, observer: Observer, env: BatchEnv, gamma: float = 0.99,
                    seed: int = 0) -> EpisodeBatch:
    """Run ``model`` (sampling, no dropout) for one episode in every row of ``env`` (which must not
    auto-reset) and record it; Monte-Carlo returns with no bootstrap after the last step."""
    if env.autoreset:
        raise ValueError("record_episodes needs an env without auto-reset")
    gen = torch.Generator().manual_seed(seed)
    was_training = model.training
    model.eval()
    obs = env.reset(seed=seed)
    state = model.initial_state(env.num_envs)
    S, G, A, V, R = [], [], [], [], []
    while env.active.any():
        logits, _, state = model(observer(obs["state"], obs["target"]), state)
        a = torch.multinomial(torch.softmax(logits, 1), 1, generator=gen)[:, 0]
        state = state.with_action(a)
        S.append(obs["state"])
        G.append(obs["target"])
        A.append(a.numpy())
        V.append(env.active.copy())
        obs, reward, _, _, _ = env.step(a.numpy())
        R.append(np.where(V[-1], reward, 0.0))
    model.train(was_training)
    rew = np.stack(R)
    ret = np.zeros_like(rew, dtype=np.float64)
    acc = np.zeros(rew.shape[1])
    for t in range(len(rew) - 1, -1, -1):
        acc = rew[t] + gamma * acc
        ret[t] = acc
    return EpisodeBatch(np.stack(S), np.stack(G), np.stack(A), np.stack(V), ret)


@torch.no_grad()
def critic_error(model: ActorCritic, observer: Observer, batch: EpisodeBatch) -> float:
    """Mean squared error between the critic's values along the recorded episodes and their returns."""
    was_training = model.training
    model.eval()
    state = model.initial_state(batch.state.shape[1])
    err, n = 0.0, 0
    for t in range(batch.state.shape[0]):
        _, v, state = model(observer(batch.state[t], batch.target[t]), state)
        state = state.with_action(torch.from_numpy(batch.action[t]))
        m = batch.valid[t]
        err += float(((v.numpy() - batch.returns[t]) ** 2)[m].sum())
        n += int(m.sum())
    model.train(was_training)
    return err / max(n, 1)
