"""Where an evaluated agent's steps go after the stage switch: every action from the switch frame on, classed by
what it did to ``d``, the pose-graph distance to the target that the paper's distance reward is made of (the
MoveAhead / RotateLeft / RotateRight actions to the nearest pose where Done succeeds under the evaluation's protocol,
:mod:`tsnav.tsrm.distance`).

    tsnav analyze pathfinding-steps [LABEL=]EVAL_FOLDER [...] [--data WORLD] [--json OUT.json]

A pose action either brings the agent one action closer (``closer``), leaves ``d`` as it was (``no progress``: a
step sideways; ``blocked``: a MoveAhead that left the agent where it was) or takes it farther (``farther``: a step
away, a turn the long way).
LookUp and LookDown never change ``d`` (``look``). ``wasted`` counts what each pose action cost beyond the shortest
walk, ``1 - (d_before - d_after)``: nothing for a ``closer`` action (``d`` falls by exactly one along any edge of
the graph), one for ``no progress``, and for ``farther`` one plus the rise of ``d`` (a step into a corridor may
rise it by several: the way back needs the turns round), so that over an episode the pose actions less ``wasted``
are the drop of ``d`` from the switch to the end.
Each action is also marked by whether some instance of the target showed in the frame it was taken from (at any
range, the world's pixel rule: ground truth, read for this analysis only), which tells a walk that loses the
target from one that wanders with it in view. Done actions are left out, and so are steps where either end has no
path to the target.

EVAL_FOLDER is a ``tsnav eval`` output (trajectories.jsonl, metrics.json); the world is the one its metrics.json
names unless ``--data`` gives another. The distances come from :func:`~tsnav.tsrm.distance.pose_distance_fields`;
:func:`step_classes_reference` is the slow reference (a dictionary BFS per target and a loop over the actions) the
tests hold it to.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_json
from ..constants import ACTIONS, DONE, LOOK_DOWN, LOOK_UP, MOVE_AHEAD
from ..data.reader import load_scene
from ..eval.runner import read_trajectories
from ..protocol import protocol_of
from ..sim.paths import UNREACHABLE
from ..tsrm.distance import pose_distance_fields, pose_distance_reference

#: How a step changed d (``blocked``: a MoveAhead that left the agent where it was); ``look`` for LookUp / LookDown.
CLASSES = ("closer", "no progress", "blocked", "farther", "look")
#: Rows of the table: the pose actions, then the two look actions together.
ROWS = ("MoveAhead", "RotateLeft", "RotateRight", "LookUp/LookDown")


def scene_tables(scene, protocol: str, success_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """``(d, in_view)`` of a loaded scene: ``(S, C)`` pose-graph distance to a success pose under ``protocol``, and
    ``(S, C)`` bool, some instance of the class shows in the frame at any range."""
    success = scene.success_table(protocol, success_distance)
    d = pose_distance_fields(scene.next_state, scene.x, scene.z, scene.rotation, scene.horizon, success)
    return d, scene.category_in_frame()


def classify(d_before: np.ndarray, d_after: np.ndarray, actions: np.ndarray, moved: np.ndarray) -> np.ndarray:
    """Per step, the index into :data:`CLASSES` (-1: Done, or an end without a path); ``moved``: the step changed
    the agent's state."""
    d0, d1 = d_before.astype(np.int64), d_after.astype(np.int64)
    out = np.where(d1 < d0, 0, np.where(d1 == d0, 1, 3))
    out = np.where((actions == MOVE_AHEAD) & ~moved, 2, out)
    out = np.where((actions == LOOK_UP) | (actions == LOOK_DOWN), 4, out)
    bad = (actions == DONE) | (d0 == UNREACHABLE) | (d1 == UNREACHABLE)
    return np.where(bad, -1, out)


def row_of(action: int) -> str:
    return "LookUp/LookDown" if action in (LOOK_UP, LOOK_DOWN) else ACTIONS[action]


