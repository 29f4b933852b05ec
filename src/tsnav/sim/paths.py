"""Shortest action counts on a scene's state graph by multi-source BFS (DESIGN.md, "TSRM"; paper III-B).

The graph is given as ``next_state[S, A]``: the state reached by each action, equal to the state itself
when the action fails. Distances are computed backwards from a set of source states (e.g. the success
states of a target category) over the reversed graph, one BFS frontier at a time, with array operations.
"""

from __future__ import annotations

import hashlib
import zipfile
from collections import deque
from pathlib import Path

import numpy as np
from scipy import sparse

from ..atomic import atomic_path
from ..data.reader import MIRROR_ACTIONS

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


def multi_source_bfs(
    next_state: np.ndarray, sources: np.ndarray, reverse: sparse.csr_matrix | None = None
) -> np.ndarray:
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


# ---------------------------------------------------------------------------------------------------------
# Distance fields for many source sets at once, optimal actions, and the per-scene cache (paper III-A, IV-A)
#
# Definition used everywhere in tsnav (simulator, episodes, metrics, rewards):
#   the optimal path length L* of an episode is the number of *movement* actions (MoveAhead, RotateLeft,
#   RotateRight, LookDown, LookUp) on the shortest action sequence from the start state to any success state
#   of the target; the final Done is NOT counted. The agent's path length L counts the same kind of actions:
#   every non-Done action it outputs (including failed ones: collisions and looks past the horizon limits), so that an agent that follows
#   a shortest path and then outputs Done has L = L* and SPL = 1.
# ---------------------------------------------------------------------------------------------------------

PATHS_CACHE_VERSION = 1


def distance_fields(
    next_state: np.ndarray, sources: np.ndarray, reverse: sparse.csr_matrix | None = None
) -> np.ndarray:
    """Multi-source BFS for several source sets at once: ``(S, C)`` int32 action counts.

    ``sources`` is an ``(S, C)`` bool matrix, one column per source set (e.g. the success states of each of
    the 22 categories). Column ``c`` of the result equals ``multi_source_bfs(next_state, sources[:, c])``;
    all columns advance together, one sparse matrix product per BFS level. Empty columns are all
    :data:`UNREACHABLE`.
    """
    next_state = np.asarray(next_state)
    sources = np.asarray(sources, dtype=bool)
    n = next_state.shape[0]
    if sources.ndim != 2 or sources.shape[0] != n:
        raise ValueError(f"sources must be (S, C) bool with S = {n}, got shape {sources.shape}")
    rev = reverse_adjacency(next_state) if reverse is None else reverse
    dist = np.full(sources.shape, UNREACHABLE, dtype=np.int32)
    dist[sources] = 0
    frontier = sources.copy()
    level = 0
    while frontier.any():
        level += 1
        reached = np.asarray(rev @ frontier.astype(np.float32)) > 0
        new = reached & (dist == UNREACHABLE)
        dist[new] = level
        frontier = new
    return dist


def optimal_action(next_state: np.ndarray, dist: np.ndarray, state: np.ndarray, done_action: int = 5) -> np.ndarray:
    """A shortest-path action for each of a batch of states (vectorised oracle step) on one ``(S,)`` field.

    Returns ``done_action`` where the distance is 0, elsewhere the first movement action (lowest action id)
    whose successor is one action closer to a source; -1 where the state cannot reach a source.
    """
    state = np.asarray(state, dtype=np.int64)
    nxt = np.asarray(next_state)[state, :done_action]  # (B, A-1)
    d_next = dist[nxt].astype(np.int64)  # (B, A-1)
    d_here = dist[state].astype(np.int64)
    best = np.argmin(d_next, axis=1)
    act = np.where(d_here == 0, done_action, best)
    return np.where(d_here == UNREACHABLE, -1, act).astype(np.int64)


