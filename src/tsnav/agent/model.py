"""The navigation policy of paper III-D: image features, IOM target memory, previous action -> LSTM actor-critic.

    i_t  = ReLU(Linear(flatten(ReLU(Conv1x1(encoder features)))))          image embedding
    F_t  = TargetMemoryAggregator(memory, pose_t, target)                     target orientation embedding
    PA   = Embedding(previous action)                                         previous-action embedding
    s_t  = ReLU(cat(i_t, F_t, PA) W)                                          eq. (10)
    h_t  = LSTMCell(Dropout(s_t), h_{t-1})                                    policy network
    pi(a_t | s_t) = softmax(Linear(h_t)),  V(s_t) = Linear(h_t)               actor (6 actions), critic

The recurrent state (:class:`AgentState`: LSTM state, target memory, previous action) is passed in and out
explicitly; :meth:`AgentState.reset` clears the rows whose episode ended (LSTM state multiplied by 1 - done,
memory emptied, previous action set to "none").
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np
import torch
import torch.nn as nn

from ..constants import NUM_ACTIONS, NUM_CATEGORIES
from .memory import MemoryState, TargetMemoryAggregator
from .observe import AgentObs

#: Previous-action id at the start of an episode (no action yet).
NO_ACTION = NUM_ACTIONS


@dataclass
class AgentConfig:
    """Sizes of the policy network (paper III-D). Defaults follow the paper / lineage (LSTM 512, dropout 0.45);
    :data:`PRESETS` ``"cpu"`` is a small variant for CPU training."""

    conv_channels: int = 64
    """Output channels of the 1x1 convolution on the encoder feature map (lineage: 64)."""
    image_dim: int = 512
    """Width of the image embedding i_t after flattening the convolution output."""
    memory_slots: int = 16
    """M, nodes of the FIFO target memory (frames where the target was detected)."""
    memory_dim: int = 256
    """Width of the memory nodes and of the attention."""
    memory_heads: int = 4
    """Heads of the memory attention."""
    memory_threshold: float = 0.5
    """A frame is written to the memory when the target's detection confidence exceeds this."""
    target_dim: int = 256
    """Width of the target orientation embedding F_t."""
    action_dim: int = 32
    """Width of the previous-action embedding PA."""
    state_dim: int = 512
    """Width of the state representation s_t (eq. 10)."""
    hidden: int = 512
    """LSTM hidden size."""
    dropout: float = 0.45
    """Dropout on s_t during training (paper IV-A: 0.45)."""

    def __post_init__(self):
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")
        for f in fields(self):
            v = getattr(self, f.name)
            if f.type in ("int", int) and v < 1:
                raise ValueError(f"{f.name} must be >= 1, got {v}")


#: Named configurations: ``paper`` (defaults) and ``cpu`` (small enough to train on two CPU cores).
PRESETS = {
    "paper": AgentConfig(),
    "cpu": AgentConfig(conv_channels=16, image_dim=128, memory_slots=8, memory_dim=64, memory_heads=2,
                       target_dim=64, action_dim=16, state_dim=128, hidden=128),
}


def agent_config(preset: str = "paper", **overrides) -> AgentConfig:
    """A preset of :data:`PRESETS` with fields overridden."""
    if preset not in PRESETS:
        raise ValueError(f"unknown agent preset {preset!r} (choose from {', '.join(PRESETS)})")
    return AgentConfig(**{**asdict(PRESETS[preset]), **overrides})


@dataclass
class AgentState:
    """Recurrent state of ``B`` episodes: LSTM ``h``, ``c`` ``(B, hidden)``, the target memory and the
    previous action ``(B,)`` (:data:`NO_ACTION` at an episode start)."""

    h: torch.Tensor
    c: torch.Tensor
    memory: MemoryState
    prev_action: torch.Tensor

    @property
    def batch_size(self) -> int:
        return int(self.h.shape[0])

    def reset(self, done) -> "AgentState":
        """Clear the rows where ``done`` (``(B,)`` bool, tensor or array) is True: multiply the LSTM state by
        ``1 - done``, empty the memory, forget the previous action."""
        done = torch.as_tensor(np.asarray(done) if not torch.is_tensor(done) else done, dtype=torch.bool,
                               device=self.h.device)
        keep = (~done).to(self.h.dtype)[:, None]
        return AgentState(h=self.h * keep, c=self.c * keep, memory=self.memory.clear(done),
                          prev_action=torch.where(done, torch.full_like(self.prev_action, NO_ACTION), self.prev_action))

    def with_action(self, action: torch.Tensor) -> "AgentState":
        """The state after ``action`` ``(B,)`` was output (the next step's previous action)."""
        return AgentState(self.h, self.c, self.memory, action.to(self.prev_action.device).long())

    def detach(self) -> "AgentState":
        """Cut the graph (truncated backpropagation through time at a rollout boundary)."""
        return AgentState(self.h.detach(), self.c.detach(), self.memory, self.prev_action)

    def index(self, rows) -> "AgentState":
        rows = torch.as_tensor(rows)
        return AgentState(self.h[rows], self.c[rows], self.memory.index(rows), self.prev_action[rows])


