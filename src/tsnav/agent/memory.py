"""IOM's non-local target memory aggregation (paper III-D, "Policy Network"): a FIFO memory of the frames in
which the target was detected, attended with the target-category embedding as query.

Each memory node keeps what was seen and where from: the detection box (fractions of the image), its
confidence, its feature, and the absolute pose ``(x, z, rotation, horizon)`` of that frame. At read time the
pose is expressed relative to the *current* pose - forward and rightward offsets in metres in the agent's
frame, the relative yaw as sin / cos, and the horizon of that frame - so the aggregated feature F_t tells the
policy where the target was seen from here. The aggregation has no positional encoding over slots, so it does
not depend on the order of the memory. An empty memory gives a learned "nothing seen" vector.

With ``history`` (``AgentConfig.memory_history``, a deviation from the paper, off by default) the aggregator also
attends to a second FIFO memory of the same layout, written at *every* step whatever the score: the detector's box
and score of the target in each of the last ``M`` frames (zeros where nothing was detected), with the pose of that
frame and its age in steps. The first memory keeps the frames where the target was seen (score above the memory
threshold) for as long as it has room; the history shows how the target's detection changed over the last steps:
turning away, coming closer, fading. Its nodes have their own embedding (``history``) and join the first memory's
nodes under the same attention.

Memory writes are batched tensor operations (one-hot slot selection with ``torch.where``), no loop over
episodes; the state tensors are never modified in place, so a state can be indexed, copied or kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn as nn


@dataclass
class MemoryState:
    """Target memory of ``B`` episodes with ``M`` slots.

    Attributes:
        box: ``(B, M, 4)`` detection boxes, fractions of the image side.
        score: ``(B, M)`` detection confidences.
        feat: ``(B, M, D)`` detection features.
        pose: ``(B, M, 4)`` ``(x m, z m, rotation deg, horizon deg)`` of the frame of each detection.
        valid: ``(B, M)`` bool, the slot holds a detection.
        ptr: ``(B,)`` int64 slot that the next write goes to (the oldest node once the memory is full).
    """

    box: torch.Tensor
    score: torch.Tensor
    feat: torch.Tensor
    pose: torch.Tensor
    valid: torch.Tensor
    ptr: torch.Tensor

    @classmethod
    def empty(cls, batch: int, slots: int, feat_dim: int, device=None) -> "MemoryState":
        z = lambda *s: torch.zeros(*s, device=device)  # noqa: E731
        return cls(
            box=z(batch, slots, 4),
            score=z(batch, slots),
            feat=z(batch, slots, feat_dim),
            pose=z(batch, slots, 4),
            valid=torch.zeros(batch, slots, dtype=torch.bool, device=device),
            ptr=torch.zeros(batch, dtype=torch.long, device=device),
        )

    def write(
        self, mask: torch.Tensor, box: torch.Tensor, score: torch.Tensor, feat: torch.Tensor, pose: torch.Tensor
    ) -> "MemoryState":
        """Append one node to the rows where ``mask`` ``(B,)`` is True (FIFO: overwrites the oldest when full)."""
        slots = self.valid.shape[1]
        hot = (torch.arange(slots, device=self.ptr.device)[None, :] == self.ptr[:, None]) & mask[:, None]
        h3 = hot[:, :, None]
        return MemoryState(
            box=torch.where(h3, box[:, None, :], self.box),
            score=torch.where(hot, score[:, None], self.score),
            feat=torch.where(h3, feat[:, None, :], self.feat),
            pose=torch.where(h3, pose[:, None, :], self.pose),
            valid=self.valid | hot,
            ptr=torch.where(mask, (self.ptr + 1) % slots, self.ptr),
        )

    def clear(self, done: torch.Tensor) -> "MemoryState":
        """Empty the memory of the rows where ``done`` ``(B,)`` is True (the episode ended)."""
        keep = ~done
        return MemoryState(
            box=self.box,
            score=self.score,
            feat=self.feat,
            pose=self.pose,
            valid=self.valid & keep[:, None],
            ptr=self.ptr * keep.long(),
        )

    def index(self, rows) -> "MemoryState":
        return MemoryState(*(getattr(self, f)[rows] for f in self.__dataclass_fields__))

    @staticmethod
    def cat(states: list["MemoryState"]) -> "MemoryState":
        return MemoryState(*(torch.cat([getattr(s, f) for s in states]) for f in MemoryState.__dataclass_fields__))


def slot_age(mem: MemoryState) -> torch.Tensor:
    """``(B, M)`` age in writes of every slot of a FIFO memory (0: the newest node, ``M - 1``: the oldest); only
    meaningful where ``mem.valid``."""
    slots = mem.valid.shape[1]
    idx = torch.arange(slots, device=mem.ptr.device)
    return (mem.ptr[:, None] - 1 - idx[None, :]) % slots


def relative_pose(node_pose: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """Pose of memory nodes relative to the current pose, in the agent's frame.

    ``node_pose (B, M, 4)`` and ``pose (B, 4)`` hold ``(x m, z m, rotation deg, horizon deg)`` (rotation 0 faces
    +z, 90 faces +x). Returns ``(B, M, 5)``: forward offset (m), rightward offset (m), sin and cos of the
    node's yaw minus the current yaw, and the node's horizon / 30 degrees.
    """
    dx = node_pose[..., 0] - pose[:, None, 0]
    dz = node_pose[..., 1] - pose[:, None, 1]
    yaw = pose[:, None, 2] * (math.pi / 180.0)
    fwd = dx * torch.sin(yaw) + dz * torch.cos(yaw)
    right = dx * torch.cos(yaw) - dz * torch.sin(yaw)
    dyaw = (node_pose[..., 2] - pose[:, None, 2]) * (math.pi / 180.0)
    return torch.stack([fwd, right, torch.sin(dyaw), torch.cos(dyaw), node_pose[..., 3] / 30.0], dim=-1)


class TargetMemoryAggregator(nn.Module):
    """Non-local target memory aggregation (IOM, used in paper III-D): ``F_t`` from the memory and the target.

    Node embedding: ``ReLU(Linear(cat(box 4, score 1, relative pose 5, feature D)))`` of width ``dim``;
    multi-head attention with the target-category embedding as the single query, a key-padding mask over
    empty slots; an empty memory yields the learned ``nothing`` vector instead. Output:
    ``ReLU(Linear(cat(attended, query)))`` of width ``out_dim`` (the query keeps the target identity in F_t,
    which the searching stage needs while nothing has been seen).

    :meth:`add_history` (not called by default): a second memory of every step's box and score (module
    docstring), embedded by ``ReLU(Linear(cat(box 4, score 1, relative pose 5, age / M 1)))`` (the parameters
    ``history.*``, which only a network with it has) and attended together with the first memory's nodes.
    """

    def __init__(
        self,
        feat_dim: int,
        dim: int = 256,
        heads: int = 4,
        out_dim: int = 256,
        num_categories: int = 22,
    ):
        super().__init__()
        if dim % heads:
            raise ValueError(f"memory dim {dim} must be divisible by the number of heads {heads}")
        self.node = nn.Linear(4 + 1 + 5 + feat_dim, dim)
        self.query = nn.Embedding(num_categories, dim)
        self.attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.nothing = nn.Parameter(torch.zeros(dim))
        self.out = nn.Linear(2 * dim, out_dim)
        self.history: nn.Linear | None = None

    def add_history(self) -> nn.Linear:
        """Attend also to a memory of every step's box and score: adds (and returns) its node embedding
        ``history``."""
        self.history = nn.Linear(4 + 1 + 5 + 1, self.node.out_features)
        return self.history

    def forward(
        self, mem: MemoryState, pose: torch.Tensor, target: torch.Tensor, history: MemoryState | None = None
    ) -> torch.Tensor:
        """``F_t`` ``(B, out_dim)`` from the memory, the current pose ``(B, 4)`` and target ids ``(B,)``; with
        ``history`` (a network made with it), also from the memory of every step's box and score."""
        rel = relative_pose(mem.pose, pose)  # [B, M, 5]
        nodes = torch.relu(self.node(torch.cat([mem.box, mem.score[..., None], rel, mem.feat], dim=-1)))  # [B, M, d]
        q = self.query(target)  # [B, d]
        valid = mem.valid
        if self.history is not None:
            if history is None:
                raise ValueError("this target memory attends to a box and score history: pass it")
            nodes, valid = self._with_history(nodes, valid, history, pose)
        empty = ~valid.any(dim=1)  # [B]
        # An all-masked row would give NaN: unmask slot 0 there and replace the result below.
        pad = ~valid
        pad = pad & ~(empty[:, None] & (torch.arange(pad.shape[1], device=pad.device) == 0)[None, :])
        att = self.attend(q, nodes, pad)  # [B, d]
        att = torch.where(empty[:, None], self.nothing[None, :].expand_as(q), att)
        return torch.relu(self.out(torch.cat([att, q], dim=-1)))

    def _with_history(
        self, nodes: torch.Tensor, valid: torch.Tensor, history: MemoryState, pose: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The first memory's nodes ``(B, M, d)`` and ``valid`` ``(B, M)`` followed by the history's ``(B, M', d)``."""
        rel = relative_pose(history.pose, pose)  # [B, M', 5]
        age = slot_age(history).to(rel.dtype)[..., None] / history.valid.shape[1]  # [B, M', 1]
        h = torch.relu(self.history(torch.cat([history.box, history.score[..., None], rel, age], dim=-1)))
        return torch.cat([nodes, h], dim=1), torch.cat([valid, history.valid], dim=1)

    def attend(self, q: torch.Tensor, nodes: torch.Tensor, pad: torch.Tensor) -> torch.Tensor:
        """``self.attn`` with the single query ``q`` ``(B, d)`` over ``nodes`` ``(B, M, d)``, slots where ``pad``
        ``(B, M)`` is True left out: ``(B, d)``. The same function as :meth:`attend_reference` (the module's own
        forward; ``tests/agent/test_agent_model.py`` holds them together) with the key and value projections moved to the
        query side, so that no projection of the ``M`` nodes is computed:

            score_hm = (W_q,h q + b_q,h) . (W_k,h n_m + b_k,h) / sqrt(e) = (W_k,h^T Q_h) . n_m / sqrt(e) + const_h
            out_h    = sum_m a_hm (W_v,h n_m + b_v,h) = W_v,h (sum_m a_hm n_m) + b_v,h       (sum_m a_hm = 1)

        (the constant of each head does not change its softmax).

        The four products are the batched matrix products that ``torch.einsum`` makes of them (the same operands,
        strides and results; ``tests/agent/test_agent_model.py`` holds them to :meth:`attend_einsum` bit for bit),
        written out so that each step records a third of the autograd nodes einsum's reshapes cost."""
        qh, w_k, w_v, b_v, scale = self._query_heads(q)
        u = torch.bmm(qh.transpose(0, 1), w_k).transpose(0, 1) * scale  # [B, H, d]
        score = torch.bmm(u, nodes.transpose(1, 2)).masked_fill(pad[:, None, :], float("-inf"))  # [B, H, M]
        z = torch.bmm(torch.softmax(score, dim=-1), nodes)  # [B, H, d]
        v = torch.bmm(z.transpose(0, 1), w_v.transpose(1, 2)).transpose(0, 1) + b_v  # [B, H, e]
        return self.attn.out_proj(v.reshape(q.shape))

    def _query_heads(self, q: torch.Tensor):
        """What both forms of :meth:`attend` start from: the per-head queries ``(B, H, e)``, the key and value
        weights as ``(H, e, d)``, the value bias ``(H, e)`` and the score scale ``1 / sqrt(e)``."""
        a = self.attn
        b, d = q.shape
        heads = a.num_heads
        e = d // heads
        w_q, w_k, w_v = a.in_proj_weight.chunk(3)
        b_q, _, b_v = a.in_proj_bias.chunk(3)
        qh = torch.nn.functional.linear(q, w_q, b_q).view(b, heads, e)
        return qh, w_k.view(heads, e, d), w_v.view(heads, e, d), b_v.view(heads, e), 1.0 / math.sqrt(e)

    def attend_einsum(self, q: torch.Tensor, nodes: torch.Tensor, pad: torch.Tensor) -> torch.Tensor:
        """Reference of :meth:`attend` as the formulas read, with ``torch.einsum``."""
        qh, w_k, w_v, b_v, scale = self._query_heads(q)
        u = torch.einsum("bhe,hed->bhd", qh, w_k) * scale  # [B, H, d]
        score = torch.einsum("bhd,bmd->bhm", u, nodes).masked_fill(pad[:, None, :], float("-inf"))
        z = torch.einsum("bhm,bmd->bhd", torch.softmax(score, dim=-1), nodes)  # [B, H, d]
        v = torch.einsum("bhd,hed->bhe", z, w_v) + b_v  # [B, H, e]
        return self.attn.out_proj(v.reshape(q.shape))

    def attend_reference(self, q: torch.Tensor, nodes: torch.Tensor, pad: torch.Tensor) -> torch.Tensor:
        """Slow reference of :meth:`attend`: ``torch.nn.MultiheadAttention``'s own forward."""
        att, _ = self.attn(q[:, None, :], nodes, nodes, key_padding_mask=pad, need_weights=False)  # [B, 1, d]
        return att[:, 0]
