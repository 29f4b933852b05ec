"""Evaluation runner: a batched policy over a fixed episode list, with the two-stage bookkeeping of paper
III-B / IV-A, producing :class:`~tsnav.eval.metrics.EpisodeRecord` objects.

All episodes of a chunk (``batch_size``, default: all of them) run in parallel in one
:class:`~tsnav.sim.batch.BatchEnv` without auto-reset, ``max_steps`` = 100 as in the paper's tests.

Stage switch: an episode enters the pathfinding stage at the first observed frame (the start frame
included) whose target confidence exceeds ``c_target`` (0.7). The confidence is the detector's when the
bank has one, else the ground-truth "target in frame" flag as 1.0 (see ``SceneBank.stage_confidence``).
``pathfinding_start_step`` is the number of actions output before that frame; the searching path length
is the number of movement actions output before it, the pathfinding path length the number output after.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..sim.batch import BatchEnv, SceneBank
from ..sim.episodes import Episode, episodes_to_arrays
from ..sim.paths import UNREACHABLE, distance_fields
from .metrics import EpisodeRecord


@dataclass
class EvalConfig:
    """Evaluation settings (paper IV-A)."""

    max_steps: int = 100
    """Episode length limit at test time (paper: 100 actions)."""
    c_target: float = 0.7
    """Stage-switch threshold C_target on the target confidence (paper IV-A: 0.7)."""
    min_optimal_length: int = 5
    """The "L >= 5" subset of the paper's tables."""
    batch_size: int = 4096
    """Episodes stepped together; the list is processed in chunks of this size."""


def evaluate(bank: SceneBank, episodes: list[Episode], policy, config: EvalConfig | None = None) -> list[EpisodeRecord]:
    """Run ``policy`` (a :class:`~tsnav.eval.policies.Policy`) on every episode; one record per episode, in
    the order of ``episodes``."""
    config = config or EvalConfig()
    if config.batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {config.batch_size}")
    scene_idx, target, start = episodes_to_arrays(bank, episodes)
    stage = bank.stage_confidence > config.c_target
    search_dist = bank.search_dist if config.c_target == bank.c_target else distance_fields(bank.next_state, stage)
    records: list[EpisodeRecord] = []
    for lo in range(0, len(episodes), config.batch_size):
        hi = min(lo + config.batch_size, len(episodes))
        cols = _run_chunk(bank, scene_idx[lo:hi], target[lo:hi], start[lo:hi], policy, stage, config)
        opt_search = search_dist[start[lo:hi], target[lo:hi]]
        for j in range(hi - lo):
            e = episodes[lo + j]
            nav = bool(cols["entered"][j])
            L = int(cols["path_length"][j])
            Ls = int(cols["switch_length"][j]) if nav else L
            os_ = int(opt_search[j])
            records.append(EpisodeRecord(
                success=bool(cols["success"][j]), path_length=L, optimal_length=int(e.optimal_length),
                entered_pathfinding=nav, pathfinding_start_step=int(cols["switch_step"][j]) if nav else None,
                search_path_length=Ls, optimal_search_length=-1 if os_ == UNREACHABLE else os_,
                pathfinding_path_length=(L - Ls) if nav else None,
                optimal_pathfinding_length=int(cols["switch_opt"][j]) if nav else None,
                room_type=e.room_type, scene=e.scene, target=e.target, start=e.start,
                steps=int(cols["steps"][j]), episode=lo + j))
    return records


def _run_chunk(bank, scene_idx, target, start, policy, stage, config) -> dict[str, np.ndarray]:
    n = len(start)
    env = BatchEnv(bank, n, max_steps=config.max_steps, autoreset=False)
    obs = env.reset(episodes=(scene_idx, target, start))
    policy.reset(np.ones(n, dtype=bool))
    entered = stage[start, target].copy()
    switch_step = np.zeros(n, dtype=np.int64)
    switch_length = np.zeros(n, dtype=np.int64)
    switch_state = start.copy()
    success = np.zeros(n, dtype=bool)
    steps = np.zeros(n, dtype=np.int64)
    path_length = np.zeros(n, dtype=np.int64)
    for _ in range(config.max_steps):
        if not env.active.any():
            break
        obs["active"] = env.active.copy()
        actions = np.asarray(policy.act(obs), dtype=np.int64)
        if actions.shape != (n,):
            raise ValueError(f"the policy returned actions of shape {actions.shape}, expected ({n},)")
        obs, _, term, trunc, info = env.step(actions)
        act = info["active"]
        new = act & ~entered & stage[info["final_state"], target]
        entered |= new
        switch_step[new] = info["steps"][new]
        switch_length[new] = info["path_length"][new]
        switch_state[new] = info["final_state"][new]
        fin = term | trunc
        success[fin] = info["success"][fin]
        steps[act] = info["steps"][act]
        path_length[act] = info["path_length"][act]
    switch_opt = bank.dist[switch_state, target]
    return {"entered": entered, "switch_step": switch_step, "switch_length": switch_length,
            "switch_opt": switch_opt, "success": success, "steps": steps, "path_length": path_length}


def config_dict(config: EvalConfig) -> dict:
    return asdict(config)

