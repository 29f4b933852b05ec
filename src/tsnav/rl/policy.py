"""A trained agent as an evaluation :class:`~tsnav.eval.policies.Policy` (``reset(mask)`` / ``act(obs)``)."""

from __future__ import annotations

import numpy as np
import torch

from ..agent.model import ActorCritic, AgentState
from ..agent.observe import Observer


class AgentPolicy:
    """Drives an :class:`ActorCritic` over a batch of evaluation episodes, keeping each episode's LSTM state,
    target memory and previous action; ``reset(mask)`` clears the rows that start a new episode. Dropout is off.

    Actions are greedy by default: the most probable action (``argmax`` of the logits), as the lineage
    evaluates (IOM's ``ThorAgent.action`` and DOA sample ``prob.multinomial(1)`` only while training and take
    ``prob.argmax`` at test time), so an evaluation is deterministic. ``greedy=False`` samples from the
    policy with a generator seeded by ``seed`` (``--sample`` on the commands)."""

    def __init__(self, model: ActorCritic, observer: Observer, greedy: bool = True, seed: int = 0):
        self.model = model.eval()
        self.observer = observer
        self.greedy = greedy
        self.generator = torch.Generator(device=observer.device).manual_seed(seed)
        self.state: AgentState | None = None

    def reset(self, mask: np.ndarray) -> None:
        mask = np.asarray(mask, dtype=bool)
        if self.state is None or self.state.batch_size != len(mask):
            self.state = self.model.initial_state(len(mask), self.observer.device)
        else:
            self.state = self.state.reset(torch.from_numpy(mask).to(self.observer.device))

    @torch.no_grad()
    def logits(self, obs: dict[str, np.ndarray]) -> tuple[torch.Tensor, AgentState]:
        """The action logits ``(B, 6)`` for the observation batch and the recurrent state after this step, not
        kept yet: :meth:`commit` keeps it with the action taken (so that several policies can choose together)."""
        n = len(obs["state"])
        if self.state is None or self.state.batch_size != n:
            self.reset(np.ones(n, dtype=bool))
        logits, _, state = self.model(self.observer(obs["state"], obs["target"]), self.state)
        return logits, state

    def commit(self, state: AgentState, action: torch.Tensor) -> None:
        """Keep the state of :meth:`logits` with the action taken as the previous action."""
        self.state = state.with_action(action)

    @torch.no_grad()
    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        logits, state = self.logits(obs)
        if self.greedy:
            action = logits.argmax(dim=1)
        else:
            action = torch.multinomial(torch.softmax(logits, dim=1), 1, generator=self.generator)[:, 0]
        self.commit(state, action)
        return action.cpu().numpy().astype(np.int64)
