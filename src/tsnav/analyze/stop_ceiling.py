"""What an evaluation's agent would score with a perfect stop: Done called at the first success state it reaches on
its own walk, the walk otherwise unchanged.

    tsnav analyze stop-ceiling EVAL_FOLDER [EVAL_FOLDER ...] [--json OUT.json]

EVAL_FOLDER is a `tsnav eval` output (records.jsonl, trajectories.jsonl with each episode's ``success_frame``, the
first frame at a success state of the target, -1 when none). Each episode that reached a success state becomes a
success whose path ends there (``success_frame`` movement actions); the others keep their failure. SR and SPL are
then counted as ``tsnav eval`` counts them, under the folder's protocol (its length convention included). The gap
between the two rows is what the agent's stopping decision costs; what is left below the ceiling is its walk.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

from ..atomic import atomic_write_json
from ..eval.runner import read_trajectories
from ..metrics import EpisodeRecord, read_records, summarize
from ..protocol import protocol_of


def stopped_records(records: list[EpisodeRecord], frames, success=None) -> list[EpisodeRecord]:
    """The records with Done output at frame ``frames[i]`` (after that many movement actions; < 0: no Done there, the
    record unchanged), a success where ``success[i]`` says so (None: every stop succeeds, as at a first success
    frame). Shared by stop-ceiling and stop-head's replays."""
    if len(records) != len(frames):
        raise ValueError(f"{len(records)} records for {len(frames)} trajectories")
    ok = [True] * len(records) if success is None else success
    return [
        r if int(f) < 0 else replace(r, success=bool(s), path_length=int(f), steps=int(f) + 1)
        for r, f, s in zip(records, frames, ok)
    ]


def sr_spl(records: list[EpisodeRecord], protocol: str) -> dict:
    """``{"SR", "SPL"}`` in percent over all the records, counted as `tsnav eval` counts them under ``protocol``."""
    m = summarize(records, by_room_type=False, protocol=protocol)["ALL"]
    return {"SR": 100 * m["SR"], "SPL": 100 * m["SPL"]}


def stop_ceiling(eval_dir: Path) -> dict:
    """``{"agent": {SR, SPL}, "stop at the first success state": {SR, SPL}, "episodes", "protocol"}`` (percent)."""
    meta = json.loads((eval_dir / "metrics.json").read_text())
    protocol = protocol_of(meta)
    records = read_records(eval_dir / "records.jsonl")
    traj = read_trajectories(eval_dir / "trajectories.jsonl")
    if any(t.success_frame is None for t in traj):
        raise ValueError(f"{eval_dir}: trajectories without success_frame (evaluated by an older tsnav)")
    rows = {
        "agent": sr_spl(records, protocol),
        "stop at the first success state": sr_spl(stopped_records(records, [t.success_frame for t in traj]), protocol),
    }
    return {"eval": str(eval_dir), "protocol": protocol, "episodes": len(records), "rows": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze stop-ceiling", description=__doc__.splitlines()[0]
    )
    ap.add_argument("eval_dirs", nargs="+", type=Path, metavar="EVAL_FOLDER")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    out = []
    for d in args.eval_dirs:
        if not (d / "records.jsonl").exists():
            print(f"tsnav analyze stop-ceiling: {d}: no records.jsonl (not a `tsnav eval` folder)", file=sys.stderr)
            return 2
        try:
            res = stop_ceiling(d)
        except ValueError as e:
            print(f"tsnav analyze stop-ceiling: {e}", file=sys.stderr)
            return 2
        out.append(res)
        a, s = res["rows"]["agent"], res["rows"]["stop at the first success state"]
        print(
            f"{d} ({res['protocol']}, {res['episodes']} episodes): agent SR {a['SR']:.2f} SPL {a['SPL']:.2f}; "
            f"Done at the first success state it reaches: SR {s['SR']:.2f} SPL {s['SPL']:.2f}"
        )
    if args.json:
        atomic_write_json(args.json, {"format": "tsnav-stop-ceiling", "results": out}, sort_keys=False)
        print(f"wrote {args.json}")
    return 0
