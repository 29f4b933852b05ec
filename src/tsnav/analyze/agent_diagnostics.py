"""Five diagnostics behind docs/RESULTS.md's agent sections (analysis only: nothing here reaches an agent).

``rotations EVAL_DIR ...``: how an evaluated agent turns. Per ``tsnav eval`` folder (its ``trajectories.jsonl``):
the share of each rotation among all actions, and the runs of one rotation repeated 5-7 times in a row. With
45-degree turns, k turns one way reach what 8 - k turns the other way reach, so such a run of length L could have
been 8 - L turns the other way: "steps in them" is the share of all steps inside such runs, and "saved steps" the
sum of 2 L - 8 over them, what turning the other way would have saved; and the folder's SPL with every successful
episode's path shortened by its saved steps (nothing else changed: a lower bound of what two-way turning buys).

``reach --data WORLD --episodes LIST --detections NAME ...``: the share of an episode list whose target's score
in the named detection table passes C_target (0.7) at some state of the episode's room, the ceiling of the stage
switch for any searcher with that table.

``outcomes EVAL_DIR ...``: how episodes end, from the trajectories alone. Per ``tsnav eval`` folder: episodes
that switched to pathfinding or not, each ending in a success, a failed Done or the step limit; the share of
MoveAheads that left the agent in the same state (blocked); the episodes with at least 10 blocked MoveAheads; and
the step-limit failures that end in a loop (at most 10 distinct states in their last 40 frames). With ``--data``,
the switched episodes are also split by whether some instance of the target was in the frame (at any range) at the
state where the switch fired: a true switch, or one made by a false positive (ground truth read for this analysis
only).

``switches EVAL_A EVAL_B``: where the stage switch fires in one evaluation and not in the other, by target: two
``tsnav eval`` folders of the same episode list (e.g. the scripted explorer on the learned table and on the
oracle's), per target the episodes, those whose switch never fired in each, and those that fired only in B (what
A's table misses where B's finds the target).

``switch-distance EVAL_DIR ...``: how far from its target the pathfinding stage begins, and what that costs. Per
``tsnav eval`` folder (its ``records.jsonl``): the episodes whose switch fired, grouped by the shortest path left
at the switch (L*Nav, in movement actions; bands of ``--band`` actions, the last open-ended from ``--last``), each
band's episodes, successes and success share, and the median ratio LNav / L*Nav of its successes (how much longer
the walk after the switch was than the shortest; bands whose successes all began at the goal show none). An
argument ``LABEL=EVAL_DIR`` names the folder in the output; ``--json OUT`` also writes the rows (atomically);
``--false-switches`` also counts, per band, the switches made where the target was not in the frame and their
successes (ground truth of the world each folder's ``metrics.json`` names, read for analysis only).

    tsnav analyze agent-diagnostics rotations EVAL_A EVAL_B
    tsnav analyze agent-diagnostics reach --data WORLD --episodes TEST.json --detections learned4 oracle
    tsnav analyze agent-diagnostics outcomes EVAL_A EVAL_B [--data WORLD]
    tsnav analyze agent-diagnostics switches EVAL_A EVAL_B
    tsnav analyze agent-diagnostics switch-distance [LABEL=]EVAL_A [LABEL=]EVAL_B [--band 5] [--last 30] [--json OUT]
        [--false-switches]
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

from ..constants import ACTIONS, C_TARGET, DONE, MOVE_AHEAD
from ..constants import class_set as get_class_set
from ..data.detections import load_detections
from ..data.reader import load_scene
from ..eval.runner import read_trajectories
from ..metrics import read_records, write_json
from ..sim.episodes import read_episodes

LEFT, RIGHT = ACTIONS.index("RotateLeft"), ACTIONS.index("RotateRight")
TURNS = 8  # 360 / 45-degree rotations
LOOP_FRAMES, LOOP_STATES, MANY_BLOCKED = 40, 10, 10


def rotation_figures(actions_per_episode) -> dict:
    """Rotation shares and the steps that turning the other way would save (module docstring)."""
    steps = left = right = saved = long_runs = in_runs = 0
    for actions in actions_per_episode:
        steps += len(actions)
        left += sum(a == LEFT for a in actions)
        right += sum(a == RIGHT for a in actions)
        for a, run in itertools.groupby(actions):
            n = len(list(run))
            if a in (LEFT, RIGHT) and TURNS // 2 < n < TURNS:
                long_runs += 1
                in_runs += n
        saved += saved_turns(actions)
    return {
        "steps": steps,
        "RotateLeft": left / steps if steps else 0.0,
        "RotateRight": right / steps if steps else 0.0,
        "runs_5_to_7": long_runs,
        "in_runs_share": in_runs / steps if steps else 0.0,
        "saved_steps": saved,
        "saved_share": saved / steps if steps else 0.0,
    }


def saved_turns(actions) -> int:
    """The steps turning the other way would save in one episode: ``2 L - 8`` over its runs of ``L`` = 5-7 turns one
    way (:func:`rotation_figures`)."""
    saved = 0
    for a, run in itertools.groupby(actions):
        n = len(list(run))
        if a in (LEFT, RIGHT) and TURNS // 2 < n < TURNS:
            saved += 2 * n - TURNS
    return saved


def short_turn_spl(folder: Path) -> tuple[float, float]:
    """``(SPL, SPL with the long turns taken the short way)`` of a ``tsnav eval`` folder, in percent, under its
    protocol: each successful episode's path shortened by :func:`saved_turns`, nothing else changed (the failures
    keep failing, although the steps saved might have let some of them succeed)."""
    from dataclasses import replace

    from ..metrics import summarize
    from ..protocol import protocol_of

    protocol = protocol_of(json.loads((folder / "metrics.json").read_text()))
    records = read_records(folder / "records.jsonl")
    actions = read_actions(folder)
    if len(records) != len(actions):
        raise SystemExit(f"{folder}: {len(records)} records but {len(actions)} trajectories")
    short = [
        replace(r, path_length=r.path_length - saved_turns(a)) if r.success else r for r, a in zip(records, actions)
    ]
    spl = [100 * summarize(x, by_room_type=False, protocol=protocol)["ALL"]["SPL"] for x in (records, short)]
    return spl[0], spl[1]


def outcome(t) -> str:
    """``success``, ``done`` (a Done that failed) or ``limit`` (the episode ran out of steps) of a trajectory."""
    if t.success:
        return "success"
    return "done" if t.actions and t.actions[-1] == DONE else "limit"


def outcome_figures(trajectories) -> dict:
    """The ``outcomes`` figures (module docstring) of :class:`~tsnav.eval.runner.Trajectory` objects."""
    ends = {f"{sw}_{o}": 0 for sw in ("switched", "unswitched") for o in ("success", "done", "limit")}
    moves = {o: [0, 0] for o in ("success", "done", "limit")}  # MoveAheads, blocked ones
    many = loops = episodes = 0
    for t in trajectories:
        episodes += 1
        o = outcome(t)
        ends[f"{'switched' if t.switch_frame >= 0 else 'unswitched'}_{o}"] += 1
        blocked = 0
        for i, a in enumerate(t.actions):
            if a == MOVE_AHEAD:
                moves[o][0] += 1
                if t.keys[i + 1] == t.keys[i]:
                    blocked += 1
        moves[o][1] += blocked
        many += blocked >= MANY_BLOCKED
        loops += o == "limit" and len(set(t.keys[-LOOP_FRAMES:])) <= LOOP_STATES
    total = [sum(m[0] for m in moves.values()), sum(m[1] for m in moves.values())]
    return {
        "episodes": episodes,
        **ends,
        "blocked_share": {o: m[1] / m[0] if m[0] else 0.0 for o, m in {**moves, "all": total}.items()},
        "many_blocked": many,
        "limit_loops": loops,
    }


def true_switches(data: Path, trajectories) -> dict[int, bool]:
    """Per switched episode (its index in the list): whether some instance of the target was in the frame (at any
    range) at the state where the switch fired (ground truth, read for analysis only)."""
    out: dict[int, bool] = {}
    seen: dict[str, tuple] = {}
    for t in trajectories:
        if t.switch_frame < 0:
            continue
        if t.scene not in seen:
            scene = load_scene(data / t.scene)
            seen[t.scene] = (scene, scene.visible_at_any_range())
        scene, visible = seen[t.scene]
        objs = np.flatnonzero(scene.object_category == scene.class_set.index[t.target])  # the scene's class set
        out[t.episode] = bool(visible[scene.index(t.keys[t.switch_frame]), objs].any())
    return out


def switch_truth(data: Path, trajectories) -> dict:
    """Switched episodes by outcome, split by whether the target was in the frame where the switch fired:
    ``{"true": {outcome: n}, "false": {outcome: n}}``."""
    out = {k: {"success": 0, "done": 0, "limit": 0} for k in ("true", "false")}
    truth = true_switches(data, trajectories)
    for t in trajectories:
        if t.episode in truth:
            out["true" if truth[t.episode] else "false"][outcome(t)] += 1
    return out


def read_actions(folder: Path) -> list[list[int]]:
    """Action ids (``constants.ACTIONS`` order) of every episode of a ``tsnav eval`` folder."""
    path = folder / "trajectories.jsonl"
    if not path.exists():
        raise SystemExit(f"{folder}: no trajectories.jsonl (a `tsnav eval` output folder?)")
    try:
        return [list(t.actions) for t in read_trajectories(path)]
    except ValueError as e:
        raise SystemExit(str(e)) from None


def reach_share(data: Path, episodes, name: str, c_target: float = C_TARGET) -> float:
    """Share of ``episodes`` (:class:`~tsnav.sim.episodes.Episode`) whose target scores above ``c_target``
    somewhere in its room's ``name`` table."""
    best: dict[str, tuple] = {}
    hit = 0
    for e in episodes:
        if e.scene not in best:
            det = load_detections(data / e.scene, name)
            best[e.scene] = (det.scores.max(axis=0), get_class_set(det.class_set).index)  # the table's columns
        scores, index = best[e.scene]
        hit += bool(scores[index[e.target]] > c_target)
    return hit / len(episodes)