def optimal_action_targets(
    next_state: np.ndarray, dist: np.ndarray, state: np.ndarray, target: np.ndarray, done_action: int = 5
) -> np.ndarray:
    """Like :func:`optimal_action` with a ``(S, C)`` distance table and one column (target) per row."""
    state = np.asarray(state, dtype=np.int64)
    target = np.asarray(target, dtype=np.int64)
    nxt = np.asarray(next_state)[state, :done_action]  # (B, A-1)
    d_next = dist[nxt, target[:, None]].astype(np.int64)
    d_here = dist[state, target].astype(np.int64)
    best = np.argmin(d_next, axis=1)
    act = np.where(d_here == 0, done_action, best)
    return np.where(d_here == UNREACHABLE, -1, act).astype(np.int64)


def shortest_path_actions(next_state: np.ndarray, dist: np.ndarray, start: int) -> list[int]:
    """The action sequence (movement actions only, no Done) that :func:`optimal_action` follows from
    ``start`` to the nearest source of the ``(S,)`` field ``dist``. Raises ``ValueError`` when unreachable."""
    if int(dist[start]) == UNREACHABLE:
        raise ValueError(f"state {start} cannot reach any source")
    out: list[int] = []
    s = int(start)
    while int(dist[s]) > 0:
        a = int(optimal_action(next_state, dist, np.array([s]))[0])
        out.append(a)
        s = int(next_state[s, a])
    return out


def _arrays_hash(*arrays: np.ndarray) -> str:
    h = hashlib.sha256(f"v{PATHS_CACHE_VERSION}".encode())
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def cached_distance_fields(next_state: np.ndarray, sources: np.ndarray, cache_file=None) -> np.ndarray:
    """:func:`distance_fields`, read from / written to ``cache_file`` (``.npz``) when one is given.

    The cache holds the fields and a SHA-256 of ``next_state`` (the state graph of ``graph.json``) and of
    ``sources`` (e.g. the success masks, which depend on the visibility tables): a change of either
    invalidates it. Writes are atomic (temporary file + ``os.replace``); a cache that cannot be written
    (read-only dataset) is skipped silently, an unreadable one is recomputed.
    """
    if cache_file is None:
        return distance_fields(next_state, sources)
    cache_file = Path(cache_file)
    key = _arrays_hash(np.asarray(next_state, dtype=np.int32), np.asarray(sources, dtype=bool))
    if cache_file.exists():
        try:
            with np.load(cache_file, allow_pickle=False) as f:
                if str(f["hash"]) == key:
                    return f["dist"].astype(np.int32)
        except (OSError, KeyError, ValueError, zipfile.BadZipFile):
            pass
    dist = distance_fields(next_state, sources)
    try:
        with atomic_path(cache_file) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, dist=dist, hash=np.array(key))
    except OSError:
        pass
    return dist


def scene_distance_fields(
    scene, success_distance: float = 1.0, cache: bool = True, protocol: str = "paper"
) -> np.ndarray:
    """``(S, 22)`` int32 optimal path lengths L* from every state of ``scene`` to the nearest success state of
    each target category under the success ``protocol`` (:mod:`tsnav.protocol`; ``paper``: target in view and
    within ``success_distance`` metres, 1.0 m in the paper; ``lineage``: listed in the visibility map).
    Movement actions counted, Done not (see the definition above); :data:`UNREACHABLE` for absent or
    unreachable categories.

    Cached per scene folder in ``shortest_paths_{success_distance:.2f}m.npz`` (``paper``) or
    ``shortest_paths_lineage.npz`` when the scene was read from a folder holding ``graph.json``.
    """
    success = scene.success_table(protocol, success_distance)
    cache_file = None
    if cache and scene.path is not None and (scene.path / "graph.json").exists():
        name = "lineage" if protocol == "lineage" else f"{success_distance:.2f}m"
        cache_file = scene.path / f"shortest_paths_{name}.npz"
    # A mirrored scene has the room's path lengths: read and write the room's cache with the room's graph.
    next_state = scene.next_state[:, MIRROR_ACTIONS] if getattr(scene, "mirror", False) else scene.next_state
    return cached_distance_fields(next_state, success, cache_file)