def _init(module: nn.Module, gain: float) -> None:
    nn.init.orthogonal_(module.weight, gain)
    if module.bias is not None:
        nn.init.zeros_(module.bias)


class ActorCritic(nn.Module):
    """LSTM actor-critic over :class:`AgentObs` (see the module docstring). ``feature_shape = (C, h, w)`` of the
    encoder features, ``det_dim`` = size of the detection feature. Orthogonal initialisation (gain sqrt 2 for
    ReLU layers, 0.01 for the actor, 1 for the critic), zero biases."""

    def __init__(self, config: AgentConfig, feature_shape: tuple[int, int, int], det_dim: int):
        super().__init__()
        self.config = config
        self.feature_shape = tuple(int(v) for v in feature_shape)
        self.det_dim = int(det_dim)
        c, h, w = self.feature_shape
        self.conv = nn.Conv2d(c, config.conv_channels, 1)
        self.image = nn.Linear(config.conv_channels * h * w, config.image_dim)
        self.memory = TargetMemoryAggregator(det_dim, config.memory_dim, config.memory_heads, config.target_dim,
                                             NUM_CATEGORIES)
        self.action_embed = nn.Embedding(NUM_ACTIONS + 1, config.action_dim)
        self.state = nn.Linear(config.image_dim + config.target_dim + config.action_dim, config.state_dim)
        self.dropout = nn.Dropout(config.dropout)
        self.lstm = nn.LSTMCell(config.state_dim, config.hidden)
        self.actor = nn.Linear(config.hidden, NUM_ACTIONS)
        self.critic = nn.Linear(config.hidden, 1)
        gain = nn.init.calculate_gain("relu")
        for m in (self.conv, self.image, self.state, self.memory.node, self.memory.out):
            _init(m, gain)
        _init(self.actor, 0.01)
        _init(self.critic, 1.0)
        for name, p in self.lstm.named_parameters():
            if "weight" in name:
                nn.init.orthogonal_(p)
            else:
                nn.init.zeros_(p)

    def initial_state(self, batch: int, device=None) -> AgentState:
        """Fresh recurrent state of ``batch`` episodes."""
        device = device or next(self.parameters()).device
        cfg = self.config
        return AgentState(h=torch.zeros(batch, cfg.hidden, device=device),
                          c=torch.zeros(batch, cfg.hidden, device=device),
                          memory=MemoryState.empty(batch, cfg.memory_slots, self.det_dim, device),
                          prev_action=torch.full((batch,), NO_ACTION, dtype=torch.long, device=device))

    def forward(self, obs: AgentObs, state: AgentState) -> tuple[torch.Tensor, torch.Tensor, AgentState]:
        """One step: ``(logits (B, 6), value (B,), new state)``. The new state holds the updated LSTM state
        and memory and still the old previous action: set it with :meth:`AgentState.with_action`."""
        memory = state.memory.write(obs.det_score > self.config.memory_threshold, obs.det_box, obs.det_score,
                                    obs.det_feat, obs.pose)
        x = torch.relu(self.conv(obs.image))  # [B, k, h, w]
        i_t = torch.relu(self.image(x.flatten(1)))  # [B, image_dim]
        f_t = self.memory(memory, obs.pose, obs.target)  # [B, target_dim]
        pa = self.action_embed(state.prev_action)  # [B, action_dim]
        s_t = torch.relu(self.state(torch.cat([i_t, f_t, pa], dim=1)))  # [B, state_dim], eq. (10)
        h, c = self.lstm(self.dropout(s_t), (state.h, state.c))
        return self.actor(h), self.critic(h)[:, 0], AgentState(h, c, memory, state.prev_action)

    def describe(self) -> dict:
        """JSON-able description that rebuilds the network: config, feature shape, detection feature size."""
        return {"agent": asdict(self.config), "feature_shape": list(self.feature_shape), "det_dim": self.det_dim}

    @classmethod
    def from_description(cls, d: dict) -> "ActorCritic":
        return cls(AgentConfig(**d["agent"]), tuple(d["feature_shape"]), int(d["det_dim"]))