def _empty() -> dict:
    return {
        v: {r: dict.fromkeys(CLASSES[:4] if r != ROWS[3] else CLASSES[4:], 0) for r in ROWS}
        for v in ("in view", "out of view")
    }


def _result(episodes: int, counts: dict, wasted: dict, wasted_fail: int, skipped: int) -> dict:
    """The counts of :func:`step_classes` and its reference, as both return them."""
    return {
        "episodes": episodes,
        "counts": counts,
        "wasted": wasted,
        "wasted_failures": wasted_fail,
        "skipped": skipped,
    }


def step_classes(data: Path, trajectories, protocol: str, success_distance: float = 1.0) -> dict:
    """Counts of the switched episodes' steps (module docstring): ``{"in view" | "out of view": {row: {class: n}}}``
    plus ``episodes`` (switched), ``wasted`` (in view / out of view), ``wasted_failures`` (in failed episodes),
    ``skipped`` (steps without a path at either end)."""
    counts, wasted, wasted_fail = _empty(), {"in view": 0, "out of view": 0}, 0
    episodes, skipped = 0, 0
    by_scene = defaultdict(list)
    for t in trajectories:
        if t.switch_frame is not None and t.switch_frame >= 0:
            by_scene[t.scene].append(t)
    for name in sorted(by_scene):
        scene = load_scene(Path(data) / name)
        d, view = scene_tables(scene, protocol, success_distance)
        for t in by_scene[name]:
            episodes += 1
            c = scene.class_set.index[t.target]
            ids = scene.indices(t.keys)
            k = t.switch_frame
            acts = np.asarray(t.actions[k:], np.int64)
            if not len(acts):
                continue
            before, after = ids[k : k + len(acts)], ids[k + 1 : k + 1 + len(acts)]
            cls = classify(d[before, c], d[after, c], acts, before != after)
            seen = view[before, c]
            skipped += int(((cls < 0) & (acts != DONE)).sum())
            cost = 1 - (d[before, c].astype(np.int64) - d[after, c].astype(np.int64))
            for a, cl, v, w in zip(acts.tolist(), cls.tolist(), seen.tolist(), cost.tolist()):
                if cl < 0:
                    continue
                key = "in view" if v else "out of view"
                counts[key][row_of(a)][CLASSES[cl]] += 1
                w = 0 if cl == 4 else w
                wasted[key] += w
                if not t.success:
                    wasted_fail += w
    return _result(episodes, counts, wasted, wasted_fail, skipped)


def step_classes_reference(data: Path, trajectories, protocol: str, success_distance: float = 1.0) -> dict:
    """Slow reference of :func:`step_classes`: per target, the pose distance by
    :func:`~tsnav.tsrm.distance.pose_distance_reference` (dictionaries and a BFS), and one action at a time."""
    counts, wasted, wasted_fail = _empty(), {"in view": 0, "out of view": 0}, 0
    episodes, skipped = 0, 0
    scenes: dict = {}
    for t in trajectories:
        if t.switch_frame is None or t.switch_frame < 0:
            continue
        episodes += 1
        if t.scene not in scenes:
            scenes[t.scene] = (load_scene(Path(data) / t.scene), {})
        scene, cols = scenes[t.scene]
        c = scene.class_set.index[t.target]
        if c not in cols:
            ok = scene.success_table(protocol, success_distance)[:, c]
            cols[c] = pose_distance_reference(scene.next_state, scene.x, scene.z, scene.rotation, ok)
        d = cols[c]
        px = scene.visible_at_any_range()
        for i in range(t.switch_frame, len(t.actions)):
            a = t.actions[i]
            if a == DONE:
                continue
            s0, s1 = scene.index(t.keys[i]), scene.index(t.keys[i + 1])
            if d[s0] == UNREACHABLE or d[s1] == UNREACHABLE:
                skipped += 1
                continue
            seen = any(px[s0, o] for o in range(len(scene.object_ids)) if scene.object_category[o] == c)
            key = "in view" if seen else "out of view"
            if a in (LOOK_UP, LOOK_DOWN):
                cl = "look"
            elif a == MOVE_AHEAD and s0 == s1:
                cl = "blocked"
            elif d[s1] < d[s0]:
                cl = "closer"
            elif d[s1] == d[s0]:
                cl = "no progress"
            else:
                cl = "farther"
            counts[key][row_of(a)][cl] += 1
            w = 0 if cl == "look" else 1 - (int(d[s0]) - int(d[s1]))
            wasted[key] += w
            if not t.success:
                wasted_fail += w
    return _result(episodes, counts, wasted, wasted_fail, skipped)


