"""Episodes: the training sampler and fixed validation / test episode lists (paper III-A, IV-A).

An episode is (scene, target category, start state). A valid episode has the target present in the scene,
a start state from which a success state of the target can be reached, and, under the ``paper`` success
protocol, a start that is not already a success state (the ``lineage`` protocol keeps those, L* = 0, as the
lineage's test lists do; :mod:`tsnav.protocol`). Starts take any of the 8 rotations and, as in the lineage's
test splits, horizon 0 or 30 (fixed lists draw each horizon with probability 1/2 per (scene, target) pair;
``start_horizon`` restricts them to one). Success is a property of the full state, horizon included, so under
``paper`` a start looking down that already sees the target close by is excluded like any other; the
optimal length stored with fixed episodes is L* of :mod:`tsnav.sim.paths` from the start state itself
(movement actions, Done not counted), so a start at horizon 30 counts the LookUp it may need.

Episode lists are JSON::

    {"format": "tsnav-episodes", "version": 1, "split": "test", "protocol": "paper", "success_distance": 1.0,
     "seed": 0, "per_room_type": 250, "start_horizon": null,
     "episodes": [{"scene": "FloorPlan1", "target": "Bowl", "start": "0.50|3.50|315|0",
                   "optimal_length": 7, "room_type": "kitchen"}, ...]}

A list of scenes of another class set than ``ithor22`` records it (``"class_set": "robothor12"``; absent means
``ithor22``). Lists converted from the RoboTHOR challenge's (:mod:`tsnav.sim.challenge`) add per episode
``optimal_metres`` and ``challenge`` (the source record); other lists do not carry these keys.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_text
from ..constants import DEFAULT_CLASS_SET
from ..errors import read_json
from ..protocol import spec
from .batch import BatchEnv, EpisodeSampler, RewardFn, SceneBank, SimConfig
from .paths import UNREACHABLE

EPISODES_FORMAT = "tsnav-episodes"
EPISODES_VERSION = 1


@dataclass
class EpisodeConfig:
    """How episodes are drawn (training sampler and fixed lists)."""

    start_horizon: int | None = None
    """Camera horizon of start states in degrees (0 = level, 30 = looking down); None (default) allows both,
    as the lineage's test splits have them (about half each)."""
    room_targets: bool = True
    """Restrict targets to the lineage's per-room-type target list (constants.ROOM_TARGETS, the ``ithor22``
    class set's room lists) when the scene's room type has one; other room types (and class sets without room
    lists, such as ``robothor12``) use every category present."""
    keep_start_success: bool | None = None
    """Keep starts that already succeed (L* = 0); None (default) follows the bank's success protocol:
    ``paper`` leaves them out, ``lineage`` keeps them, as the lineage's test lists and trainer do
    (:mod:`tsnav.protocol`)."""


@dataclass
class ValidStarts:
    """CSR table of valid (scene, target, start) triples, grouped by (scene, target) pair.

    ``pair_scene[p]``, ``pair_target[p]`` describe pair ``p``; its valid global start states are
    ``starts[ptr[p]:ptr[p+1]]``. Pairs are sorted by scene then target; ``scene_ptr[i]:scene_ptr[i+1]`` are
    the pairs of scene ``i``.
    """

    pair_scene: np.ndarray
    pair_target: np.ndarray
    ptr: np.ndarray
    starts: np.ndarray
    scene_ptr: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.ptr)


def allowed_targets(bank: SceneBank, config: EpisodeConfig) -> np.ndarray:
    """``(N, C)`` bool: categories that may be targets in each scene (present, and in the room's list)."""
    allowed = bank.present.copy()
    if config.room_targets:
        for i, rt in enumerate(bank.room_types):
            allowed[i] &= bank.class_set.room_target_mask(rt)
    return allowed


