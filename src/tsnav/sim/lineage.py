"""The lineage's episode lists and optimal actions from and to tsnav's simulator (docs/AI2THOR.md).

* :func:`episodes_from_splits`: the lineage's ``test_val_split/*.pkl`` (read safely by
  :mod:`tsnav.data.lineage_splits`) as tsnav episodes of a dataset, dropping and counting what it lacks;
* :func:`write_splits`: tsnav's fixed episodes (:func:`tsnav.sim.episodes.make_episodes`) of a dataset's test and
  val scenes as the lineage's lists;
* :func:`optimal_actions`: the lineage's ``optimal_action.json`` from the BFS distance fields, with a slow
  reference (:func:`optimal_actions_reference`).

Success radius: both the lists and the optimal actions are made for a ``success_distance``; 1.5 m is the
lineage's visibility-map rule (:data:`LINEAGE_SUCCESS_DISTANCE`), 1.0 m the paper's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..constants import ACTION_ORDER, DONE
from ..data import lineage_splits as LS
from ..data.lineage import SPLIT_DIR
from ..data.reader import list_scenes, load_scene
from ..protocol import spec
from .batch import SceneBank
from .episodes import Episode, make_episodes
from .paths import UNREACHABLE, bfs_reference, optimal_action_targets, scene_distance_fields

#: Success radius of the lineage's evaluator (its visibility map: in view within 1.5 m).
LINEAGE_SUCCESS_DISTANCE = 1.5


@dataclass
class SplitImport:
    """What :func:`episodes_from_splits` kept and dropped."""

    read: int = 0
    kept: int = 0
    dropped: dict = field(default_factory=dict)
    """reason -> count: ``scene not in DATA``, ``start not a state``, ``target not in scene``, ``target
    unreachable``, ``start already succeeds``."""

    start_success: int = 0
    """Kept episodes whose start already succeeds (``lineage`` protocol only)."""

    def drop(self, why: str) -> None:
        self.dropped[why] = self.dropped.get(why, 0) + 1

    def summary(self) -> str:
        """One line: read, kept, and the dropped counts by reason."""
        drops = ", ".join(f"{n} {why}" for why, n in sorted(self.dropped.items(), key=lambda kv: -kv[1]))
        return (
            f"{self.read} episodes read, {self.kept} kept"
            + (f" ({self.start_success} start already succeeds)" if self.start_success else "")
            + f", {self.read - self.kept} dropped"
            + (f" ({drops})" if drops else "")
        )


def episodes_from_splits(paths, data: str | Path, success_distance: float = 1.0, protocol: str = "paper"):
    """tsnav episodes (:class:`tsnav.sim.episodes.Episode`) of the lineage's split files ``paths`` for the
    scenes present in the dataset folder ``data``; returns ``(episodes, SplitImport)``.

    An episode is dropped (and counted by reason) when its scene is not in ``data``, its start is not a
    state of the scene, the scene has no success state of its target (no such object, or not a target
    category), the start cannot reach one, or - under the ``paper`` protocol only - the start already
    succeeds within ``success_distance`` (no path to measure). Under ``lineage`` such a start is kept with
    L* = 0, as the lineage's evaluator keeps it (:mod:`tsnav.protocol`); ``SplitImport.start_success``
    counts them. The optimal length is L* of the start state under the protocol.
    """
    records = []
    for p in paths:
        records += LS.read_split(p)
    stats = SplitImport(read=len(records))
    folders = {LS.scene_base_name(d.name): d for d in list_scenes(data)}
    wanted = sorted({LS.scene_base_name(r["scene"]) for r in records} & set(folders))
    if not wanted:
        for _ in records:
            stats.drop("scene not in DATA")
        return [], stats
    bank = SceneBank([load_scene(folders[n]) for n in wanted], success_distance=success_distance, protocol=protocol)
    keep_start_success = spec(protocol).keeps_start_success
    index = {LS.scene_base_name(n): i for i, n in enumerate(bank.names)}
    out = []
    for r in records:
        name = LS.scene_base_name(r["scene"])
        if name not in index:
            stats.drop("scene not in DATA")
            continue
        i = index[name]
        try:
            s = bank.global_state(i, r["state"])
        except (KeyError, ValueError, IndexError):
            stats.drop("start not a state")
            continue
        c = bank.class_set.index.get(r["goal_object_type"])
        if c is None or not bank.present[i, c] or not bank.success[bank.scene_of == i, c].any():
            stats.drop("target not in scene")
            continue
        d = int(bank.dist[s, c])
        if d == UNREACHABLE:
            stats.drop("target unreachable")
            continue
        if d == 0:
            if not keep_start_success:
                stats.drop("start already succeeds")
                continue
            stats.start_success += 1
        out.append(
            Episode(
                scene=bank.names[i],
                target=bank.class_set.categories[c],
                start=r["state"],
                optimal_length=d,
                room_type=bank.room_types[i],
            )
        )
    stats.kept = len(out)
    return out, stats


def optimal_actions(scene, success_distance: float = LINEAGE_SUCCESS_DISTANCE) -> dict[str, dict[str, int]]:
    """``{state key: {target type: action id}}`` of ``optimal_action.json`` for every target category with a
    success state in ``scene``: :func:`tsnav.sim.paths.optimal_action_targets` on the BFS distance fields
    (the lowest action id among those one step closer; Done where the state succeeds). States that cannot
    reach a target's success states have no entry for it. Action ids in ``constants.ACTIONS`` order, which
    is the lineage's."""
    dist = scene_distance_fields(scene, success_distance)
    S = scene.num_states
    out: dict[str, dict[str, int]] = {str(k): {} for k in scene.keys}
    for c in np.flatnonzero((dist == 0).any(axis=0)):
        states = np.flatnonzero(dist[:, c] < UNREACHABLE)
        act = optimal_action_targets(scene.next_state, dist, states, np.full(len(states), c), done_action=DONE)
        name = scene.class_set.categories[int(c)]
        for s, a in zip(states.tolist(), act.tolist()):
            out[str(scene.keys[s])][name] = int(a)
    assert len(out) == S
    return out


