"""The RoboTHOR ObjectNav challenge's episodes as tsnav episode lists (``tsnav thor challenge-episodes``).

The challenge (allenai/robothor-challenge, 2021; ``../shared/robothor/README.md``) ships, per scene, a gzipped JSON
list of episodes: ``id``, ``scene``, ``object_type`` (one of 12 types, the ``robothor12`` class set),
``initial_position`` {x, y, z} on the 0.25 m grid, ``initial_orientation`` (degrees, multiples of 30),
``initial_horizon`` (30), ``shortest_path`` (navmesh corners) and ``shortest_path_length`` (metres on the
navmesh). Its agent turns in 30-degree steps; tsnav's graph (the lineage's) has 8 headings 45 degrees apart. A
start becomes a tsnav start state by these rules:

* position: the challenge's (x, z), snapped to the 0.25 m grid (a start more than 1 cm off it is dropped as
  ``start off the 0.25 m grid``; the records have none);
* heading: the nearest of tsnav's 8 headings, ``45 * floor(o / 45 + 1/2) mod 360`` for the challenge's
  orientation ``o``. A multiple of 30 is never halfway between two multiples of 45 (it is 0 or 15 degrees from
  the nearest), so no tie arises on the records: 0, 90, 180, 270 stay; 30, 60 -> 45; 120, 150 -> 135;
  210, 240 -> 225; 300, 330 -> 315. The episode keeps the original as ``challenge.initial_orientation``;
* horizon: the challenge's (30) as it is (tsnav's horizons are 0 and 30).

An episode is dropped, counted by reason and per scene (:class:`ChallengeImport`), when its scene is not in the
dataset, its target type is not a class of the scenes' class set, its start is not a state of the built graph
(``start not a state``: the position is not reachable in tsnav's grid), the scene has no instance of the target
(``target not in scene``) or no state where Done would succeed for it (``target has no success state``: no
instance is ever in view within the protocol's radius), the start cannot reach a success state, or - under the ``paper`` protocol only - the start already succeeds.
Under ``lineage`` such a start is kept with L* = 0 (:mod:`tsnav.protocol`), as :mod:`tsnav.sim.lineage` keeps the
lineage's.

Each kept episode carries tsnav's optimal length twice: ``optimal_length``, L* in actions (:mod:`tsnav.sim.paths`,
the metrics' length), and ``optimal_metres``, the shortest walk in metres along the grid's MoveAhead edges (0.25 m
straight, 0.25 * sqrt(2) m diagonal) from the start position to a position holding a success state of the
target, turns free (:func:`grid_metres`), the quantity the navmesh's ``shortest_path_length`` measures; beside
them the challenge's ``shortest_path_length`` (``challenge.shortest_path_length``), its ``id`` and start.
"""

from __future__ import annotations

import gzip
import heapq
import json
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from ..constants import GRID_SIZE, HORIZONS, MOVE_AHEAD, ROTATE_STEP, state_key
from ..protocol import spec
from .batch import SceneBank
from .episodes import Episode
from .paths import UNREACHABLE

#: Where the challenge's episodes say they come from (recorded in every converted list).
CHALLENGE_SOURCE = "allenai/robothor-challenge @ f3c4f35bc397aff4d5236e269efe3ff41f6d218e, dataset/{split}/episodes/"
#: The rule that maps the challenge's heading to tsnav's, in one line (recorded in every converted list).
HEADING_RULE = (
    "tsnav rotation = 45 * floor(o / 45 + 1/2) mod 360 of the challenge's orientation o (the nearest "
    "of the 8 headings; multiples of 30 never tie); the original is kept as "
    "challenge.initial_orientation"
)
#: A start farther than this from the 0.25 m grid (metres, in x or z) is dropped.
GRID_TOLERANCE = 0.01
_FIELDS = (
    "id",
    "scene",
    "object_type",
    "initial_position",
    "initial_orientation",
    "initial_horizon",
    "shortest_path_length",
)


def challenge_heading(orientation: float) -> int:
    """tsnav's heading (one of :data:`~tsnav.constants.ROTATIONS`) for the challenge's ``orientation`` in
    degrees: the nearest multiple of 45, halfway cases up (clockwise)."""
    return int(math.floor(float(orientation) / ROTATE_STEP + 0.5)) * ROTATE_STEP % 360


