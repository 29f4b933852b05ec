"""The navigation policy of paper III-D: image features, IOM target memory, previous action -> LSTM actor-critic.

    i_t  = ReLU(Linear(flatten(ReLU(Conv1x1(encoder features)))))          image embedding
    F_t  = TargetMemoryAggregator(memory, pose_t, target)                     target orientation embedding
    PA   = Embedding(previous action)                                         previous-action embedding
           (``blocked_action``, off by default: a MoveAhead that left the pose unchanged has an id of its own)
    s_t  = ReLU(cat(i_t, F_t, PA) W)                                          eq. (10)
    h_t  = LSTMCell(Dropout(s_t), h_{t-1})                                    policy network
    pi(a_t | s_t) = softmax(Linear(h_t)),  V(s_t) = Linear(h_t)               actor (6 actions), critic

The recurrent state (:class:`AgentState`: LSTM state, target memory, previous action) is passed in and out
explicitly; :meth:`AgentState.reset` clears the rows whose episode ended (LSTM state multiplied by 1 - done,
memory emptied, previous action set to "none").

``AgentConfig.memory_history`` is a deviation from the paper, off by default and in every preset: besides the frames
where the target was detected, the target memory keeps the detector's box and score of the target at each of the
last ``memory_slots`` steps, whatever the score, with the step's pose and age (:mod:`tsnav.agent.memory`), so that
the policy sees how the detection changed while it walked (issue 47: what tells the agent where the target is after
the switch). A network without it has the parameters, recurrent state and outputs it had before the setting existed.

``AgentConfig.target_depth`` is a deviation from the paper, off by default and in every preset: the depth a readout of
the encoder's feature map estimates inside the target's box (:class:`~tsnav.agent.observe.TargetDepth`) is added to
s_t before its ReLU, ``s_t = ReLU(cat(i_t, F_t, PA) W + D_t W_d)`` (issue 47: the stop lacks how far the target is).

``AgentConfig.mirror_policy`` is a deviation from the paper, off by default and in every preset: a policy that is
mirror-symmetric by construction. The network runs twice per step, on the observation and on its mirror image (the
frames flipped left to right, the detector's table of the flipped frames, the mirrored pose), each stream with its
own recurrent state, and the logits are ``(l(o) + P l(m(o))) / 2`` with ``P`` swapping RotateLeft and RotateRight
(the value the mean of the two). So ``pi(a | m(o)) = pi(P a | o)`` exactly: a policy that turns left wherever it is
cannot be expressed, since in the mirror of the same room it must then turn right (issue 47: the shipped iTHOR agent
never turns right after the switch, and training on mirrored rooms alone did not change that).

``AgentConfig.blocked_action`` is a deviation from the paper, off by default and in every preset: the agent's
previous-action input tells a MoveAhead that moved it from one that did not (its pose, an input of the target
memory already, unchanged: AI2-THOR's ``lastActionSuccess``). Greedy agents without it were seen pressing MoveAhead
into a blocked cell for the rest of an episode (docs/RESULTS.md, issue 23, session 15).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np
import torch
import torch.nn as nn

from ..constants import DEFAULT_CLASS_SET, MOVE_AHEAD, NUM_ACTIONS, ROTATE_LEFT, ROTATE_RIGHT
from ..constants import class_set as get_class_set
from .memory import MemoryState, TargetMemoryAggregator
from .observe import AgentObs

#: Previous-action id at the start of an episode (no action yet).
NO_ACTION = NUM_ACTIONS
#: Previous-action id of a MoveAhead that left the agent where it was (``AgentConfig.blocked_action`` only).
BLOCKED_MOVE = NUM_ACTIONS + 1
#: Action permutation of the mirror image: RotateLeft and RotateRight trade places (the same as
#: :data:`tsnav.data.reader.MIRROR_ACTIONS`, which a test holds it to).
MIRROR_ACTIONS = tuple(
    ROTATE_RIGHT if a == ROTATE_LEFT else ROTATE_LEFT if a == ROTATE_RIGHT else a for a in range(NUM_ACTIONS)
)
#: Width of the target-depth input (``AgentConfig.target_depth``): :func:`~tsnav.agent.observe.box_depth_stats`.
DEPTH_INPUTS = 4


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
    blocked_action: bool = False
    """Deviation from the paper (off by default): a MoveAhead after which the agent's position is unchanged is its
    own previous-action id (:data:`BLOCKED_MOVE`), so that the policy knows the move failed."""
    mirror_policy: bool = False
    """Deviation from the paper (off by default): a mirror-symmetric policy. The network also runs on the mirror image
    of each observation (frames flipped left to right: the feature and detection caches of ``tsnav features
    --mirror`` and ``tsnav detect --mirror``; the mirrored pose) with its own recurrent state, and its logits are the
    mean of the two streams' with RotateLeft and RotateRight swapped in the mirror's, so that the policy in a room's
    mirror image is the policy in the room with the two turns traded (the value is the mean of the two). Twice the
    network's compute per step; no parameters of its own."""
    memory_history: bool = False
    """Deviation from the paper (off by default): the target memory also keeps the detector's box (fractions of the
    image, x0 y0 x1 y1) and score of the target at each of the last ``memory_slots`` steps, whatever the score
    (zeros where nothing is detected), with the pose and age of that step, as extra nodes of its attention (their
    own embedding, parameters ``memory.history.*``). The frames where the target was seen (score above
    ``memory_threshold``) stay in the memory's own slots as before."""
    target_depth: str | None = None
    """Deviation from the paper (off by default): a depth readout file (``tsnav analyze depth-readout``: a decoder of
    the frozen encoder's feature map, trained on the training rooms' depth frames). The network also reads the depth
    it estimates inside the target's box in the current frame (median, minimum and 10th percentile, clipped to 5 m,
    and whether anything is detected), added to the state representation s_t through its own linear map
    (parameters ``depth_in.*``): how far the target is, which the paper's inputs tell only through the box. The value
    ``ground-truth`` reads the world's true depth frames instead: a privileged diagnostic that bounds what a better
    estimate could give, never an agent to ship."""

    def __post_init__(self):
        if self.target_depth == "":
            self.target_depth = None  # off, described as a network without it
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")
        for f in fields(self):
            v = getattr(self, f.name)
            if f.type in ("int", int) and v < 1:
                raise ValueError(f"{f.name} must be >= 1, got {v}")