def valid_starts(bank: SceneBank, config: EpisodeConfig | None = None) -> ValidStarts:
    """All valid episodes of a bank as a :class:`ValidStarts` table (array operations, no loop over states)."""
    config = config or EpisodeConfig()
    keep = config.keep_start_success
    if keep is None:
        keep = spec(getattr(bank, "protocol", None)).keeps_start_success
    ok = bank.dist < UNREACHABLE
    if not keep:
        ok &= ~bank.success
    ok &= allowed_targets(bank, config)[bank.scene_of]
    if config.start_horizon is not None:
        ok &= (bank.horizon == config.start_horizon)[:, None]
    s, c = np.nonzero(ok)  # sorted by state (hence scene), then category
    C = bank.num_categories
    pair_key = bank.scene_of[s].astype(np.int64) * C + c
    order = np.argsort(pair_key, kind="stable")
    s, pair_key = s[order], pair_key[order]
    keys, first, counts = np.unique(pair_key, return_index=True, return_counts=True)
    ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    pair_scene = (keys // C).astype(np.int64)
    pair_target = (keys % C).astype(np.int64)
    scene_ptr = np.searchsorted(pair_scene, np.arange(bank.num_scenes + 1)).astype(np.int64)
    return ValidStarts(pair_scene, pair_target, ptr, s.astype(np.int64), scene_ptr)


class TrainingSampler:
    """Random training episodes (implements :class:`~tsnav.sim.batch.EpisodeSampler`).

    A scene is drawn uniformly among the scenes with a valid episode, a target uniformly among its valid
    categories, and a start uniformly among that target's valid start states. Fully vectorised.
    """

    def __init__(self, bank: SceneBank, config: EpisodeConfig | None = None):
        self.bank = bank
        self.config = config or EpisodeConfig()
        self.table = valid_starts(bank, self.config)
        if len(self.table.pair_scene) == 0:
            raise ValueError("no valid episode in these scenes (no reachable target category)")
        npairs = np.diff(self.table.scene_ptr)
        self.scenes = np.flatnonzero(npairs > 0)
        self._npairs = npairs
        self._counts = self.table.counts

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = self.table
        scene = self.scenes[rng.integers(0, len(self.scenes), size=n)]
        u = rng.random((2, n))
        pair = t.scene_ptr[scene] + (u[0] * self._npairs[scene]).astype(np.int64)
        start = t.starts[t.ptr[pair] + (u[1] * self._counts[pair]).astype(np.int64)]
        return scene, t.pair_target[pair], start

    def sample_one(self, rng: np.random.Generator) -> tuple[int, int, int]:
        """One episode as Python ints: the same draws from ``rng`` and the same episode as ``sample(1, rng)``
        (the single Gymnasium env's path; ``tests/sim/test_gym_fast.py`` holds them equal)."""
        t = self.table
        scene = int(self.scenes[rng.integers(0, len(self.scenes), size=1)[0]])
        u0, u1 = rng.random((2, 1))[:, 0]
        pair = int(t.scene_ptr[scene]) + int(u0 * self._npairs[scene])
        start = int(t.starts[int(t.ptr[pair]) + int(u1 * self._counts[pair])])
        return scene, int(t.pair_target[pair]), start


def make_env(
    scenes_or_bank,
    num_envs: int,
    config: SimConfig | None = None,
    sampler: EpisodeSampler | None = None,
    reward_fn: RewardFn | None = None,
    seed: int | None = None,
) -> BatchEnv:
    """A :class:`BatchEnv` over ``scenes_or_bank`` (a :class:`SceneBank` or a list of scenes) configured by
    ``config``; ``sampler`` defaults to the :class:`TrainingSampler`. With a bank, ``config``'s protocol and
    success distance must be the bank's (``ValueError`` otherwise: they are properties of the bank); C_target
    is the bank's alone (``SceneBank(c_target=)``, default 0.7)."""
    given = config is not None
    config = config or SimConfig()
    if isinstance(scenes_or_bank, SceneBank):
        bank = scenes_or_bank
        for name in ("protocol", "success_distance"):  # the bank's are in force: never ignore a config's
            if name == "success_distance" and bank.protocol != "paper":
                continue  # only the paper rule has a radius
            if given and getattr(config, name) != getattr(bank, name):
                raise ValueError(
                    f"SimConfig.{name} = {getattr(config, name)} differs from the bank's "
                    f"{getattr(bank, name)}; build the bank with it or pass the scenes instead"
                )
    else:
        bank = SceneBank(scenes_or_bank, success_distance=config.success_distance, protocol=config.protocol)
    if sampler is None:
        sampler = TrainingSampler(bank)
    return BatchEnv(
        bank,
        num_envs,
        sampler=sampler,
        reward_fn=reward_fn,
        max_steps=config.max_steps,
        autoreset=config.autoreset,
        seed=seed,
    )


@dataclass
class Episode:
    """One fixed evaluation episode."""

    scene: str
    target: str
    start: str
    """Start state key."""
    optimal_length: int
    """L*: movement actions to the nearest success state (Done not counted)."""
    room_type: str = "unknown"
    optimal_metres: float | None = None
    """Episodes converted from another benchmark's (:mod:`tsnav.sim.challenge`): the shortest walk in metres along
    the grid to a success position (turns free); None (not written) otherwise."""
    challenge: dict | None = None
    """The source episode's own record (id, start pose, its navmesh ``shortest_path_length``), for episodes
    converted from the RoboTHOR challenge's; None (not written) otherwise."""

    def to_json(self) -> dict:
        """The episode as a JSON object; the optional fields only when set, so lists without them read as before."""
        return {k: v for k, v in asdict(self).items() if v is not None or k not in _OPTIONAL}


_OPTIONAL = ("optimal_metres", "challenge")


def make_episodes(
    bank: SceneBank, per_room_type: int = 250, seed: int = 0, config: EpisodeConfig | None = None
) -> list[Episode]:
    """Draw a fixed episode list: ``per_room_type`` distinct episodes for each room type (fewer when the room
    type has fewer valid episodes), each (scene, target) pair of a room type equally likely and, within a
    pair, each start horizon that has valid starts equally likely (the lineage's test splits start about half
    at horizon 0, half at 30), like the lineage's 250 test episodes per room type. Deterministic for a given
    bank and ``seed``."""
    if per_room_type < 1:
        raise ValueError(f"per_room_type must be >= 1, got {per_room_type}")
    config = config or EpisodeConfig()
    t = valid_starts(bank, config)
    rng = np.random.default_rng(seed)
    rooms = np.array(bank.room_types)
    pair_room = rooms[t.pair_scene] if len(t.pair_scene) else np.zeros(0, dtype=rooms.dtype)
    npairs = np.diff(t.scene_ptr)
    out: list[Episode] = []
    for rt in sorted(set(bank.room_types)):
        pairs = np.flatnonzero(pair_room == rt)
        if len(pairs) == 0:
            continue
        scenes_rt = np.unique(t.pair_scene[pairs])
        # weight of a triple: 1 / (scenes of the room type * pairs of its scene * horizons of its pair
        #                          * starts of its pair at its horizon)
        cnt = t.counts[pairs]
        w_pair = 1.0 / (len(scenes_rt) * npairs[t.pair_scene[pairs]])
        idx = np.concatenate([np.arange(t.ptr[p], t.ptr[p + 1]) for p in pairs])
        pair_of = np.repeat(pairs, cnt)
        hor = np.asarray(bank.horizon)[t.starts[idx]].astype(np.int64)
        _, group, per_group = np.unique(pair_of * 1000 + hor, return_inverse=True, return_counts=True)
        _, hgroup = np.unique(pair_of, return_inverse=True)
        horizons_of_pair = np.bincount(hgroup[np.unique(group, return_index=True)[1]])  # horizons per pair
        w = np.repeat(w_pair, cnt) / (horizons_of_pair[hgroup] * per_group[group])
        k = min(per_room_type, len(idx))
        chosen = rng.choice(len(idx), size=k, replace=False, p=w / w.sum())
        for j in chosen:
            p, s = int(pair_of[j]), int(t.starts[idx[j]])
            c = int(t.pair_target[p])
            out.append(
                Episode(
                    scene=bank.names[int(t.pair_scene[p])],
                    target=bank.class_set.categories[c],
                    start=str(bank.keys[s]),
                    optimal_length=int(bank.dist[s, c]),
                    room_type=rt,
                )
            )
    return out


def episodes_to_arrays(bank: SceneBank, episodes: list[Episode], check: bool = True):
    """``(scene_idx, target, start_state)`` int64 arrays (global start ids) for :meth:`BatchEnv.reset`.

    With ``check``, each stored optimal length must equal the bank's (a mismatch means the dataset or the
    success distance changed since the list was written): ``ValueError`` naming the first bad episode.
    """
    n = len(episodes)
    scene_idx = np.zeros(n, dtype=np.int64)
    target = np.zeros(n, dtype=np.int64)
    start = np.zeros(n, dtype=np.int64)
    index = bank.class_set.index
    for i, e in enumerate(episodes):
        scene_idx[i] = bank.scene_index(e.scene)
        if e.target not in index:
            raise ValueError(
                f"episode {i}: target {e.target!r} is not a class of the scenes' class set {bank.class_set.name}"
            )
        target[i] = index[e.target]
        start[i] = bank.global_state(int(scene_idx[i]), e.start)
    if check and n:
        opt = bank.dist[start, target]
        stored = np.array([e.optimal_length for e in episodes])
        bad = np.flatnonzero(opt != stored)
        if len(bad):
            i = int(bad[0])
            e = episodes[i]
            got = "unreachable" if opt[i] == UNREACHABLE else int(opt[i])
            raise ValueError(
                f"episode {i} ({e.scene}, {e.target}, {e.start}): stored optimal length "
                f"{e.optimal_length} but the dataset gives {got}; regenerate the episode list"
            )
    return scene_idx, target, start


def class_set_meta(bank: SceneBank) -> dict:
    """The episode list's record of the bank's class set: ``{"class_set": name}``, or ``{}`` for ``ithor22`` (lists
    without the key read as ``ithor22``, so iTHOR lists are written as before)."""
    return {} if bank.class_set.name == DEFAULT_CLASS_SET else {"class_set": bank.class_set.name}


def write_episodes(path: str | Path, episodes: list[Episode], **meta) -> None:
    """Write an episode list as JSON, atomically; ``meta`` (split, seed, success_distance, ...) is stored."""
    path = Path(path)
    doc = {"format": EPISODES_FORMAT, "version": EPISODES_VERSION, **meta, "episodes": [e.to_json() for e in episodes]}
    atomic_write_text(path, json.dumps(doc, indent=1) + "\n")


def read_episodes(path: str | Path) -> tuple[list[Episode], dict]:
    """Read an episode list: ``(episodes, meta)``; ``ValueError`` naming the file when malformed."""
    path = Path(path)
    doc = read_json(path, ValueError)
    if not isinstance(doc, dict) or doc.get("format") != EPISODES_FORMAT:
        raise ValueError(f'{path}: not a tsnav episode list (missing "format": "{EPISODES_FORMAT}")')
    try:
        eps = [Episode(**e) for e in doc["episodes"]]
    except (KeyError, TypeError) as e:
        raise ValueError(f"{path}: malformed episode ({e})") from None
    meta = {k: v for k, v in doc.items() if k != "episodes"}
    return eps, meta
