"""Shortest action counts on a scene's state graph by multi-source BFS (DESIGN.md, "TSRM"; paper III-B).

The graph is given as ``next_state[S, A]``: the state reached by each action, equal to the state itself
when the action fails. Distances are computed backwards from a set of source states (e.g. the success
states of a target category) over the reversed graph, one BFS frontier at a time, with array operations.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

UNREACHABLE = np.iinfo(np.int32).max


def reverse_adjacency(next_state: np.ndarray) -> sparse.csr_matrix:
    """Sparse matrix M with M[s, t] = 1 when some action moves s to t != s.

    ``M @ frontier`` marks the predecessors of a frontier: one backward BFS step on the reversed graph.
    """
    next_state = np.asarray(next_state)
    n = next_state.shape[0]
    src = np.repeat(np.arange(n), next_state.shape[1])
    dst = next_state.reshape(-1)
    keep = dst != src
    data = np.ones(int(keep.sum()), dtype=np.int8)
    return sparse.csr_matrix((data, (src[keep], dst[keep])), shape=(n, n))


def multi_source_bfs(next_state: np.ndarray, sources: np.ndarray, reverse: sparse.csr_matrix | None = None) -> np.ndarray:
    """Number of actions from every state to the nearest state in ``sources`` (bool mask or indices).

    Returns int32 ``(S,)``; :data:`UNREACHABLE` where no source can be reached. ``reverse`` may be passed to
    reuse :func:`reverse_adjacency` across many source sets.
    """
    next_state = np.asarray(next_state)
    n = next_state.shape[0]
    rev = reverse_adjacency(next_state) if reverse is None else reverse
    mask = np.zeros(n, dtype=bool)
    src = np.asarray(sources)
    if src.dtype == bool:
        mask[:] = src
    else:
        mask[src.astype(np.int64)] = True
    dist = np.full(n, UNREACHABLE, dtype=np.int32)
    dist[mask] = 0
    frontier = mask.copy()
    level = 0
    while frontier.any():
        level += 1
        reached = (rev @ frontier.astype(np.int8)) > 0
        new = reached & (dist == UNREACHABLE)
        dist[new] = level
        frontier = new
    return dist


def bfs_reference(next_state: np.ndarray, sources) -> np.ndarray:
    """Slow, obviously-correct reference for :func:`multi_source_bfs`: a queue over Python lists."""
    from collections import deque

    n = len(next_state)
    preds: list[list[int]] = [[] for _ in range(n)]
    for s in range(n):
        for t in next_state[s]:
            if int(t) != s:
                preds[int(t)].append(s)
    src = np.asarray(sources)
    idx = np.flatnonzero(src) if src.dtype == bool else src
    dist = [UNREACHABLE] * n
    q = deque()
    for s in idx:
        dist[int(s)] = 0
        q.append(int(s))
    while q:
        t = q.popleft()
        for s in preds[t]:
            if dist[s] == UNREACHABLE:
                dist[s] = dist[t] + 1
                q.append(s)
    return np.array(dist, dtype=np.int32)