def read_challenge_episodes(root: str | Path, split: str) -> list[dict]:
    """Every episode of ``root/split/*.json.gz`` (files in name order, episodes in file order); ``ValueError``
    naming the file when the folder holds none or an episode lacks a field of :data:`_FIELDS`."""
    folder = Path(root) / split
    files = sorted(folder.glob("*.json.gz"))
    if not files:
        raise ValueError(
            f"{folder}: no challenge episode files (*.json.gz); pass the folder that holds "
            f"train/ and val/ (e.g. ../shared/robothor/challenge_episodes)"
        )
    out = []
    for f in files:
        try:
            with gzip.open(f, "rt") as fh:
                eps = json.load(fh)
        except (OSError, EOFError, json.JSONDecodeError) as e:
            raise ValueError(f"{f}: unreadable challenge episode file ({e})") from None
        if not isinstance(eps, list):
            raise ValueError(f"{f}: not a list of challenge episodes")
        for i, e in enumerate(eps):
            missing = [k for k in _FIELDS if not isinstance(e, dict) or k not in e]
            if missing:
                raise ValueError(f"{f}: episode {i} has no {missing[0]!r}")
        out += eps
    return out


@dataclass
class ChallengeImport:
    """What :func:`challenge_episodes` kept and dropped, overall and per scene."""

    read: int = 0
    kept: int = 0
    dropped: dict = field(default_factory=dict)
    """reason -> count: ``scene not in DATA``, ``target not a class of <set>``, ``start off the 0.25 m grid``,
    ``horizon not 0 or 30``, ``start not a state``, ``target not in scene``, ``target has no success state``,
    ``target unreachable``, ``start already succeeds`` (``paper`` only)."""
    per_scene: dict = field(default_factory=dict)
    """scene -> {"read", "kept", "start not a state", ...}: the same counts per scene."""
    start_success: int = 0
    """Kept episodes whose start already succeeds (``lineage`` only)."""

    def _scene(self, scene: str) -> Counter:
        return self.per_scene.setdefault(scene, Counter())

    def count(self, scene: str, what: str) -> None:
        self._scene(scene)[what] += 1

    def drop(self, scene: str, why: str) -> None:
        self.dropped[why] = self.dropped.get(why, 0) + 1
        self.count(scene, why)

    @property
    def starts_on_graph(self) -> tuple[int, int]:
        """``(starts that are states, starts looked up)`` over the scenes of the dataset (episodes of a missing
        scene or of an unknown type are not looked up)."""
        off = self.dropped.get("start not a state", 0) + self.dropped.get("start off the 0.25 m grid", 0)
        looked = sum(c["looked up"] for c in self.per_scene.values())
        return looked - off, looked

    def summary(self) -> str:
        """One line: read, kept, dropped by reason, and the share of starts that are states."""
        drops = ", ".join(f"{n} {why}" for why, n in sorted(self.dropped.items(), key=lambda kv: -kv[1]))
        on, looked = self.starts_on_graph
        return (
            f"{self.read} episodes read, {self.kept} kept"
            + (f" ({self.start_success} start already succeeds)" if self.start_success else "")
            + f", {self.read - self.kept} dropped"
            + (f" ({drops})" if drops else "")
            + (f"; {on} / {looked} starts are states ({100 * on / looked:.1f} %)" if looked else "")
        )

    def to_json(self) -> dict:
        return {
            "read": self.read,
            "kept": self.kept,
            "start_success": self.start_success,
            "dropped": dict(sorted(self.dropped.items())),
            "per_scene": {s: dict(sorted(c.items())) for s, c in sorted(self.per_scene.items())},
        }


def position_graph(bank: SceneBank) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """``(src, dst, metres, positions)``: the directed MoveAhead edges between the bank's positions
    (``bank.position`` ids; one edge per distinct pair) with their lengths in metres, and the number of positions."""
    s = np.flatnonzero(bank.next_state[:, MOVE_AHEAD] != np.arange(bank.num_states))
    t = bank.next_state[s, MOVE_AHEAD].astype(np.int64)
    pairs = np.unique(np.stack([bank.position[s], bank.position[t]], axis=1), axis=0)
    px = np.zeros(int(bank.position.max()) + 1, np.float64)
    pz = np.zeros_like(px)
    px[bank.position], pz[bank.position] = bank.x, bank.z
    metres = np.hypot(px[pairs[:, 1]] - px[pairs[:, 0]], pz[pairs[:, 1]] - pz[pairs[:, 0]])
    return pairs[:, 0], pairs[:, 1], metres, len(px)


