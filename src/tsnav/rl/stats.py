"""On-the-fly episode statistics of training rollouts: return per reward term, SR, SPL, SSR, SSSPL, NSNPL.

:class:`EpisodeStats` follows the ``B`` rows of a :class:`~tsnav.sim.batch.BatchEnv` with auto-reset and
collects one entry per finished episode (array operations per step, no loop over episodes). The two-stage
bookkeeping is the env's (paper III-B / IV-A; ``info["entered"]``, ``switch_length``, ``switch_state`` from
the env's one :class:`~tsnav.sim.stage.StageSwitch`, whose stage the reward is handed): an episode enters the
pathfinding stage at the first frame (the start included) whose target confidence exceeds C_target; searching
length = movement actions before that frame. Training episodes are truncated at ``max_steps`` (30), so these figures are lower
than the 100-step test figures.
"""

from __future__ import annotations

import numpy as np

from ..metrics import metric_values
from ..sim.paths import UNREACHABLE

FIELDS = (
    "success",
    "path_length",
    "optimal_length",
    "entered",
    "search_length",
    "optimal_search_length",
    "nav_length",
    "optimal_nav_length",
    "steps",
    "return",
)


def stage_lengths(
    dist: np.ndarray,
    search_dist: np.ndarray,
    start: np.ndarray,
    target: np.ndarray,
    path_length: np.ndarray,
    entered: np.ndarray,
    switch_length: np.ndarray,
    switch_state: np.ndarray,
    unreachable: int | None = None,
) -> dict[str, np.ndarray]:
    """Searching and pathfinding lengths of ``K`` finished episodes (paper III-B / IV-A), as ``(K,)`` int64
    arrays: ``search_length`` (LSearch: movement actions before the switching frame; all of them when the
    episode never switched), ``optimal_search_length`` (L*Search: ``search_dist[start, target]``),
    ``nav_length`` (LNav: the movement actions after it) and ``optimal_nav_length`` (L*Nav: ``dist`` from the
    switching state to the target); both pathfinding lengths are 0 where the episode never switched.

    ``start``, ``target``, ``switch_state`` are global state / category ids; ``path_length`` L, ``entered``
    Nav, ``switch_length`` and ``switch_state`` as :class:`~tsnav.sim.stage.StageSwitch` keeps them.
    A start from which no switching frame can be reached has ``optimal_search_length`` UNREACHABLE; with
    ``unreachable`` given it stands there instead (the evaluation records write -1; the training statistics
    keep UNREACHABLE and :func:`summarize` counts it 0)."""
    ls = np.where(entered, switch_length, path_length)
    opt_s = search_dist[start, target].astype(np.int64)
    if unreachable is not None:
        opt_s = np.where(opt_s == UNREACHABLE, unreachable, opt_s)
    return {
        "search_length": ls,
        "optimal_search_length": opt_s,
        "nav_length": np.where(entered, path_length - ls, 0),
        "optimal_nav_length": np.where(entered, dist[switch_state, target], 0).astype(np.int64),
    }


class EpisodeStats:
    """Per-row accumulators over a batch of training episodes; :meth:`pop` returns the finished ones."""

    def __init__(self, bank, num_envs: int):
        self.bank = bank
        self.search_dist = bank.search_dist
        b = num_envs
        self.start = np.zeros(b, dtype=np.int64)
        self.target = np.zeros(b, dtype=np.int64)
        self.ret = np.zeros(b, dtype=np.float64)
        self.terms: dict[str, np.ndarray] = {}
        self._done: list[dict[str, np.ndarray]] = []

    def start_rows(self, mask: np.ndarray, obs: dict) -> None:
        """Rows where ``mask`` is True begin an episode whose first observation is ``obs``."""
        rows = np.flatnonzero(mask)
        s, g = obs["state"][rows], obs["target"][rows]
        self.start[rows] = s
        self.target[rows] = g
        self.ret[rows] = 0.0
        for v in self.terms.values():
            v[rows] = 0.0

    def step(
        self, reward: np.ndarray, terminated: np.ndarray, truncated: np.ndarray, info: dict, next_obs: dict
    ) -> int:
        """Account one :meth:`BatchEnv.step`; returns the number of episodes that finished."""
        active = info["active"]
        self.ret += np.where(active, reward, 0.0)
        for k, v in info["reward_terms"].items():
            if k not in self.terms:
                self.terms[k] = np.zeros(len(self.ret), dtype=np.float64)
            self.terms[k] += np.where(active, v, 0.0)
        fin = terminated | truncated
        if fin.any():
            r = np.flatnonzero(fin)
            g, s0 = self.target[r], self.start[r]
            L = info["path_length"][r].astype(np.int64)
            entered = info["entered"][r].copy()
            entry = {
                "success": info["success"][r].astype(bool),
                "path_length": L,
                "optimal_length": self.bank.dist[s0, g].astype(np.int64),
                "entered": entered,
                **stage_lengths(
                    self.bank.dist,
                    self.search_dist,
                    s0,
                    g,
                    L,
                    entered,
                    info["switch_length"][r],
                    info["switch_state"][r],
                ),
                "steps": info["steps"][r].astype(np.int64),
                "return": self.ret[r].copy(),
            }
            for k, v in self.terms.items():
                entry[f"reward/{k}"] = v[r].copy()
            self._done.append(entry)
            self.start_rows(fin, next_obs)
        return int(fin.sum())

    def pop(self) -> dict[str, np.ndarray]:
        """Finished episodes since the last call, as arrays of equal length (empty dict when none)."""
        done, self._done = self._done, []
        return concat(done)


def concat(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Concatenate entries of :meth:`EpisodeStats.pop` (e.g. from several workers)."""
    parts = [p for p in parts if p]
    if not parts:
        return {}
    return {k: np.concatenate([np.asarray(p[k]) for p in parts]) for k in parts[0]}


def summarize(ep: dict[str, np.ndarray], protocol: str = "paper") -> dict[str, float]:
    """Means over finished episodes: ``return``, each ``reward/<term>``, ``length``, ``SR``, ``SPL``, ``SSR``,
    ``SSSPL``, ``NSNPL`` (fractions; SPL counted under the run's success ``protocol``) and the count
    ``n_episodes``."""
    if not ep or len(ep["success"]) == 0:
        return {"n_episodes": 0}
    opt_s = np.where(ep["optimal_search_length"] >= UNREACHABLE, 0, ep["optimal_search_length"])
    out = {
        "n_episodes": int(len(ep["success"])),
        "return": float(np.mean(ep["return"])),
        "length": float(np.mean(ep["steps"])),
        **metric_values(
            ep["success"],
            ep["entered"],
            ep["path_length"],
            ep["optimal_length"],
            ep["search_length"],
            opt_s,
            ep["nav_length"],
            ep["optimal_nav_length"],
            protocol=protocol,
        ),
    }
    for k, v in ep.items():
        if k.startswith("reward/"):
            out[k] = float(np.mean(v))
    return out