def switch_misses(a, b) -> dict:
    """Trajectories ``a`` and ``b`` of the same episode list (matched by episode index): ``{"both": n, "a_only": n,
    "b_only": n, "neither": n, "targets": {target: [episodes, a never, b never, b only]}}``, where "a never" counts
    the episodes whose switch never fired in ``a`` and "b only" those whose switch fired in ``b`` and not in ``a``."""
    bi = {t.episode: t for t in b}
    if sorted(bi) != sorted(t.episode for t in a):
        raise ValueError("the two evaluations are not of the same episode list")
    out = {"both": 0, "a_only": 0, "b_only": 0, "neither": 0, "targets": {}}
    for t in a:
        u = bi[t.episode]
        if t.target != u.target or t.scene != u.scene:
            raise ValueError(f"episode {t.episode}: another room or target in the second evaluation")
        fa, fb = t.switch_frame >= 0, u.switch_frame >= 0
        out["both" if fa and fb else "a_only" if fa else "b_only" if fb else "neither"] += 1
        row = out["targets"].setdefault(t.target, [0, 0, 0, 0])
        row[0] += 1
        row[1] += not fa
        row[2] += not fb
        row[3] += fb and not fa
    return out


def check_bands(band: int, last: int) -> None:
    """``ValueError`` in one line unless ``band`` >= 1 and ``last`` is a positive multiple of it."""
    if band < 1 or last < band or last % band:
        raise ValueError(
            f"switch-distance: --band {band} and --last {last} must be positive, --last a multiple of --band"
        )