#: Fields added to :class:`AgentConfig` after agents were shipped: a description leaves them out at their default
#: (off), so that a network without them is described, saved and loaded as before they existed.
ADDED_OFF = {"memory_history": False, "target_depth": None, "mirror_policy": False}

#: Named configurations: ``paper`` (defaults) and ``cpu`` (small enough to train on two CPU cores).
PRESETS = {
    "paper": AgentConfig(),
    "cpu": AgentConfig(
        conv_channels=16,
        image_dim=128,
        memory_slots=8,
        memory_dim=64,
        memory_heads=2,
        target_dim=64,
        action_dim=16,
        state_dim=128,
        hidden=128,
    ),
}


def agent_config(preset: str = "paper", **overrides) -> AgentConfig:
    """A preset of :data:`PRESETS` with fields overridden."""
    if preset not in PRESETS:
        raise ValueError(f"unknown agent preset {preset!r} (choose from {', '.join(PRESETS)})")
    return AgentConfig(**{**asdict(PRESETS[preset]), **overrides})


@dataclass
class AgentState:
    """Recurrent state of ``B`` episodes: LSTM ``h``, ``c`` ``(B, hidden)``, the target memory, the
    previous action ``(B,)`` (:data:`NO_ACTION` at an episode start) and, for ``AgentConfig.blocked_action``,
    the position ``(B, 2)`` (x, z) the previous action was taken from (None otherwise); for
    ``AgentConfig.memory_history``, the memory of every step's box and score (None otherwise); for
    ``AgentConfig.mirror_policy``, the state of the stream that reads the mirror images (None otherwise), whose
    previous action is the mirror of the one taken (RotateLeft and RotateRight traded)."""

    h: torch.Tensor
    c: torch.Tensor
    memory: MemoryState
    prev_action: torch.Tensor
    prev_position: torch.Tensor | None = None
    history: MemoryState | None = None
    mirror: "AgentState | None" = None

    @property
    def batch_size(self) -> int:
        return int(self.h.shape[0])

    def reset(self, done) -> "AgentState":
        """Clear the rows where ``done`` (``(B,)`` bool, tensor or array) is True: multiply the LSTM state by
        ``1 - done``, empty the memory, forget the previous action."""
        done = torch.as_tensor(
            np.asarray(done) if not torch.is_tensor(done) else done, dtype=torch.bool, device=self.h.device
        )
        keep = (~done).to(self.h.dtype)[:, None]
        return AgentState(
            h=self.h * keep,
            c=self.c * keep,
            memory=self.memory.clear(done),
            prev_action=torch.where(done, torch.full_like(self.prev_action, NO_ACTION), self.prev_action),
            prev_position=self.prev_position,
            history=None if self.history is None else self.history.clear(done),
            mirror=None if self.mirror is None else self.mirror.reset(done),
        )

    def with_action(self, action: torch.Tensor) -> "AgentState":
        """The state after ``action`` ``(B,)`` was output (the next step's previous action; the mirror stream's is
        its mirror)."""
        action = action.to(self.prev_action.device).long()
        mirror = None
        if self.mirror is not None:
            mirror = self.mirror.with_action(torch.as_tensor(MIRROR_ACTIONS, device=action.device)[action])
        return AgentState(self.h, self.c, self.memory, action, self.prev_position, self.history, mirror)

    def detach(self) -> "AgentState":
        """Cut the graph (truncated backpropagation through time at a rollout boundary)."""
        return AgentState(
            self.h.detach(),
            self.c.detach(),
            self.memory,
            self.prev_action,
            self.prev_position,
            self.history,
            None if self.mirror is None else self.mirror.detach(),
        )

    def float(self) -> "AgentState":
        """The LSTM states (the mirror stream's too) in float32 (after a step in another precision)."""
        return AgentState(
            self.h.float(),
            self.c.float(),
            self.memory,
            self.prev_action,
            self.prev_position,
            self.history,
            None if self.mirror is None else self.mirror.float(),
        )

    def index(self, rows) -> "AgentState":
        rows = torch.as_tensor(rows)
        return AgentState(
            self.h[rows],
            self.c[rows],
            self.memory.index(rows),
            self.prev_action[rows],
            None if self.prev_position is None else self.prev_position[rows],
            None if self.history is None else self.history.index(rows),
            None if self.mirror is None else self.mirror.index(rows),
        )


