"""How evaluation episodes end, and what the stage switch had to do with it.

SR alone does not say why an agent fails. Every episode ends in one of three ways - Done in a success state
(success), Done elsewhere (a wrong Done), or the step limit - and either did or did not enter the pathfinding
stage (the target's detector confidence passed C_target at some frame, paper III-B). Crossing the two shows
whether failures are search failures (the switch never fired: the detector never became confident about the
target) or pathfinding / stopping failures (it fired, yet no success). Per target class, SR beside the switch
rate shows which classes the detector cannot see. Failed episodes that passed through a success state (the target
in view within the success distance, where Done would have succeeded) separate "did not stop" from "did not get
there". After the switch, the same split (passed a success state without Done / wrong Done / never got to one)
and the path length of the successful switched episodes against the shortest one from the switch frame show what
the pathfinding stage costs. The action shares show degenerate policies (e.g. one that never turns left).

:func:`outcome_summary` is what ``tsnav eval`` prints under its metrics table and writes to ``outcomes.json``.
"""

from __future__ import annotations

from collections import Counter
from typing import Sequence

import numpy as np

from ..constants import ACTIONS, DONE
from ..metrics import EpisodeRecord

# Trajectories are :class:`tsnav.eval.runner.Trajectory` objects (runner imports this module, so they are typed
# by what is read from them: ``episode``, ``target``, ``success``, ``actions``).

#: File of :func:`outcome_summary` in an evaluation folder.
OUTCOMES_FILE = "outcomes.json"
#: How an episode ended.
ENDINGS = ("success", "wrong Done", "step limit")


def outcome_keys() -> list[str]:
    """The six (ending, switch) cells, in display order."""
    return [f"{e}, {'switched' if s else 'never switched'}" for e in ENDINGS for s in (True, False)]


def episode_ending(trajectory) -> str:
    """``success``, ``wrong Done`` (Done outside a success state) or ``step limit`` (no Done: the episode was
    cut at the evaluation's step limit)."""
    if trajectory.success:
        return "success"
    if trajectory.actions and trajectory.actions[-1] == DONE:
        return "wrong Done"
    return "step limit"