def switch_distance_figures(records, band: int = 5, last: int = 30, truth: dict[int, bool] | None = None) -> list[dict]:
    """The ``switch-distance`` rows (module docstring) of :class:`~tsnav.metrics.EpisodeRecord` objects: one per
    band ``[lo, lo + band)`` of L*Nav up to ``last``, then ``[last, inf)``; bands without episodes are left out.
    With ``truth`` (:func:`true_switches`, by episode index) each row also counts its false switches (the target
    not in the frame where the switch fired) and their successes; a switched episode it does not hold is refused."""
    check_bands(band, last)
    if truth is not None:
        missing = [r.episode for r in records if r.entered_pathfinding and r.episode not in truth]
        if missing:
            raise ValueError(
                f"switch-distance: episode {missing[0]} switched in the records but not in the trajectories "
                "(records.jsonl and trajectories.jsonl of different evaluations?)"
            )
    groups: dict[int, list] = {}
    for r in records:
        if not r.entered_pathfinding or r.optimal_pathfinding_length is None:
            continue
        lo = min(r.optimal_pathfinding_length // band * band, last)
        groups.setdefault(lo, []).append(r)
    rows = []
    for lo in sorted(groups):
        rs = groups[lo]
        wins = [r for r in rs if r.success]
        ratios = [
            r.pathfinding_path_length / r.optimal_pathfinding_length for r in wins if r.optimal_pathfinding_length
        ]
        rows.append(
            {
                "from": lo,
                "to": None if lo == last else lo + band,
                "episodes": len(rs),
                "successes": len(wins),
                "success_share": len(wins) / len(rs),
                "median_ratio": float(np.median(ratios)) if ratios else None,
            }
        )
        if truth is not None:
            false = [r for r in rs if not truth[r.episode]]
            rows[-1]["false_switches"] = len(false)
            rows[-1]["false_successes"] = sum(r.success for r in false)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze agent-diagnostics", description=__doc__.splitlines()[0]
    )
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("rotations", help="how evaluated agents turn")
    r.add_argument("evals", nargs="+", help="tsnav eval output folders")
    q = sub.add_parser("reach", help="share of an episode list the stage switch can reach")
    q.add_argument("--data", required=True)
    q.add_argument("--episodes", required=True)
    q.add_argument("--detections", nargs="+", required=True)
    o = sub.add_parser("outcomes", help="how episodes end; blocked MoveAheads and loops")
    o.add_argument("evals", nargs="+", help="tsnav eval output folders")
    o.add_argument("--data", default=None, help="the evaluated world: also split the switches into true and false")
    w = sub.add_parser("switches", help="where the switch fires in one evaluation and not in another, by target")
    w.add_argument("eval_a")
    w.add_argument("eval_b")
    d = sub.add_parser("switch-distance", help="success after the switch by the shortest path left at the switch")
    d.add_argument("evals", nargs="+", help="tsnav eval output folders, each as EVAL_DIR or LABEL=EVAL_DIR")
    d.add_argument("--band", type=int, default=5, help="band width in movement actions (default 5)")
    d.add_argument("--last", type=int, default=30, help="the open-ended last band starts here (default 30)")
    d.add_argument("--json", default=None, help="also write the rows of every folder to this JSON file")
    d.add_argument(
        "--false-switches",
        action="store_true",
        help="also count each band's false switches (the target not in view), reading each folder's world",
    )
    a = p.parse_args(argv)
    if a.cmd == "switch-distance":
        try:
            check_bands(a.band, a.last)
        except ValueError as e:
            raise SystemExit(str(e)) from None
        out = []
        for arg in a.evals:
            label, _, f = arg.rpartition("=")
            label = label or f
            needed = ["records.jsonl"] + (["metrics.json", "trajectories.jsonl"] if a.false_switches else [])
            for name in needed:
                if not (Path(f) / name).exists():
                    raise SystemExit(f"{f}: no {name} (a `tsnav eval` output folder?)")
            try:
                records = read_records(Path(f) / "records.jsonl")
                truth = None
                if a.false_switches:
                    data = json.loads((Path(f) / "metrics.json").read_text()).get("data")
                    if not data or not Path(data).is_dir():
                        raise ValueError(f"{f}: its world ({data or 'not named in metrics.json'}) is not here")
                    truth = true_switches(Path(data), read_trajectories(Path(f) / "trajectories.jsonl"))
                rows = switch_distance_figures(records, a.band, a.last, truth)
            except ValueError as e:
                raise SystemExit(str(e)) from None
            n = sum(r["episodes"] for r in rows)
            out.append({"label": label, "folder": f, "episodes": len(records), "switched": n, "bands": rows})
            print(f"{label}: {n} of {len(records)} episodes switched")
            extra = f" {'false':>6s} {'their successes':>15s}" if truth is not None else ""
            print(f"  {'L*Nav':>9s} {'episodes':>8s} {'successes':>9s} {'success %':>9s} {'LNav/L*Nav':>10s}{extra}")
            for r in rows:
                span = f"{r['from']}-{r['to'] - 1}" if r["to"] is not None else f">={r['from']}"
                ratio = f"{r['median_ratio']:10.2f}" if r["median_ratio"] is not None else f"{'-':>10s}"
                extra = f" {r['false_switches']:6d} {r['false_successes']:15d}" if truth is not None else ""
                print(
                    f"  {span:>9s} {r['episodes']:8d} {r['successes']:9d} {100 * r['success_share']:9.1f} {ratio}{extra}"
                )
        if a.json:
            write_json(a.json, {"band": a.band, "last": a.last, "evaluations": out})
            print(f"wrote {a.json}")
        return 0
    if a.cmd == "switches":
        runs = []
        for f in (a.eval_a, a.eval_b):
            path = Path(f) / "trajectories.jsonl"
            if not path.exists():
                raise SystemExit(f"{f}: no trajectories.jsonl (a `tsnav eval` output folder?)")
            runs.append(read_trajectories(path))
        try:
            r = switch_misses(*runs)
        except ValueError as e:
            raise SystemExit(str(e)) from None
        print(f"switch fired in both {r['both']}, only A {r['a_only']}, only B {r['b_only']}, neither {r['neither']}")
        print(f"{'target':16s} {'episodes':>8s} {'A never':>8s} {'B never':>8s} {'B only':>7s}")
        for k, v in sorted(r["targets"].items(), key=lambda kv: (-kv[1][3], -kv[1][1], kv[0])):
            print(f"{k:16s} {v[0]:8d} {v[1]:8d} {v[2]:8d} {v[3]:7d}")
        return 0
    if a.cmd == "outcomes":
        for f in a.evals:
            path = Path(f) / "trajectories.jsonl"
            if not path.exists():
                raise SystemExit(f"{f}: no trajectories.jsonl (a `tsnav eval` output folder?)")
            trajectories = read_trajectories(path)
            r = outcome_figures(trajectories)
            b = r["blocked_share"]
            print(f"{f}: {r['episodes']} episodes")
            for sw in ("switched", "unswitched"):
                print(
                    f"  {sw:10s}  success {r[sw + '_success']:5d}  failed Done {r[sw + '_done']:5d}  "
                    f"step limit {r[sw + '_limit']:5d}"
                )
            print(
                f"  blocked MoveAheads: {100 * b['all']:.1f} % (in successes {100 * b['success']:.1f} %, failed "
                f"Dones {100 * b['done']:.1f} %, step-limit failures {100 * b['limit']:.1f} %); episodes with >= "
                f"{MANY_BLOCKED} blocked: {r['many_blocked']}; step-limit failures ending in a loop: "
                f"{r['limit_loops']}"
            )
            if a.data is not None:
                for k, v in switch_truth(Path(a.data), trajectories).items():
                    print(f"  {k} switches: success {v['success']}, failed Done {v['done']}, step limit {v['limit']}")
        return 0
    if a.cmd == "rotations":
        print(
            f"{'eval':56s} {'left %':>7s} {'right %':>8s} {'runs 5-7':>9s} {'steps in them':>14s} {'saved steps':>12s}"
            "  SPL -> turning the short way"
        )
        for f in a.evals:
            r = rotation_figures(read_actions(Path(f)))
            spl = short_turn_spl(Path(f)) if (Path(f) / "records.jsonl").exists() else None
            print(
                f"{f[-56:]:56s} {100 * r['RotateLeft']:7.1f} {100 * r['RotateRight']:8.1f} {r['runs_5_to_7']:9d} "
                f"{100 * r['in_runs_share']:12.1f} % {r['saved_steps']:6d} ({100 * r['saved_share']:.1f} % of "
                f"{r['steps']})" + (f"  {spl[0]:.2f} -> {spl[1]:.2f}" if spl else "")
            )
        return 0
    data = Path(a.data)
    if not data.is_dir():
        raise SystemExit(f"--data {data}: no such folder")
    try:
        episodes, _ = read_episodes(a.episodes)
        for name in a.detections:
            print(f"{name}: {100 * reach_share(data, episodes, name):.1f} % of {len(episodes)} episodes")
    except (ValueError, FileNotFoundError) as e:
        raise SystemExit(str(e)) from None
    return 0