def _init(module: nn.Module, gain: float) -> None:
    nn.init.orthogonal_(module.weight, gain)
    if module.bias is not None:
        nn.init.zeros_(module.bias)


class ActorCritic(nn.Module):
    """LSTM actor-critic over :class:`AgentObs` (see the module docstring). ``feature_shape = (C, h, w)`` of the
    encoder features, ``det_dim`` = size of the detection feature, ``class_set`` = the target classes (a
    :class:`~tsnav.constants.ClassSet` name: ``ithor22``, 22 target embeddings, or ``robothor12``, 12; recorded by
    :meth:`describe`, and an agent is only run on scenes of its class set). Orthogonal initialisation (gain sqrt 2
    for ReLU layers, 0.01 for the actor, 1 for the critic), zero biases."""

    def __init__(
        self, config: AgentConfig, feature_shape: tuple[int, int, int], det_dim: int, class_set: str = DEFAULT_CLASS_SET
    ):
        super().__init__()
        self.config = config
        self.class_set = get_class_set(class_set).name
        self.feature_shape = tuple(int(v) for v in feature_shape)
        self.det_dim = int(det_dim)
        c, h, w = self.feature_shape
        self.conv = nn.Conv2d(c, config.conv_channels, 1)
        self.image = nn.Linear(config.conv_channels * h * w, config.image_dim)
        self.memory = TargetMemoryAggregator(
            det_dim,
            config.memory_dim,
            config.memory_heads,
            config.target_dim,
            get_class_set(class_set).size,
        )
        self.action_embed = nn.Embedding(NUM_ACTIONS + 1 + int(config.blocked_action), config.action_dim)
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
        if config.memory_history:  # made last: the other parameters are initialised as in a network without it
            _init(self.memory.add_history(), gain)
        if config.target_depth:  # made last, as memory history
            self.depth_in = nn.Linear(DEPTH_INPUTS, config.state_dim)
            _init(self.depth_in, gain)

    def initial_state(self, batch: int, device=None, _stream: bool = False) -> AgentState:
        """Fresh recurrent state of ``batch`` episodes (with ``mirror_policy``, the mirror stream's inside)."""
        device = device or next(self.parameters()).device
        cfg = self.config
        return AgentState(
            h=torch.zeros(batch, cfg.hidden, device=device),
            c=torch.zeros(batch, cfg.hidden, device=device),
            memory=MemoryState.empty(batch, cfg.memory_slots, self.det_dim, device),
            prev_action=torch.full((batch,), NO_ACTION, dtype=torch.long, device=device),
            prev_position=torch.zeros(batch, 2, device=device) if cfg.blocked_action else None,
            history=MemoryState.empty(batch, cfg.memory_slots, 0, device) if cfg.memory_history else None,
            mirror=self.initial_state(batch, device, _stream=True) if cfg.mirror_policy and not _stream else None,
        )

    def forward(self, obs: AgentObs, state: AgentState) -> tuple[torch.Tensor, torch.Tensor, AgentState]:
        """One step: ``(logits (B, 6), value (B,), new state)``. The new state holds the updated LSTM state
        and memory and still the old previous action: set it with :meth:`AgentState.with_action`. With
        ``mirror_policy`` the step runs on ``obs`` and on ``obs.mirror``, each with its own state (module
        docstring)."""
        if not self.config.mirror_policy:
            return self._stream(obs, state)
        if obs.mirror is None or state.mirror is None:
            raise ValueError(
                "this agent is mirror-symmetric (mirror_policy): its observer must give the mirror images "
                "(obs.mirror) and its state the mirror stream's (made by initial_state)"
            )
        la, va, sa = self._stream(obs, state)
        lb, vb, sb = self._stream(obs.mirror, state.mirror)
        logits = 0.5 * (la + lb[:, torch.as_tensor(MIRROR_ACTIONS, device=lb.device)])
        sa.mirror = sb
        return logits, 0.5 * (va + vb), sa

    def _stream(self, obs: AgentObs, state: AgentState) -> tuple[torch.Tensor, torch.Tensor, AgentState]:
        """One step of one stream: the paper's network."""
        memory = state.memory.write(
            obs.det_score > self.config.memory_threshold, obs.det_box, obs.det_score, obs.det_feat, obs.pose
        )
        history = None
        if self.config.memory_history:  # every step's box and score (no feature: the first memory has them)
            history = state.history.write(
                torch.ones_like(obs.det_score, dtype=torch.bool),
                obs.det_box,
                obs.det_score,
                obs.det_box.new_zeros(obs.det_box.shape[0], 0),
                obs.pose,
            )
        x = torch.relu(self.conv(obs.image))  # [B, k, h, w]
        i_t = torch.relu(self.image(x.flatten(1)))  # [B, image_dim]
        f_t = self.memory(memory, obs.pose, obs.target, history)  # [B, target_dim]
        pa = self.action_embed(self.previous_action_ids(obs, state))  # [B, action_dim]
        s_t = self.state(torch.cat([i_t, f_t, pa], dim=1))  # [B, state_dim], eq. (10)
        if self.config.target_depth:
            if obs.det_depth is None:
                raise ValueError("this agent reads the target's depth: its observer needs a TargetDepth")
            s_t = s_t + self.depth_in(obs.det_depth)
        s_t = torch.relu(s_t)
        h, c = self.lstm(self.dropout(s_t), (state.h, state.c))
        here = obs.pose[:, :2] if self.config.blocked_action else None  # where the next action is taken from
        return self.actor(h), self.critic(h)[:, 0], AgentState(h, c, memory, state.prev_action, here, history)

    def previous_action_ids(self, obs: AgentObs, state: AgentState) -> torch.Tensor:
        """``(B,)`` ids of the previous-action embedding: the previous action, or with ``blocked_action``
        :data:`BLOCKED_MOVE` where it was a MoveAhead and the position (x, z) is the one it was taken from."""
        if not self.config.blocked_action:
            return state.prev_action
        if state.prev_position is None:
            raise ValueError("blocked_action: the agent state has no previous position (made by another network?)")
        stayed = (obs.pose[:, :2] == state.prev_position).all(dim=1)
        return torch.where(
            (state.prev_action == MOVE_AHEAD) & stayed,
            torch.full_like(state.prev_action, BLOCKED_MOVE),
            state.prev_action,
        )

    def autocast_weights(self) -> list[str]:
        """Names of the parameters whose every use in :meth:`forward` is an operand of a matrix product that
        ``torch.autocast`` runs in bfloat16 (convolution, linear layers, the attention's projections, the LSTM
        cell), so that casting them once per rollout gives what autocast's per-step cast gives
        (``RolloutCollector(cast_once=True)``). Left out: the embeddings (autocast keeps them in float32), the
        attention's input bias (its value part is added in float32) and the memory's ``nothing`` vector."""
        keep = (
            "conv.",
            "image.",
            "memory.node.",
            "memory.attn.in_proj_weight",
            "memory.attn.out_proj.",
            "memory.out.",
            "memory.history.",
            "depth_in.",
            "state.",
            "lstm.",
            "actor.",
            "critic.",
        )
        return [name for name, _ in self.named_parameters() if name.startswith(keep)]

    def describe(self) -> dict:
        """JSON-able description that rebuilds the network: config (less the fields of :data:`ADDED_OFF` at their
        default), feature shape, detection feature size and, beyond ``ithor22`` (the meaning of a description
        without it), the class set."""
        agent = {k: v for k, v in asdict(self.config).items() if not (k in ADDED_OFF and v == ADDED_OFF[k])}
        d = {"agent": agent, "feature_shape": list(self.feature_shape), "det_dim": self.det_dim}
        if self.class_set != DEFAULT_CLASS_SET:
            d["class_set"] = self.class_set
        return d

    @classmethod
    def from_description(cls, d: dict) -> "ActorCritic":
        return cls(
            AgentConfig(**d["agent"]),
            tuple(d["feature_shape"]),
            int(d["det_dim"]),
            d.get("class_set", DEFAULT_CLASS_SET),
        )
