"""Batched scripted policies for evaluation and sanity baselines, and the :class:`Policy` hook.

A policy sees the observation dict of :class:`~tsnav.sim.batch.BatchEnv` (``(B,)`` arrays ``state`` global
state id, ``target`` category id, ``scene``, ``step``, plus ``active`` from the runner) and returns ``(B,)``
int64 actions in the order of ``constants.ACTIONS``. Actions of inactive rows are ignored.

* :class:`RandomPolicy` — uniform over the 6 actions.
* :class:`OraclePolicy` — follows a shortest path on the optimal distance field, then Done (SR = SPL = 1).
* :class:`ExplorerPolicy` — a coverage-driven scripted searcher: it looks around (a full turn) at the start
  and at every waypoint it reaches, walks to the nearest waypoint not yet visited, and once the target is
  detected (the stage switch of paper III-B) follows the shortest path to success and outputs Done.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from ..constants import DONE, NUM_ACTIONS, ROTATE_RIGHT, ROTATE_STEP
from ..sim.batch import SceneBank
from ..sim.paths import UNREACHABLE, distance_fields, optimal_action_targets
from ..sim.stage import above_threshold


@runtime_checkable
class Policy(Protocol):
    """What the evaluation runner drives; learned agents implement the same two methods."""

    def reset(self, mask: np.ndarray) -> None:
        """Rows where ``mask`` (``(B,)`` bool) is True start a new episode: clear their memory."""

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """``(B,)`` int64 actions for the observation batch."""


class RandomPolicy:
    """Uniform over the 6 actions (Done included), seeded."""

    def __init__(self, seed: int = 0):
        self.rng = np.random.default_rng(seed)

    def reset(self, mask: np.ndarray) -> None:
        return None

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        return self.rng.integers(0, NUM_ACTIONS, size=len(obs["state"]), dtype=np.int64)


class OraclePolicy:
    """Shortest path to the nearest success state of the target, then Done (lowest action id on ties).
    Outputs Done where no success state can be reached."""

    def __init__(self, bank: SceneBank):
        self.bank = bank

    def reset(self, mask: np.ndarray) -> None:
        return None

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        a = optimal_action_targets(self.bank.next_state, self.bank.dist, obs["state"], obs["target"], DONE)
        return np.where(a < 0, DONE, a)


@dataclass
class ExplorerConfig:
    """Parameters of the scripted explorer."""

    cover_radius: float = 1.0
    """Every reachable position lies within this many metres of some waypoint (farthest-point sampling)."""
    look_around: bool = True
    """Turn a full circle (7 x RotateRight) at the start and at each newly reached waypoint."""


def scene_waypoints(x: np.ndarray, z: np.ndarray, radius: float) -> np.ndarray:
    """Indices (into the given positions) of waypoints covering every position within ``radius`` metres,
    chosen by farthest-point sampling from the first position (deterministic)."""
    pts = np.stack([x, z], axis=1).astype(np.float64)
    chosen = [0]
    d = np.hypot(*(pts - pts[0]).T)
    while d.max() > radius + 1e-9:
        j = int(np.argmax(d))
        chosen.append(j)
        d = np.minimum(d, np.hypot(*(pts - pts[j]).T))
    return np.array(chosen, dtype=np.int64)


class ExplorerPolicy:
    """Coverage-driven search then shortest-path pathfinding (a sanity baseline; see the module docstring).

    Per scene, waypoints cover the reachable positions (:func:`scene_waypoints`); ``wp_dist[s, j]`` is the
    number of actions from global state ``s`` to the level-view (horizon 0) states of waypoint ``j`` of the
    scene of ``s``. Detection uses ``bank.stage_confidence > c_target`` (the runner's stage switch).
    """

    def __init__(self, bank: SceneBank, config: ExplorerConfig | None = None, c_target: float | None = None):
        self.bank = bank
        self.config = config or ExplorerConfig()
        thr = bank.c_target if c_target is None else c_target
        self.detect = above_threshold(bank.stage_confidence, thr)
        fields, counts = [], []
        for i in range(bank.num_scenes):
            lo, hi = int(bank.offsets[i]), int(bank.offsets[i + 1])
            pos = bank.position[lo:hi]
            uniq, first = np.unique(pos, return_index=True)
            wp = scene_waypoints(bank.x[lo:hi][first], bank.z[lo:hi][first], self.config.cover_radius)
            src = (pos[:, None] == uniq[wp][None, :]) & (bank.horizon[lo:hi] == 0)[:, None]
            local_next = bank.next_state[lo:hi].astype(np.int64) - lo
            fields.append(distance_fields(local_next, src))
            counts.append(len(wp))
        w_max = max(counts)
        self.num_waypoints = np.array(counts, dtype=np.int64)
        self.wp_dist = np.full((bank.num_states, w_max), UNREACHABLE, dtype=np.int32)
        for i, f in enumerate(fields):
            self.wp_dist[bank.offsets[i] : bank.offsets[i + 1], : f.shape[1]] = f
        self.visited = np.zeros((0, w_max), dtype=bool)
        self.spin = np.zeros(0, dtype=np.int64)
        self.found = np.zeros(0, dtype=bool)

    def _ensure(self, n: int) -> None:
        if len(self.spin) != n:
            self.visited = np.zeros((n, self.wp_dist.shape[1]), dtype=bool)
            self.spin = np.zeros(n, dtype=np.int64)
            self.found = np.zeros(n, dtype=bool)
            self._fresh = np.ones(n, dtype=bool)

    def reset(self, mask: np.ndarray) -> None:
        mask = np.asarray(mask, dtype=bool)
        self._ensure(len(mask))
        self.visited[mask] = False
        self.spin[mask] = 0
        self.found[mask] = False
        self._fresh[mask] = True

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        s = np.asarray(obs["state"], dtype=np.int64)
        g = np.asarray(obs["target"], dtype=np.int64)
        n = len(s)
        self._ensure(n)
        bank = self.bank
        rows = np.arange(n)
        self.found |= self.detect[s, g]
        turns = 360 // ROTATE_STEP - 1
        if self.config.look_around:
            self.spin[self._fresh] = turns
        self._fresh[:] = False
        # Waypoints reached now: mark them, and look around at newly reached ones.
        d_here = self.wp_dist[s]  # (B, W)
        arrived = (d_here == 0) & ~self.visited
        self.visited |= d_here == 0
        if self.config.look_around:
            self.spin[arrived.any(axis=1)] = turns
        valid = d_here < UNREACHABLE
        todo = valid & ~self.visited
        exhausted = ~todo.any(axis=1)
        if exhausted.any():  # everything visited: start another sweep
            self.visited[exhausted] = False
            self.visited[exhausted] |= d_here[exhausted] == 0
            todo = valid & ~self.visited
        goal = np.argmin(np.where(todo, d_here, UNREACHABLE), axis=1)  # (B,)
        nxt = bank.next_state[s, :DONE].astype(np.int64)  # (B, 5)
        d_next = self.wp_dist[nxt, goal[:, None]]
        explore = np.argmin(d_next, axis=1).astype(np.int64)
        explore = np.where(todo[rows, goal], explore, ROTATE_RIGHT)
        spinning = self.spin > 0
        explore = np.where(spinning, ROTATE_RIGHT, explore)
        self.spin = np.maximum(self.spin - 1, 0)
        path = optimal_action_targets(bank.next_state, bank.dist, s, g, DONE)
        use_path = self.found & (path >= 0)
        return np.where(use_path, path, explore).astype(np.int64)


def make_policy(name: str, bank: SceneBank, seed: int = 0, c_target: float | None = None):
    """A policy by name: ``random``, ``oracle``, ``explorer``, or ``package.module:factory`` where
    ``factory(bank, seed=..., c_target=...)`` returns a :class:`Policy` (the hook for learned agents)."""
    if name == "random":
        return RandomPolicy(seed)
    if name == "oracle":
        return OraclePolicy(bank)
    if name == "explorer":
        return ExplorerPolicy(bank, c_target=c_target)
    if ":" in name:
        mod, _, attr = name.partition(":")
        try:
            factory = getattr(importlib.import_module(mod), attr)
        except (ImportError, AttributeError) as e:
            raise ValueError(f"policy {name!r}: cannot import ({e})") from None
        policy = factory(bank, seed=seed, c_target=c_target)
        if not isinstance(policy, Policy):
            raise ValueError(f"policy {name!r}: the factory did not return an object with reset(mask) and act(obs)")
        return policy
    raise ValueError(f"unknown policy {name!r} (choose random, oracle, explorer or module:factory)")
