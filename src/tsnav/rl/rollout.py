"""Rollouts, advantages and the actor-critic loss shared by the A3C and batched trainers (paper III-D).

A rollout is ``T`` steps of ``B`` episodes of a :class:`~tsnav.sim.batch.BatchEnv` with auto-reset, acted on
by the :class:`~tsnav.agent.ActorCritic` with gradients kept (as the lineage's A3C: one forward per step,
one backward per rollout; the recurrent state is detached at the rollout start).

Episode ends: Done *terminates* an episode (no bootstrap); the time limit *truncates* it, and then the return
is bootstrapped from the critic's value of the final observation (one extra forward of the truncated rows
with their pre-reset recurrent state). The last step of a rollout bootstraps from the value of the next
observation. With ``bootstrap[t]`` = value after step ``t`` within the same episode:

    delta_t = r_t + gamma * (1 - terminated_t) * bootstrap_t - V(s_t)
    A_t     = delta_t + gamma * tau * (1 - finished_t) * A_{t+1}          (GAE; the lineage's tau = 1.0)
    R_t     = A_t + V(s_t)

Loss per episode row, summed over the rollout's steps and averaged over rows (the lineage sums over the
steps of its single-episode rollouts):

    L = sum_t [ -log pi(a_t|s_t) A_t  -  c_ent H(pi(.|s_t))  +  c_v 0.5 (R_t - V(s_t))^2 ]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..agent.model import ActorCritic, AgentState
from ..constants import DONE
from ..agent.observe import Observer
from ..sim.batch import BatchEnv
from .config import PRECISIONS
from .stats import EpisodeStats


@dataclass
class Rollout:
    """``(T, B)`` tensors of one rollout; ``logp``, ``entropy`` and ``value`` carry gradients."""

    logp: torch.Tensor
    entropy: torch.Tensor
    value: torch.Tensor
    reward: torch.Tensor
    bootstrap: torch.Tensor
    terminated: torch.Tensor
    finished: torch.Tensor
    episodes: int = 0
    """Episodes that finished during the rollout."""
    states: np.ndarray | None = None
    """``(T, B)`` global state ids observed (the test helper ``replay`` re-runs them)."""
    targets: np.ndarray | None = None
    """``(T, B)`` target category ids."""
    actions: np.ndarray | None = None
    """``(T, B)`` actions taken."""
    start: AgentState | None = None
    """Recurrent state at the rollout start (detached)."""
    done_prob: float = 0.0
    """Mean probability the policy gave Done over the rollout's steps (the "Done collapse" of docs/RESULTS.md
    shows as this falling towards 0 while episodes run to their step limit)."""

    @property
    def steps(self) -> int:
        return int(self.reward.numel())


class RolloutCollector:
    """Steps ``env`` with ``model`` and keeps the observation and recurrent state between rollouts."""

    def __init__(
        self,
        env: BatchEnv,
        observer: Observer,
        model: ActorCritic,
        stats: EpisodeStats | None = None,
        generator: torch.Generator | None = None,
        precision: str = "fp32",
        cast_once: bool = True,
    ):
        if precision not in PRECISIONS:
            raise ValueError(f"unknown precision {precision!r} (choose from {', '.join(PRECISIONS)})")
        self.precision = precision
        self.cast_once = bool(cast_once)
        self.low: dict[str, tuple] | None = None  # name -> (weight, its bf16 copy) during a rollout (cast_once)
        self.env = env
        self.observer = observer
        self.model = model
        self.stats = stats or EpisodeStats(env.bank, env.num_envs)
        self.generator = generator
        self.obs: dict | None = None
        self.state: AgentState | None = None

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    def forward(self, obs, state: AgentState) -> tuple[torch.Tensor, torch.Tensor, AgentState]:
        """The model's step in the collector's precision; logits, value and LSTM state come back as float32.

        In bf16 the step runs under ``torch.autocast``. Autocast casts every float32 weight to bfloat16 at every
        step (its cast cache lives for one context); with ``cast_once`` the weights that only feed matrix products
        (:meth:`ActorCritic.autocast_weights`) are cast once per rollout instead (:meth:`collect`) and handed to
        each step through :class:`CastOnce`, whose backward returns the gradient in float32 as autocast's cast
        does: the same values, the same graph shape, so the same rollout and gradients bit for bit (held
        together with the per-step cast by ``tests/rl/test_rl_batched.py``)."""
        if self.precision == "fp32":
            return self.model(obs, state)
        with torch.autocast(self.device.type, dtype=torch.bfloat16):
            if self.low is None:
                logits, value, new = self.model(obs, state)
            else:
                weights = {name: CastOnce.apply(w, low) for name, (w, low) in self.low.items()}
                logits, value, new = torch.func.functional_call(self.model, weights, (obs, state), strict=False)
        return (
            logits.float(),
            value.float(),
            new.float(),
        )

    def start(self) -> None:
        """Begin fresh episodes in every row (drawn from the env's sampler and RNG)."""
        self.obs = self.env.reset()
        self.state = self.model.initial_state(self.env.num_envs, self.device)
        self.stats.start_rows(np.ones(self.env.num_envs, dtype=bool), self.obs)

    def collect(self, steps: int) -> Rollout:
        """Run ``steps`` steps; the model must be in the mode wanted (``train()`` for dropout)."""
        if self.obs is None:
            self.start()
        if self.precision == "bf16" and self.cast_once:  # the weights are fixed during a rollout
            params = dict(self.model.named_parameters())
            with torch.no_grad():
                self.low = {
                    name: (params[name], params[name].detach().to(torch.bfloat16))
                    for name in self.model.autocast_weights()
                }
        try:
            return self._collect(steps)
        finally:
            self.low = None  # the next rollout casts the weights the optimizer has changed

    def _collect(self, steps: int) -> Rollout:
        dev = self.device
        b = self.env.num_envs
        logps, ents, values, rewards, boots, terms, fins = [], [], [], [], [], [], []
        states, targets, actions = [], [], []
        state = self.state.detach()
        start = state
        obs = self.obs
        episodes = 0
        done_prob = 0.0
        for t in range(steps):
            o = self.observer(obs["state"], obs["target"])
            logits, value, state = self.forward(o, state)
            pol = Policy(logits)
            action = pol.sample(self.generator)
            state = state.with_action(action)
            done_prob += float(pol.probs.detach()[:, DONE].mean())
            target = obs["target"]
            states.append(obs["state"])
            targets.append(target)
            actions.append(action.cpu().numpy())
            obs, reward, term, trunc, info = self.env.step(actions[-1])
            boot = torch.zeros(b, device=dev)
            if trunc.any():  # bootstrap from the critic at the final observation of truncated episodes
                rows = np.flatnonzero(trunc)
                with torch.no_grad():
                    o_fin = self.observer(info["final_state"][rows], target[rows])
                    _, v_fin, _ = self.forward(o_fin, state.index(torch.from_numpy(rows).to(dev)))
                boot[torch.from_numpy(rows).to(dev)] = v_fin
            fin = term | trunc
            episodes += self.stats.step(reward, term, trunc, info, obs)
            state = state.reset(torch.from_numpy(fin).to(dev))
            logps.append(pol.log_prob(action))
            ents.append(pol.entropy())
            values.append(value)
            rewards.append(torch.from_numpy(np.asarray(reward, dtype=np.float32)).to(dev))
            boots.append(boot)
            terms.append(torch.from_numpy(term).to(dev))
            fins.append(torch.from_numpy(fin).to(dev))
        with torch.no_grad():  # value of the observation after the rollout
            _, v_next, _ = self.forward(self.observer(obs["state"], obs["target"]), state)
        self.obs, self.state = obs, state
        value = torch.stack(values)
        boot = torch.stack(boots)
        fin = torch.stack(fins)
        nxt = torch.cat([value[1:].detach(), v_next[None]])  # V(s_{t+1}) within the episode when not finished
        boot = torch.where(fin, boot, nxt)
        return Rollout(
            logp=torch.stack(logps),
            entropy=torch.stack(ents),
            value=value,
            reward=torch.stack(rewards),
            bootstrap=boot,
            terminated=torch.stack(terms),
            finished=fin,
            episodes=episodes,
            states=np.stack(states),
            targets=np.stack(targets),
            actions=np.stack(actions),
            start=start,
            done_prob=done_prob / steps,
        )


class Policy:
    """The categorical policy of ``(B, A)`` logits: what ``torch.distributions.Categorical(logits=logits)`` computes
    for the collector (sampling, log-probabilities, entropy), by the same operators in the same order, so the same
    actions, values and gradients bit for bit, without the distribution object's argument checks and lazy
    properties (a tenth of a small batch's step; ``tests/rl/test_rl_batched.py`` holds the two together). Invalid
    logits still fail loudly, in ``torch.multinomial``."""

    def __init__(self, logits: torch.Tensor):
        self.logits = logits - logits.logsumexp(dim=-1, keepdim=True)
        self.probs = torch.nn.functional.softmax(self.logits, dim=-1)

    def sample(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """``(B,)`` actions: ``Categorical.sample()`` without a generator, else ``torch.multinomial`` with it."""
        if generator is not None:
            return torch.multinomial(self.probs.detach(), 1, generator=generator)[:, 0]
        probs_2d = self.probs.reshape(-1, self.probs.shape[-1])
        return torch.multinomial(probs_2d, 1, True).T.reshape(self.probs.shape[:-1])

    def log_prob(self, action: torch.Tensor) -> torch.Tensor:
        value = action.long().unsqueeze(-1)
        value, log_pmf = torch.broadcast_tensors(value, self.logits)
        return log_pmf.gather(-1, value[..., :1]).squeeze(-1)

    def entropy(self) -> torch.Tensor:
        p_log_p = torch.clamp(self.logits, min=torch.finfo(self.logits.dtype).min) * self.probs
        return -p_log_p.sum(-1)


class CastOnce(torch.autograd.Function):
    """``CastOnce.apply(weight, low)`` -> ``low``, a bfloat16 copy of the float32 ``weight`` made beforehand, in
    place of autocast's per-use cast ``weight.to(bfloat16)``: the forward returns the copy, the backward returns
    the incoming gradient in float32 for ``weight`` (as autocast's cast, ``ToCopyBackward``, does)."""

    @staticmethod
    def forward(ctx, weight: torch.Tensor, low: torch.Tensor) -> torch.Tensor:
        ctx.dtype = weight.dtype
        return low.view_as(low)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        return grad.to(ctx.dtype), None


def gae(
    reward: torch.Tensor,
    value: torch.Tensor,
    bootstrap: torch.Tensor,
    terminated: torch.Tensor,
    finished: torch.Tensor,
    gamma: float = 0.99,
    tau: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalised advantage estimation over ``(T, B)`` tensors (see the module docstring); returns
    ``(advantages, returns)``, both detached. ``terminated`` implies ``finished``."""
    reward, value, bootstrap = reward.detach(), value.detach(), bootstrap.detach()
    not_term = 1.0 - terminated.to(reward.dtype)
    not_fin = 1.0 - finished.to(reward.dtype)
    adv = torch.zeros_like(reward)
    last = torch.zeros_like(reward[0])
    for t in range(reward.shape[0] - 1, -1, -1):
        delta = reward[t] + gamma * not_term[t] * bootstrap[t] - value[t]
        last = delta + gamma * tau * not_fin[t] * last
        adv[t] = last
    return adv, adv + value


def gae_reference(reward, value, bootstrap, terminated, finished, gamma=0.99, tau=1.0):
    """Slow reference for :func:`gae`: per row, split the rollout into episode segments and sum
    ``(gamma tau)^k delta_{t+k}`` inside each segment with Python floats."""
    reward, value, bootstrap = (np.asarray(x, dtype=np.float64) for x in (reward, value, bootstrap))
    terminated, finished = np.asarray(terminated, dtype=bool), np.asarray(finished, dtype=bool)
    T, B = reward.shape
    adv = np.zeros((T, B))
    for b in range(B):
        for t in range(T):
            total, k = 0.0, t
            while k < T:
                nxt = 0.0 if terminated[k, b] else bootstrap[k, b]
                delta = reward[k, b] + gamma * nxt - value[k, b]
                total += (gamma * tau) ** (k - t) * delta
                if finished[k, b]:
                    break
                k += 1
            adv[t, b] = total
    return adv, adv + value


def a2c_loss(
    ro: Rollout, advantages: torch.Tensor, returns: torch.Tensor, entropy_coef: float = 0.01, value_coef: float = 0.5
) -> tuple[torch.Tensor, dict[str, float]]:
    """The actor-critic loss of the module docstring and its parts (floats, per row and rollout)."""
    policy = -(ro.logp * advantages.detach()).sum(0).mean()
    entropy = ro.entropy.sum(0).mean()
    value = (0.5 * (returns.detach() - ro.value) ** 2).sum(0).mean()
    loss = policy - entropy_coef * entropy + value_coef * value
    return loss, {
        "loss": loss.item(),
        "policy_loss": policy.item(),
        "value_loss": value.item(),
        "entropy": entropy.item() / ro.reward.shape[0],
    }


def collect_and_loss(collector: "RolloutCollector", cfg) -> tuple[Rollout, torch.Tensor, dict[str, float]]:
    """One rollout of ``cfg.rollout_steps`` and its actor-critic loss (GAE with ``cfg.gamma`` / ``cfg.gae_tau``,
    :func:`a2c_loss` with ``cfg.entropy_coef`` / ``cfg.value_coef``): the step both trainers share."""
    ro = collector.collect(cfg.rollout_steps)
    adv, ret = gae(ro.reward, ro.value, ro.bootstrap, ro.terminated, ro.finished, cfg.gamma, cfg.gae_tau)
    loss, parts = a2c_loss(ro, adv, ret, cfg.entropy_coef, cfg.value_coef)
    parts["done_prob"] = ro.done_prob  # the Done collapse monitor (docs/RESULTS.md)
    parts["done_rate"] = float((ro.actions == DONE).mean())  # collect always records the actions
    return ro, loss, parts
