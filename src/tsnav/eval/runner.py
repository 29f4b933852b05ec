"""Evaluation runner: a batched policy over a fixed episode list, with the two-stage bookkeeping of paper
III-B / IV-A, producing :class:`~tsnav.metrics.EpisodeRecord` objects; and the evaluation folder
(``records.jsonl``, ``trajectories.jsonl``, ``metrics.json``): writing one (:func:`evaluate_to_folder`) and
rebuilding its bank, policy and trajectories (:func:`eval_bank`, :func:`eval_policy`, :func:`eval_trajectories`).

All episodes of a chunk (``batch_size``, default: all of them) run in parallel in one
:class:`~tsnav.sim.batch.BatchEnv` without auto-reset, ``max_steps`` = 100 as in the paper's tests.

Stage switch: an episode enters the pathfinding stage at the first observed frame (the start frame
included) whose target confidence exceeds ``c_target`` (0.7). The confidence is the detector's when the
bank has one, else the ground-truth "target in frame" flag as 1.0 (see ``SceneBank.stage_confidence``).
``pathfinding_start_step`` is the number of actions output before that frame; the searching path length
is the number of movement actions output before it, the pathfinding path length the number output after.

The runner keeps only per-episode counts. For pictures we need the states an agent went through, so
:func:`record_trajectories` runs :func:`evaluate` unchanged with the policy wrapped in a
:class:`TrajectoryRecorder` that notes the observed state and the returned action of every row at every
step. The records are therefore exactly those of a plain evaluation (same batches, same policy calls, same
random draws), and each :class:`Trajectory` is consistent with its record (``len(actions) == steps``;
movement actions ``== path_length``).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..atomic import atomic_write_text
from ..constants import ACTION_ORDER, C_TARGET, OLD_ACTION_ORDER, action_permutation, check_same_class_set, class_set_of
from ..data.reader import is_complete, load_scene
from ..errors import CommandError, read_json
from ..sim.batch import BatchEnv, SceneBank
from ..sim.episodes import Episode, episodes_to_arrays, read_episodes
from ..sim.paths import UNREACHABLE, distance_fields
from ..sim.stage import StageSwitch, switch_frame
from ..protocol import check_protocol, protocol_of
from ..rl.stats import stage_lengths
from ..metrics import EpisodeRecord, read_records, summarize, write_json, write_records
from .outcomes import OUTCOMES_FILE, outcome_summary
from .policies import make_policy


@dataclass
class EvalConfig:
    """Evaluation settings (paper IV-A)."""

    max_steps: int = 100
    """Episode length limit at test time (paper: 100 actions)."""
    c_target: float = C_TARGET
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
    switch = StageSwitch(bank, config.c_target)
    search_dist = (
        bank.search_dist if config.c_target == bank.c_target else distance_fields(bank.next_state, switch.switches)
    )
    records: list[EpisodeRecord] = []
    for lo in range(0, len(episodes), config.batch_size):
        hi = min(lo + config.batch_size, len(episodes))
        cols = _run_chunk(bank, scene_idx[lo:hi], target[lo:hi], start[lo:hi], policy, switch, config)
        lengths = stage_lengths(
            bank.dist,
            search_dist,
            start[lo:hi],
            target[lo:hi],
            cols["path_length"],
            cols["entered"],
            cols["switch_length"],
            cols["switch_state"],
            unreachable=-1,
        )
        for j in range(hi - lo):
            e = episodes[lo + j]
            nav = bool(cols["entered"][j])
            records.append(
                EpisodeRecord(
                    success=bool(cols["success"][j]),
                    path_length=int(cols["path_length"][j]),
                    optimal_length=int(e.optimal_length),
                    entered_pathfinding=nav,
                    pathfinding_start_step=int(cols["switch_step"][j]) if nav else None,
                    search_path_length=int(lengths["search_length"][j]),
                    optimal_search_length=int(lengths["optimal_search_length"][j]),
                    pathfinding_path_length=int(lengths["nav_length"][j]) if nav else None,
                    optimal_pathfinding_length=int(lengths["optimal_nav_length"][j]) if nav else None,
                    room_type=e.room_type,
                    scene=e.scene,
                    target=e.target,
                    start=e.start,
                    steps=int(cols["steps"][j]),
                    episode=lo + j,
                )
            )
    return records


def _run_chunk(bank, scene_idx, target, start, policy, switch: StageSwitch, config) -> dict[str, np.ndarray]:
    n = len(start)
    env = BatchEnv(bank, n, max_steps=config.max_steps, autoreset=False, stage=switch)  # the env keeps the stage
    obs = env.reset(episodes=(scene_idx, target, start))
    policy.reset(np.ones(n, dtype=bool))
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
        fin = term | trunc
        success[fin] = info["success"][fin]
        steps[act] = info["steps"][act]
        path_length[act] = info["path_length"][act]
    return {
        "entered": switch.entered.copy(),
        "switch_step": switch.switch_step.copy(),
        "switch_length": switch.switch_length.copy(),
        "switch_state": switch.switch_state.copy(),
        "success": success,
        "steps": steps,
        "path_length": path_length,
    }


def config_dict(config: EvalConfig) -> dict:
    return asdict(config)


# ---------------------------------------------------------------------------------------------------------
# Trajectories (for the gallery)
# ---------------------------------------------------------------------------------------------------------


@dataclass
class Trajectory:
    """The frames and actions of one evaluation episode (frames 0..T: the start frame, then one per action)."""

    episode: int
    """Index of the episode in its episode list (``EpisodeRecord.episode``)."""
    scene: str
    target: str
    keys: list[str]
    """State keys of the frames, start first (``len(actions) + 1`` entries)."""
    actions: list[int]
    """Action ids in the order of ``constants.ACTIONS``, Done included."""
    switch_frame: int = -1
    """First frame whose target confidence exceeded C_target (the pathfinding stage starts there), or -1."""
    success_frame: int | None = None
    """First frame in a success state for the target (in view within the success distance; Done there would have
    succeeded), -1 when the episode never was in one, None in files written before this field existed."""
    switch_distance: int | None = None
    """L* at the switch frame: the fewest movement actions from there to a success state (Done not counted), -1
    when the switch never fired or no success state can be reached from there, None in older files."""
    success_after_switch: int | None = None
    """First frame at or after the switch frame in a success state, -1 when there is none (or no switch), None in
    older files."""
    success: bool = False
    action_order: str = ACTION_ORDER
    """The order ``actions`` are written in (``constants.ACTION_ORDER``); files without it are from the old order."""

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)


class TrajectoryRecorder:
    """A :class:`~tsnav.eval.policies.Policy` wrapper noting ``obs["state"]``, ``obs["active"]`` and the actions.

    Each ``reset`` whose mask is all True starts a new chunk (the runner resets once per chunk of episodes).
    """

    def __init__(self, policy):
        self.policy = policy
        self.chunks: list[dict[str, list[np.ndarray]]] = []

    def reset(self, mask: np.ndarray) -> None:
        mask = np.asarray(mask, dtype=bool)
        if mask.all():
            self.chunks.append({"state": [], "active": [], "action": []})
        self.policy.reset(mask)

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        a = np.asarray(self.policy.act(obs))
        c = self.chunks[-1]
        c["state"].append(np.asarray(obs["state"], dtype=np.int64).copy())
        c["active"].append(np.asarray(obs.get("active", np.ones(len(a), bool)), dtype=bool).copy())
        c["action"].append(a.astype(np.int64).copy())
        return a


def first_true(flags) -> int:
    """Index of the first True of ``flags``, -1 when there is none."""
    hit = np.flatnonzero(np.asarray(flags, dtype=bool))
    return int(hit[0]) if len(hit) else -1


def record_trajectories(
    bank, episodes, policy, config: EvalConfig | None = None
) -> tuple[list[EpisodeRecord], list[Trajectory]]:
    """Evaluate ``policy`` on ``episodes`` (exactly like :func:`evaluate`) and return the
    records together with one :class:`Trajectory` per episode, in the same order."""
    config = config or EvalConfig()
    rec = TrajectoryRecorder(policy)
    records = evaluate(bank, episodes, rec, config)
    conf = bank.stage_confidence
    trajectories: list[Trajectory] = []
    lo = 0
    for chunk in rec.chunks:
        states = np.stack(chunk["state"]) if chunk["state"] else np.zeros((0, 0), np.int64)  # [T, B]
        active = np.stack(chunk["active"]) if chunk["active"] else np.zeros((0, 0), bool)
        actions = np.stack(chunk["action"]) if chunk["action"] else np.zeros((0, 0), np.int64)
        n = states.shape[1] if states.ndim == 2 and states.shape[0] else 0
        for j in range(n):
            r = records[lo + j]
            t = np.flatnonzero(active[:, j])
            s, a = states[t, j], actions[t, j]
            if len(s):
                final = int(bank.next_state[s[-1], a[-1]])
                frames = np.concatenate([s, [final]])
            else:
                frames = np.array([bank.global_state(bank.scene_index(r.scene), r.start)], dtype=np.int64)
            g = bank.class_set.index[r.target]
            sw = switch_frame(conf[frames, g], config.c_target)
            hit = bank.success[frames, g]
            d = int(bank.dist[frames[sw], g]) if sw >= 0 else -1
            reach = first_true(hit[sw:]) if sw >= 0 else -1
            trajectories.append(
                Trajectory(
                    episode=r.episode,
                    scene=r.scene,
                    target=r.target,
                    keys=[str(k) for k in bank.keys[frames]],
                    actions=[int(x) for x in a],
                    switch_frame=sw,
                    success_frame=first_true(hit),
                    switch_distance=d if d != UNREACHABLE else -1,
                    success_after_switch=sw + reach if reach >= 0 else -1,
                    success=bool(r.success),
                )
            )
        lo += n
    if len(trajectories) != len(records):
        raise RuntimeError(f"recorded {len(trajectories)} trajectories for {len(records)} episodes")
    return records, trajectories


def write_trajectories(path: str | Path, trajectories: Sequence[Trajectory]) -> None:
    """JSON Lines, one trajectory per line, written atomically."""
    atomic_write_text(Path(path), "".join(t.to_json() + "\n" for t in trajectories))


def read_trajectories(path: str | Path) -> list[Trajectory]:
    """Trajectories of a JSON Lines file, action ids converted to ``constants.ACTIONS`` (lines without an
    ``action_order`` were written in ``constants.OLD_ACTION_ORDER``); ``ValueError`` naming the line otherwise."""
    out = []
    with open(path) as f:
        for i, line in enumerate(f, 1):
            if line.strip():
                try:
                    d = json.loads(line)
                    perm = action_permutation(d.pop("action_order", OLD_ACTION_ORDER))
                    d["actions"] = [int(perm[a]) for a in d["actions"]]
                    out.append(Trajectory(**d))
                except (json.JSONDecodeError, TypeError, KeyError, IndexError, ValueError) as e:
                    raise ValueError(f"{path}:{i}: not a trajectory ({e})") from None
    return out


# ---------------------------------------------------------------------------------------------------------
# Evaluation folders
# ---------------------------------------------------------------------------------------------------------


def load_bank_for_episodes(data, episodes, **bank_kwargs):
    """A :class:`SceneBank` of exactly the scenes an episode list refers to (folders ``data/<scene>``)."""
    names = sorted({e.scene for e in episodes})
    scenes = []
    for name in names:
        p = Path(data) / name
        if not is_complete(p):
            raise CommandError(f"{p}: scene of the episode list is missing or incomplete")
        scenes.append(load_scene(p))
    return SceneBank(scenes, **bank_kwargs)


def run_protocol(run: str | Path) -> str:
    """The success protocol a training run was trained under (its ``config.json``; ``paper`` for runs made
    before protocols were recorded)."""
    path = Path(run) / "config.json"
    if not path.exists():
        raise CommandError(f"{run}: not a training run (no config.json)")
    cfg = read_json(path)
    return protocol_of(cfg.get("train", {}))


def resolve_protocol(
    episodes_meta: dict, episodes_file, run=None, protocol: str | None = None
) -> tuple[str, str | None]:
    """``(evaluated, trained)``: the protocol an evaluation counts under and the one the agent of ``run`` was
    trained under (None for scripted policies). The episode list fixes the first (its L* and its start-success
    episodes were drawn under it); ``protocol``, when given, must be it. An agent trained under another
    protocol is refused in one line unless ``protocol`` is given: naming it is how one agent is evaluated
    across protocols (on a list drawn under each, ``tsnav episodes --protocol``)."""
    listed = protocol_of(episodes_meta)
    if protocol is not None:
        protocol = check_protocol(protocol)
        if protocol != listed:
            raise CommandError(
                f"{episodes_file} was drawn under the {listed} protocol; to evaluate under {protocol} "
                f"use a list drawn under it (tsnav episodes --protocol {protocol})"
            )
    trained = run_protocol(run) if run is not None else None
    if trained is not None and trained != listed and protocol is None:
        raise CommandError(
            f"{run} was trained under the {trained} protocol but {episodes_file} is a {listed} "
            f"episode list; pass --protocol {listed} to evaluate it across protocols"
        )
    return listed, trained


def eval_bank(meta: dict, episodes):
    """The scene bank an evaluation folder's ``metrics.json`` describes (same scenes, success protocol and
    distance, C_target and detection tables)."""
    cfg = meta.get("config", {})
    bank = load_bank_for_episodes(
        meta["data"],
        episodes,
        success_distance=float(meta.get("success_distance", 1.0)),
        c_target=float(cfg.get("c_target", C_TARGET)),
        protocol=protocol_of(meta),
    )
    if meta.get("detections"):
        bank.install_detections(meta["detections"])
    return bank


def eval_policy(meta: dict, bank):
    """The policy of an evaluation folder: the trained agent of ``meta["run"]`` (or of a ``run:PATH`` policy, as
    ``tsnav eval --run`` records it) or a scripted policy. The agent acts greedily unless ``meta["sample"]`` is
    true; folders written before that key existed were evaluated by sampling, so a missing key means
    sampling (a re-roll must reproduce the recorded episodes)."""
    seed = int(meta.get("seed", 0))
    name = str(meta.get("policy", "explorer"))
    run = meta.get("run") or (name[len("run:") :] if name.startswith("run:") else None)
    if run:
        # lazy: rl.checkpoint imports torch (about 1.9 s, `python -X importtime`), which scripted policies never need
        from ..rl.checkpoint import load_policy

        return load_policy(
            run,
            bank,
            greedy=not bool(meta.get("sample", True)),
            seed=seed,
            checkpoint=meta.get("checkpoint", "auto"),
            detections=meta.get("detections"),
        )
    return make_policy(name, bank, seed=seed, c_target=bank.c_target)


def eval_trajectories(eval_dir: str | Path):
    """``(bank, records, trajectories, c_target)`` of an evaluation folder; trajectories are read from
    ``trajectories.jsonl`` or re-rolled with the recorded policy and seed."""
    eval_dir = Path(eval_dir)
    meta = json.loads((eval_dir / "metrics.json").read_text())
    episodes, _ = read_episodes(meta["episodes_file"])
    bank = eval_bank(meta, episodes)
    records = read_records(eval_dir / "records.jsonl")
    cfg = meta.get("config", {})
    c_target = bank.c_target  # eval_bank took it from the folder's config
    tp = eval_dir / "trajectories.jsonl"
    if tp.exists():
        trajectories = read_trajectories(tp)
    else:
        config = EvalConfig(
            max_steps=int(cfg.get("max_steps", 100)), c_target=c_target, batch_size=int(cfg.get("batch_size", 4096))
        )
        policy = eval_policy(meta, bank)
        rerolled, trajectories = record_trajectories(bank, episodes, policy, config)
        same = [
            (a.success, a.path_length, a.steps) == (b.success, b.path_length, b.steps)
            for a, b in zip(rerolled, records)
        ]
        if len(rerolled) != len(records) or not all(same):
            raise ValueError(f"{eval_dir}: re-rolled episodes differ from records.jsonl (another policy or data?)")
        try:
            write_trajectories(tp, trajectories)
        except OSError:
            pass
    if len(trajectories) != len(records):
        raise ValueError(f"{tp}: {len(trajectories)} trajectories for {len(records)} records")
    return bank, records, trajectories, c_target


def evaluate_to_folder(
    out_dir: str | Path,
    data: str | Path,
    episodes_file: str | Path,
    policy: str = "explorer",
    run: str | Path | None = None,
    detections: str | None = None,
    c_target: float = C_TARGET,
    seed: int = 0,
    label: str | None = None,
    max_steps: int = 100,
    sample: bool = False,
    checkpoint: str = "auto",
    success_distance: float | None = None,
    batch_size: int = 4096,
    protocol: str | None = None,
    videos: int = 0,
) -> dict:
    """Evaluate a scripted policy (``random`` / ``oracle`` / ``explorer``) or the trained agent of ``run`` on an
    episode list; writes ``records.jsonl``, ``trajectories.jsonl`` and ``metrics.json`` (with everything
    :mod:`tsnav.report.html` needs to rebuild the bank and the policy). The agent acts greedily (argmax, the
    lineage's test-time rule) unless ``sample``; ``checkpoint`` names which of the run's checkpoints
    (``auto`` / ``best`` / ``latest`` / a folder, as :func:`~tsnav.rl.checkpoint.resolve_checkpoint`), recorded so
    that a re-roll loads the same one. ``success_distance`` (metres) defaults to the episode list's;
    ``batch_size`` episodes are stepped together. This is ``tsnav eval``; it also writes ``outcomes.json``
    (:func:`~tsnav.eval.outcomes.outcome_summary`: how episodes ended, with and without the stage switch).
    The success protocol is the episode list's (:func:`resolve_protocol`: ``protocol`` given explicitly lets
    an agent trained under the other one be evaluated); ``metrics.json`` records it as ``protocol`` and the
    agent's as ``trained_protocol``. ``videos`` > 0 also writes clips of that many episodes into ``videos/``
    (:func:`tsnav.eval.video.write_evaluation_videos`). Returns the :func:`summarize` result."""
    out_dir = Path(out_dir)
    episodes, emeta = read_episodes(episodes_file)
    if not episodes:
        raise CommandError(f"{episodes_file}: the episode list is empty")
    protocol, trained = resolve_protocol(emeta, episodes_file, run, protocol)
    if success_distance is None:
        success_distance = float(emeta.get("success_distance", 1.0))
    config = EvalConfig(max_steps=max_steps, c_target=c_target, batch_size=batch_size)
    meta = {
        "policy": "agent" if run else policy,
        "run": str(Path(run).resolve()) if run else None,
        "seed": seed,
        "sample": bool(sample),
        "checkpoint": str(checkpoint) if run else None,
        "episodes_file": str(Path(episodes_file).resolve()),
        "data": str(Path(data).resolve()),
        "protocol": protocol,
        "trained_protocol": trained,
        "success_distance": float(success_distance),
        "detections": detections,
        "config": config_dict(config),
        "label": label or (f"agent {Path(run).name}" if run else policy),
    }
    bank = eval_bank(meta, episodes)
    try:
        check_same_class_set(class_set_of(emeta), bank.class_set, str(episodes_file), f"the scenes of {data}")
    except ValueError as e:
        raise CommandError(str(e)) from None
    pol = eval_policy(meta, bank)
    t0 = time.perf_counter()
    records, trajectories = record_trajectories(bank, episodes, pol, config)
    summary = summarize(records, config.min_optimal_length, protocol=protocol)
    write_evaluation(out_dir, meta, summary, records, trajectories, bank, time.perf_counter() - t0)
    if videos > 0:
        from .video import write_evaluation_videos  # matplotlib, Pillow and ffmpeg only when clips are asked for

        write_evaluation_videos(out_dir, bank, records, trajectories, videos, config.c_target)
    return summary


def write_evaluation(out_dir: Path, meta: dict, summary: dict, records, trajectories, bank, seconds: float) -> None:
    """The files of an evaluation folder: ``records.jsonl``, ``trajectories.jsonl``, ``outcomes.json`` and
    ``metrics.json`` (``meta`` with the metrics, the time taken and whether the bank had a detector's confidence)."""
    write_records(out_dir / "records.jsonl", records)
    write_trajectories(out_dir / "trajectories.jsonl", trajectories)
    write_json(out_dir / OUTCOMES_FILE, outcome_summary(records, trajectories))
    write_json(
        out_dir / "metrics.json",
        {**meta, "metrics": summary, "seconds": seconds, "detector_confidence": bank.confidence is not None},
    )