def select_episodes(records: Sequence[EpisodeRecord], n: int = 6, seed: int = 0) -> list[int]:
    """Indices (into ``records``) of about ``n`` episodes to show: half successes, half failures (whichever
    kind is short is filled with the other), preferring episodes with ``L* >= 5`` that switched stage, spread
    over scenes and targets. Deterministic."""
    rng = np.random.default_rng(seed)
    if n <= 0 or not records:
        return []

    def score(i: int) -> tuple:
        r = records[i]
        return (-(r.optimal_length >= 5), -bool(r.entered_pathfinding), rng.random())

    succ = sorted([i for i, r in enumerate(records) if r.success], key=score)
    fail = sorted([i for i, r in enumerate(records) if not r.success], key=score)

    def spread(pool: list[int], k: int) -> list[int]:
        chosen, seen = [], set()
        for i in pool:  # first pass: one per (scene, target)
            key = (records[i].scene, records[i].target)
            if key not in seen and len(chosen) < k:
                chosen.append(i)
                seen.add(key)
        for i in pool:
            if len(chosen) >= k:
                break
            if i not in chosen:
                chosen.append(i)
        return chosen

    k_s = min(len(succ), max(n - len(fail), (n + 1) // 2))
    k_f = min(len(fail), n - k_s)
    return spread(succ, k_s) + spread(fail, k_f)


def outcome_summary(records: Sequence[EpisodeRecord], trajectories: Sequence) -> dict:
    """Counts of (ending, switched) over the episodes, success rates with and without a switch, per-target
    episodes / SR / switch rate, and the share of each action among all actions taken.

    ``records`` and ``trajectories`` are the same episodes in the same order (as ``tsnav eval`` writes them);
    ``ValueError`` when they are not."""
    if len(records) != len(trajectories):
        raise ValueError(f"{len(records)} records but {len(trajectories)} trajectories")
    counts = {k: 0 for k in outcome_keys()}
    targets: dict[str, list[int]] = {}
    actions: Counter = Counter()
    missed = {"switched": 0, "never switched": 0}
    known = all(getattr(t, "success_frame", None) is not None for t in trajectories)
    for r, t in zip(records, trajectories):
        if (r.episode, r.target, bool(r.success)) != (t.episode, t.target, bool(t.success)):
            raise ValueError(f"episode {r.episode}: record and trajectory disagree (another evaluation?)")
        switched = bool(r.entered_pathfinding)
        counts[f"{episode_ending(t)}, {'switched' if switched else 'never switched'}"] += 1
        if known and not r.success and t.success_frame >= 0:
            missed["switched" if switched else "never switched"] += 1
        row = targets.setdefault(r.target, [0, 0, 0])
        row[0] += 1
        row[1] += int(bool(r.success))
        row[2] += int(switched)
        actions.update(t.actions)
    n = len(records)
    after = after_switch(records, trajectories)
    n_sw = sum(v for k, v in counts.items() if k.endswith(", switched"))
    succ_sw = counts["success, switched"]
    succ_no = counts["success, never switched"]
    total_actions = sum(actions.values())
    return {
        "episodes": n,
        "counts": counts,
        "switched": n_sw,
        "success_if_switched": succ_sw / n_sw if n_sw else None,
        "success_if_never_switched": succ_no / (n - n_sw) if n - n_sw else None,
        # failed episodes that were in a success state at some frame (None: trajectories without success_frame)
        "failed_after_a_success_state": missed if known else None,
        # the pathfinding stage (None: trajectories without switch_distance)
        "after_switch": after,
        "per_target": {
            k: {"episodes": v[0], "SR": v[1] / v[0], "switch_rate": v[2] / v[0]} for k, v in sorted(targets.items())
        },
        "action_shares": {a: (actions[i] / total_actions if total_actions else 0.0) for i, a in enumerate(ACTIONS)},
    }


def after_switch(records: Sequence[EpisodeRecord], trajectories: Sequence) -> dict | None:
    """What the switched episodes did from their switch frame on: successes, failures split into passed a success
    state at or after the switch without calling Done / called Done in a wrong state / never got to a success
    state, the median L* at the switch, and ``path_ratio``: actions taken from the switch frame on (Done
    included) over L* + 1, summed over the successful switched episodes (1.0 = the shortest path, then Done).
    None when a trajectory lacks ``switch_distance`` (files written before it existed)."""
    if any(
        getattr(t, "switch_distance", None) is None or getattr(t, "success_after_switch", None) is None
        for t in trajectories
    ):
        return None
    failures = {"passed a success state without Done": 0, "wrong Done": 0, "never got to a success state": 0}
    successes, taken, shortest, at_switch = 0, 0, 0, []
    for r, t in zip(records, trajectories):
        if not r.entered_pathfinding or t.switch_frame < 0:
            continue
        if t.switch_distance >= 0:
            at_switch.append(t.switch_distance)
        if r.success:
            successes += 1
            if t.switch_distance >= 0:
                taken += len(t.actions) - t.switch_frame
                shortest += t.switch_distance + 1
        elif episode_ending(t) == "wrong Done":
            failures["wrong Done"] += 1
        elif t.success_after_switch >= 0:
            failures["passed a success state without Done"] += 1
        else:
            failures["never got to a success state"] += 1
    return {
        "episodes": successes + sum(failures.values()),
        "success": successes,
        "failures": failures,
        "median_distance_at_switch": float(np.median(at_switch)) if at_switch else None,
        "path_ratio": taken / shortest if shortest else None,
    }


def format_outcomes(summary: dict) -> str:
    """The summary as plain text: endings x switch, the two conditional success rates, per-target rows sorted
    by SR, action shares (percent)."""
    n = summary["episodes"]
    lines = [f"how the {n} episodes ended (switch = the target's confidence passed C_target at some frame):"]
    for k in outcome_keys():
        v = summary["counts"].get(k, 0)
        lines.append(f"  {k:32s} {v:6d}  {100 * v / n if n else 0:5.1f} %")

    def pct(x):
        return "-" if x is None else f"{100 * x:.1f} %"

    lines.append(
        f"  success when the switch fired: {pct(summary['success_if_switched'])}; "
        f"when it never fired: {pct(summary['success_if_never_switched'])}"
    )
    missed = summary.get("failed_after_a_success_state")
    if missed is not None:
        fails = {
            k: sum(v for c, v in summary["counts"].items() if c.endswith(f", {k}") and not c.startswith("success"))
            for k in ("switched", "never switched")
        }
        lines.append(
            "  failed although in a success state at some frame (Done there would have succeeded): "
            f"{missed['switched']} of {fails['switched']} switched failures, "
            f"{missed['never switched']} of {fails['never switched']} never-switched ones"
        )
    after = summary.get("after_switch")
    if after is not None and after["episodes"]:
        f = after["failures"]
        ratio = "-" if after["path_ratio"] is None else f"{after['path_ratio']:.2f}"
        lines.append(
            f"  after the switch: {after['success']} of {after['episodes']} succeeded; failures: passed a "
            f"success state without Done {f['passed a success state without Done']}, wrong Done "
            f"{f['wrong Done']}, never got to one {f['never got to a success state']}; median L* at the "
            f"switch {after['median_distance_at_switch']:g}; successes took {ratio}x the shortest path"
        )
    lines.append("  target            episodes     SR   switch")
    rows = sorted(summary["per_target"].items(), key=lambda kv: (-kv[1]["SR"], -kv[1]["switch_rate"], kv[0]))
    for name, row in rows:
        lines.append(f"  {name:16s} {row['episodes']:9d} {100 * row['SR']:6.1f} {100 * row['switch_rate']:8.1f}")
    shares = ", ".join(f"{a} {100 * summary['action_shares'].get(a, 0.0):.1f} %" for a in ACTIONS)
    lines.append(f"  actions: {shares}")
    return "\n".join(lines)
