"""Where an evaluation's failed Dones happen: for every episode that switched to pathfinding and ended in a Done
that did not succeed, the target at the final state, whether some instance of it is in the frame at any range,
the nearest such instance's distance, and the score the named detection table gives it there.

    tsnav analyze wrong-done --data WORLD --eval EVAL_FOLDER --detections learned4 [--json OUT.json]

EVAL_FOLDER is a `tsnav eval` output (its trajectories.jsonl). The ground-truth visibility and distances are read
for this analysis only; nothing here reaches an agent. (RESULTS.md, "the detector's share under the lineage
protocol": the breakdown of its wrong Dones.)
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_json
from ..constants import DONE, TARGET_CATEGORIES
from ..data.detections import load_detections
from ..data.reader import load_scene
from ..eval.runner import read_trajectories


def failed_dones(data: Path, eval_dir: Path, detections: str) -> list[dict]:
    """One row per switched episode of ``eval_dir`` (``switch_frame`` >= 0) that ended in a failed Done: target,
    score, in_view, dist."""
    scenes, rows = {}, []
    for t in read_trajectories(eval_dir / "trajectories.jsonl"):
        if t.success or not t.actions or t.actions[-1] != DONE or t.switch_frame < 0:
            continue
        if t.scene not in scenes:
            s = load_scene(data / t.scene)
            scenes[t.scene] = (s, load_detections(data / t.scene, detections), s.visible_at_any_range())
        s, det, seen = scenes[t.scene]
        i, c = s.index(t.keys[-1]), TARGET_CATEGORIES.index(t.target)
        objs = np.flatnonzero(s.object_category == c)
        vis = seen[i, objs]
        rows.append(
            {
                "target": t.target,
                "score": float(det.scores[i, c]),
                "in_view": bool(vis.any()),
                "dist": float(s.distance[i, objs][vis].min()) if vis.any() else None,
            }
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze wrong-done", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--data", required=True, type=Path)
    ap.add_argument("--eval", required=True, type=Path, dest="eval_dir")
    ap.add_argument("--detections", required=True)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    if not (a.eval_dir / "trajectories.jsonl").is_file():
        print(f"wrong_done: {a.eval_dir} has no trajectories.jsonl (a `tsnav eval` output folder)", file=sys.stderr)
        return 2
    rows = failed_dones(a.data, a.eval_dir, a.detections)
    inv = [r for r in rows if r["in_view"]]
    far = np.array([r["dist"] for r in inv])
    gone = [r["score"] for r in rows if not r["in_view"]]
    print(
        f"{a.eval_dir.name}: {len(rows)} failed Dones after a switch; target in view: {len(inv)} (distance median "
        f"{np.median(far) if len(far) else float('nan'):.2f} m; <= 1.5 m {int((far <= 1.5).sum())}, 1.5-2.5 m "
        f"{int(((far > 1.5) & (far <= 2.5)).sum())}, > 2.5 m {int((far > 2.5).sum())}); not in view: {len(gone)} "
        f"(score there: median {np.median(gone) if gone else float('nan'):.2f})"
    )
    print(" by target:", Counter(r["target"] for r in rows).most_common(8))
    if a.json:
        atomic_write_json(a.json, {"n": len(rows), "in_view": len(inv), "rows": rows})
    return 0
