"""Distance fields of the pathfinding-stage reward (paper section III-B, eq. DistanceReward).

``d(p, g)`` is the number of actions on the directed graph of *pose* nodes - (position, rotation) pairs,
the horizon projected away - with one edge of weight 1 per MoveAhead, RotateLeft and RotateRight
transition, from pose ``p`` to the nearest pose where the target ``g`` can be reached: a pose is a success
pose when Done succeeds for ``g`` (an instance in view within 1.0 m, paper III-A) at *any* horizon of that
pose. An edge exists between two poses when the action succeeds from the pose at some horizon (in the
offline data MoveAhead does not depend on the horizon, so this is the union of identical edge sets).

LookUp / LookDown are not edges: they leave the pose, hence ``d``, unchanged and earn no distance reward,
and a success pose that is a success only looking down still has ``d = 0``. This is the paper's graph
("each directed edge corresponds to a MoveAhead or Rotation action").

The fields are computed once per scene bank and category by a multi-source BFS over the reversed pose graph
(:func:`tsnav.sim.paths.distance_fields`, all categories at once) and mapped back to every full state, so
training only gathers ``d[state, target]``; it never searches.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from ..constants import GRID_SIZE, MOVE_AHEAD, ROTATE_LEFT, ROTATE_RIGHT, ROTATE_STEP
from ..sim.paths import UNREACHABLE, distance_fields

#: The actions that are edges of the pose graph.
POSE_ACTIONS = (MOVE_AHEAD, ROTATE_LEFT, ROTATE_RIGHT)


def pose_nodes(
    x: np.ndarray, z: np.ndarray, rotation: np.ndarray, scene_of: np.ndarray | None = None
) -> tuple[np.ndarray, int]:
    """Pose node of every state: ``(node_of (S,) int64, num_nodes)``; states sharing scene, grid position
    and rotation share a node (x, z metres on the 0.25 m grid; rotation degrees)."""
    x = np.asarray(x, np.float64)
    scene_of = np.zeros(len(x), np.int64) if scene_of is None else np.asarray(scene_of, np.int64)
    key = np.stack(
        [
            scene_of,
            np.round(x / GRID_SIZE).astype(np.int64),
            np.round(np.asarray(z, np.float64) / GRID_SIZE).astype(np.int64),
            (np.asarray(rotation, np.int64) % 360) // ROTATE_STEP,
        ],
        axis=1,
    )
    _, node_of = np.unique(key, axis=0, return_inverse=True)
    node_of = node_of.reshape(-1).astype(np.int64)
    return node_of, int(node_of.max()) + 1 if len(node_of) else 0


def pose_graph(next_state: np.ndarray, node_of: np.ndarray, num_nodes: int, horizon: np.ndarray) -> np.ndarray:
    """``(N, 3 * H)`` int64 successor table of the pose graph, ``H`` = number of distinct horizons.

    Column ``3 k + j`` holds the pose reached by action ``POSE_ACTIONS[j]`` from the node's state at the
    ``k``-th horizon (the node itself when that action fails or the node has no state at that horizon), so
    the graph's edges are the union over horizons; usable by :func:`tsnav.sim.paths.distance_fields`.
    """
    next_state = np.asarray(next_state, np.int64)
    horizon = np.asarray(horizon)
    levels = np.unique(horizon)
    out = np.repeat(np.arange(num_nodes, dtype=np.int64)[:, None], len(POSE_ACTIONS) * len(levels), axis=1)
    for k, h in enumerate(levels):
        sel = np.flatnonzero(horizon == h)
        for j, a in enumerate(POSE_ACTIONS):
            out[node_of[sel], len(POSE_ACTIONS) * k + j] = node_of[next_state[sel, a]]
    return out


def pose_distance_fields(
    next_state: np.ndarray,
    x: np.ndarray,
    z: np.ndarray,
    rotation: np.ndarray,
    horizon: np.ndarray,
    success: np.ndarray,
    scene_of: np.ndarray | None = None,
) -> np.ndarray:
    """``d(p, g)`` for every state and category: ``(S, C)`` int32 pose-graph actions to the nearest success
    pose (:data:`~tsnav.sim.paths.UNREACHABLE` when none is reachable or the category is absent).

    ``next_state``: ``(S, 6)`` successor ids (global ids of a bank are fine, with ``scene_of``); ``success``:
    ``(S, C)`` bool, Done succeeds in that state for the category.
    """
    success = np.asarray(success, dtype=bool)
    if success.ndim != 2 or success.shape[0] != len(next_state):
        raise ValueError(f"success must be (S, C) bool with S = {len(next_state)}, got shape {success.shape}")
    node_of, n = pose_nodes(x, z, rotation, scene_of)
    graph = pose_graph(next_state, node_of, n, horizon)
    # A pose is a success pose when any of its states is: count success states per node.
    node_success = np.zeros((n, success.shape[1]), dtype=np.int64)
    np.add.at(node_success, node_of, success.astype(np.int64))
    return distance_fields(graph, node_success > 0)[node_of]


def bank_pose_distance(bank) -> np.ndarray:
    """:func:`pose_distance_fields` over all scenes of a :class:`~tsnav.sim.batch.SceneBank` (global ids)."""
    return pose_distance_fields(
        bank.next_state, bank.x, bank.z, bank.rotation, bank.horizon, bank.success, bank.scene_of
    )


def scene_pose_distance(scene, success_distance: float = 1.0) -> np.ndarray:
    """:func:`pose_distance_fields` of one :class:`~tsnav.data.reader.Scene`, ``(S, 22)`` int32."""
    return pose_distance_fields(
        scene.next_state,
        scene.x,
        scene.z,
        scene.rotation,
        scene.horizon,
        scene.category_visible_within(success_distance),
    )


def pose_distance_reference(next_state, x, z, rotation, success_states) -> np.ndarray:
    """Slow, obviously-correct reference of one column of :func:`pose_distance_fields`.

    Builds the pose graph edge by edge in Python dicts keyed by ``(x, z, rotation)`` and runs a
    breadth-first search backwards from the success poses; returns ``(S,)`` int32 per state.
    """
    pose = [(round(float(x[s]), 2), round(float(z[s]), 2), int(rotation[s]) % 360) for s in range(len(x))]
    preds: dict = {p: set() for p in pose}
    for s in range(len(x)):
        for a in POSE_ACTIONS:
            t = int(next_state[s][a])
            if pose[t] != pose[s]:
                preds[pose[t]].add(pose[s])
    dist = {p: None for p in preds}
    q = deque()
    for s in range(len(x)):
        if success_states[s] and dist[pose[s]] is None:
            dist[pose[s]] = 0
            q.append(pose[s])
    while q:
        p = q.popleft()
        for r in preds[p]:
            if dist[r] is None:
                dist[r] = dist[p] + 1
                q.append(r)
    return np.array([UNREACHABLE if dist[p] is None else dist[p] for p in pose], dtype=np.int32)


def distance_delta(d: np.ndarray, prev_state: np.ndarray, new_state: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``d(p_{t-1}, g) - d(p_t, g)`` for a batch (float64 actions); 0 where either end is unreachable.

    The distance reward of eq. DistanceReward is ``K_d`` times this.
    """
    d0 = d[prev_state, target].astype(np.int64)
    d1 = d[new_state, target].astype(np.int64)
    ok = (d0 != UNREACHABLE) & (d1 != UNREACHABLE)
    return np.where(ok, d0 - d1, 0).astype(np.float64)