def grid_metres(bank: SceneBank, target: int) -> np.ndarray:
    """``(S,)`` float64: metres of the shortest walk along the grid's MoveAhead edges from each state's position
    to a position that holds a success state of category ``target`` (turns and looks free; ``inf`` when none can
    be reached). One multi-source Dijkstra on the reversed position graph (scipy); slow reference:
    :func:`grid_metres_reference`."""
    src, dst, metres, n = position_graph(bank)
    goal = np.unique(bank.position[bank.success[:, target]])
    if len(goal) == 0:
        return np.full(bank.num_states, np.inf)
    rev = coo_matrix((metres, (dst, src)), shape=(n, n)).tocsr()
    d = dijkstra(rev, directed=True, indices=goal, min_only=True)
    return d[bank.position]


def grid_metres_reference(bank: SceneBank, start: int, target: int) -> float:
    """Slow reference for :func:`grid_metres` of one start state: Dijkstra with a heap over the states (turns and
    looks cost 0, a MoveAhead its length in metres) until a success state of ``target`` is popped."""
    best = {start: 0.0}
    heap = [(0.0, start)]
    while heap:
        d, s = heapq.heappop(heap)
        if d > best[s]:
            continue
        if bank.success[s, target]:
            return d
        for a in range(5):  # the movement actions: MoveAhead, the turns and the looks
            t = int(bank.next_state[s, a])
            step = math.hypot(bank.x[t] - bank.x[s], bank.z[t] - bank.z[s]) if a == MOVE_AHEAD else 0.0
            if t != s and d + step < best.get(t, math.inf):
                best[t] = d + step
                heapq.heappush(heap, (d + step, t))
    return math.inf


def _snap(v: float) -> float | None:
    g = round(float(v) / GRID_SIZE) * GRID_SIZE
    return round(g, 2) + 0.0 if abs(g - float(v)) <= GRID_TOLERANCE else None


def challenge_episodes(records: list[dict], bank: SceneBank) -> tuple[list[Episode], ChallengeImport]:
    """tsnav episodes of the challenge's ``records`` (:func:`read_challenge_episodes`) over ``bank``, under the
    bank's success protocol, and what was kept and dropped (module docstring: the rules). Episodes keep the
    records' order; each has ``optimal_length`` (actions), ``optimal_metres`` and ``challenge`` (``id``,
    ``initial_position``, ``initial_orientation``, ``initial_horizon``, ``shortest_path_length``)."""
    stats = ChallengeImport(read=len(records))
    keep_start_success = spec(bank.protocol).keeps_start_success
    index = {n: i for i, n in enumerate(bank.names)}
    classes = bank.class_set
    found: list[tuple[dict, int, int, int]] = []  # (record, scene, category, global start)
    for r in records:
        scene = str(r["scene"])
        stats.count(scene, "read")
        if scene not in index:
            stats.drop(scene, "scene not in DATA")
            continue
        i = index[scene]
        c = classes.index.get(str(r["object_type"]))
        if c is None:
            stats.drop(scene, f"target not a class of {classes.name}")
            continue
        stats.count(scene, "looked up")
        p = r["initial_position"]
        x, z = _snap(p["x"]), _snap(p["z"])
        if x is None or z is None:
            stats.drop(scene, "start off the 0.25 m grid")
            continue
        h = int(round(float(r["initial_horizon"])))
        if h not in HORIZONS:
            stats.drop(scene, "horizon not 0 or 30")
            continue
        key = state_key(x, z, challenge_heading(r["initial_orientation"]), h)
        try:
            s = bank.global_state(i, key)
        except KeyError:
            stats.drop(scene, "start not a state")
            continue
        if not bank.present[i, c]:
            stats.drop(scene, "target not in scene")
            continue
        if not bank.success[bank.offsets[i] : bank.offsets[i + 1], c].any():
            stats.drop(scene, "target has no success state")
            continue
        d = int(bank.dist[s, c])
        if d == UNREACHABLE:
            stats.drop(scene, "target unreachable")
            continue
        if d == 0 and not keep_start_success:
            stats.drop(scene, "start already succeeds")
            continue
        stats.start_success += d == 0
        found.append((r, i, c, s))
    metres = {c: grid_metres(bank, c) for c in sorted({c for _, _, c, _ in found})}
    out = []
    for r, i, c, s in found:
        p = r["initial_position"]
        out.append(
            Episode(
                scene=bank.names[i],
                target=classes.categories[c],
                start=str(bank.keys[s]),
                optimal_length=int(bank.dist[s, c]),
                room_type=bank.room_types[i],
                optimal_metres=round(float(metres[c][s]), 4),
                challenge={
                    "id": str(r["id"]),
                    "initial_position": {k: float(p[k]) for k in ("x", "y", "z")},
                    "initial_orientation": float(r["initial_orientation"]),
                    "initial_horizon": float(r["initial_horizon"]),
                    "shortest_path_length": float(r["shortest_path_length"]),
                },
            )
        )
        stats.count(bank.names[i], "kept")
    stats.kept = len(out)
    return out, stats