def read_eval(folder: Path) -> tuple[list, dict]:
    """The trajectories and metrics.json of a ``tsnav eval`` folder; ``ValueError`` naming what is missing."""
    for f in ("trajectories.jsonl", "metrics.json"):
        if not (folder / f).is_file():
            raise ValueError(f"{folder}: no {f} (not a `tsnav eval` output folder)")
    traj = read_trajectories(folder / "trajectories.jsonl")
    if any(t.switch_frame is None for t in traj):
        raise ValueError(f"{folder}: trajectories without switch_frame (evaluated by an older tsnav)")
    return traj, json.loads((folder / "metrics.json").read_text())


def format_result(label: str, res: dict) -> str:
    """The counts as text: per row and view, the share of each class, then the wasted actions."""
    lines = [f"{label}: {res['episodes']} switched episodes, after the switch (protocol {res['protocol']})"]
    lines.append(f"  {'action':16s} {'target':12s} {'steps':>7s}  closer  no progress  blocked  farther")
    for r in ROWS[:3]:
        for v in ("in view", "out of view"):
            row = res["counts"][v][r]
            n = sum(row.values())
            pct = [f"{100 * row[k] / n:5.1f} %" if n else "-" for k in CLASSES[:4]]
            lines.append(f"  {r:16s} {v:12s} {n:7d}  {pct[0]:>6s}  {pct[1]:>11s}  {pct[2]:>7s}  {pct[3]:>7s}")
    look = sum(res["counts"][v][ROWS[3]]["look"] for v in ("in view", "out of view"))
    pose = sum(sum(res["counts"][v][r].values()) for v in ("in view", "out of view") for r in ROWS[:3])
    w = res["wasted"]
    tot = w["in view"] + w["out of view"]
    lines.append(
        f"  pose actions {pose}, wasted {tot} ({100 * tot / pose if pose else 0:.1f} %): with the target in view "
        f"{w['in view']}, out of view {w['out of view']}; in failed episodes {res['wasted_failures']}; "
        f"LookUp/LookDown {look}"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze pathfinding-steps", description=__doc__.splitlines()[0]
    )
    ap.add_argument("evals", nargs="+", metavar="[LABEL=]EVAL_FOLDER")
    ap.add_argument("--data", type=Path, default=None, help="the world (default: the one metrics.json names)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    out = []
    for arg in a.evals:
        label, _, path = arg.rpartition("=")
        folder = Path(path)
        try:
            traj, meta = read_eval(folder)
            data = a.data or Path(meta.get("data", ""))
            if not str(data) or not data.is_dir():
                raise ValueError(f"{folder}: its world {data} is not a folder (give --data)")
            protocol = protocol_of(meta)
            res = step_classes(data, traj, protocol, float(meta.get("success_distance", 1.0)))
        except (ValueError, KeyError, FileNotFoundError) as e:
            print(f"tsnav analyze pathfinding-steps: {e}", file=sys.stderr)
            return 2
        res.update({"eval": str(folder), "label": label or folder.name, "protocol": protocol})
        out.append(res)
        print(format_result(res["label"], res))
    if a.json:
        atomic_write_json(a.json, {"format": "tsnav-pathfinding-steps", "results": out}, sort_keys=False)
        print(f"wrote {a.json}")
    return 0