def optimal_actions_reference(scene, success_distance: float = LINEAGE_SUCCESS_DISTANCE) -> dict[str, dict[str, int]]:
    """Slow reference for :func:`optimal_actions`: per state and category, a Python loop over the actions
    comparing the successors' BFS distances (:func:`tsnav.sim.paths.bfs_reference`)."""
    success = scene.category_visible_within(success_distance)
    out: dict[str, dict[str, int]] = {str(k): {} for k in scene.keys}
    for c in range(scene.num_categories):
        if not success[:, c].any():
            continue
        d = bfs_reference(scene.next_state, success[:, c])
        for s in range(scene.num_states):
            if d[s] == UNREACHABLE:
                continue
            if d[s] == 0:
                a = DONE
            else:
                a = next(a for a in range(DONE) if d[scene.next_state[s, a]] == d[s] - 1)
            out[str(scene.keys[s])][scene.class_set.categories[c]] = a
    return out


def write_splits(
    root: str | Path, success_distance: float = LINEAGE_SUCCESS_DISTANCE, per_room_type: int = 1000, seed: int = 0
) -> dict[str, int]:
    """Write ``root/test_val_split/{room}_{split}_22.pkl`` for the test and val scenes of ``root`` and the info
    file naming ``success_distance``; returns file name -> episodes. Room types without a valid episode in
    a split get no file."""
    folder = Path(root) / SPLIT_DIR
    written: dict[str, int] = {}
    for split in LS.SPLIT_NAMES:
        dirs = list_scenes(root, split=split)
        if not dirs:
            continue
        bank = SceneBank([load_scene(d) for d in dirs], success_distance=success_distance)
        eps = make_episodes(bank, per_room_type, seed)
        for room in LS.SPLIT_ROOMS:
            mine = [e for e in eps if e.room_type == room]
            if not mine:
                continue
            name = LS.split_file_name(room, split)
            LS.write_split(folder / name, LS.split_records(bank, mine))
            written[name] = len(mine)
    if written:
        rule = (
            "the lineage's: the target in its visibility map (in view within 1.5 m)"
            if success_distance == 1.5
            else f"in view and within {success_distance} m of the agent on the floor plane (the paper's rule at 1.0 m)"
        )
        LS.write_split_info(
            folder,
            {
                "format": "tsnav-lineage-splits",
                "success_distance": success_distance,
                "success_rule": rule,
                "per_room_type": per_room_type,
                "seed": seed,
                "action_order": ACTION_ORDER,
                "start_horizons": "0 or 30, each with probability 1/2 per (scene, target) pair",
                "files": written,
                "note": "optimal_action.json in every scene folder was made for the same success distance",
            },
        )
    return written