def length_ratios(episodes: list[Episode]) -> np.ndarray:
    """``optimal_metres / shortest_path_length`` of the episodes whose navmesh length is positive."""
    r = [
        e.optimal_metres / e.challenge["shortest_path_length"]
        for e in episodes
        if e.challenge and e.optimal_metres is not None and e.challenge["shortest_path_length"] > 0
    ]
    return np.asarray(r, dtype=np.float64)


def ratio_summary(episodes: list[Episode]) -> dict:
    """Figures of tsnav's grid metres against the navmesh length: count, median, quartiles, share within
    +-25 % (the issue's goal reads median 0.95-1.10 and >= 90 % within +-25 %); and the mean L* in actions."""
    r = length_ratios(episodes)
    if not len(r):
        return {"episodes": 0}
    q1, med, q3 = np.percentile(r, [25, 50, 75])
    return {
        "episodes": int(len(r)),
        "median": float(med),
        "q1": float(q1),
        "q3": float(q3),
        "within_25pct": float(np.mean(np.abs(r - 1.0) <= 0.25)),
        "mean_optimal_actions": float(np.mean([e.optimal_length for e in episodes])),
        "mean_optimal_metres": float(np.mean([e.optimal_metres for e in episodes])),
        "mean_navmesh_metres": float(np.mean([e.challenge["shortest_path_length"] for e in episodes])),
    }


def packaged_challenge() -> Path:
    """The challenge's episode folder packaged with tsnav (``tsnav/world/data/robothor/challenge_episodes``, the
    layout :func:`read_challenge_episodes` reads): its ``val/`` split only, the 1,800 episodes of the 15 val scenes
    (the 108,000 train episodes are not packaged: ``../shared/robothor/challenge_episodes`` holds them)."""
    from importlib import resources

    return Path(str(resources.files("tsnav.world") / "data" / "robothor" / "challenge_episodes"))


def take_sample(episodes: list[Episode], per_room_type: int | None, seed: int) -> tuple[list[Episode], dict]:
    """``episodes`` and the list metadata that records it: a :func:`sample_per_room_type` of them with its
    ``{"sample": ...}`` record, or all of them and ``{}`` when ``per_room_type`` is None."""
    if per_room_type is None:
        return episodes, {}
    kept = sample_per_room_type(episodes, per_room_type, seed)
    return kept, {"sample": {"per_room_type": per_room_type, "seed": seed, "of": len(episodes)}}


def sample_per_room_type(episodes: list[Episode], per_room_type: int, seed: int) -> list[Episode]:
    """A fixed sample of ``episodes``: at most ``per_room_type`` of each room type (RoboTHOR's apartments are one
    room type, so that is the sample's size), drawn without replacement by ``numpy.random.default_rng(seed)``
    over the room types in name order, kept in the list's order."""
    rng = np.random.default_rng(seed)
    keep: list[int] = []
    for t in sorted({e.room_type for e in episodes}):
        idx = [i for i, e in enumerate(episodes) if e.room_type == t]
        keep += [idx[j] for j in rng.choice(len(idx), size=min(per_room_type, len(idx)), replace=False)]
    return [episodes[i] for i in sorted(keep)]
