"""One factor at a time against a base run, on the same evaluation episodes: every metric of each row and each
lever's paired difference from the base, with 95 % bootstrap intervals over the episodes.

    tsnav analyze lever-table --out docs/results/levers.json --title "..." \\
        --base "shipped recipe=EVAL_BASE" --lever "memory history=EVAL_A" --lever "regret reward=EVAL_B" \\
        [--setting KEY=VALUE ...] [--resamples 2000] [--seed 0]

Each EVAL is a `tsnav eval` output folder (its records.jsonl) or a folder holding one per protocol
(``EVAL/lineage/records.jsonl``, ``EVAL/paper/records.jsonl``; or the ``PROTOCOL/agent/`` folders of
`tsnav release eval`). Every row must hold the same episodes in the same order (scene, start, target): the
difference is paired, episode by episode. The interval resamples the episodes (the same resample for the base and
the lever), so it measures how much the figure depends on which episodes were drawn, not how much it depends on the
training seed: a lever run at one seed is one draw of its training.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_json
from ..metrics import METRICS, EpisodeRecord, long_episode, metric_values, read_records, record_columns
from ..protocol import PROTOCOLS


def find_records(folder: Path) -> dict[str, Path]:
    """protocol -> records.jsonl of an evaluation folder (one protocol read from its metrics.json, or one per
    protocol subfolder). ``ValueError`` naming the folder when it holds none."""
    if (folder / "records.jsonl").is_file():
        proto = "paper"
        if (folder / "metrics.json").is_file():
            proto = json.loads((folder / "metrics.json").read_text()).get("protocol", proto)
        return {proto: folder / "records.jsonl"}
    found = {}
    for proto in PROTOCOLS:
        for sub in (folder / proto, folder / proto / "agent"):
            if (sub / "records.jsonl").is_file():
                found[proto] = sub / "records.jsonl"
                break
    if not found:
        raise ValueError(f"{folder}: no records.jsonl (a `tsnav eval` or `tsnav release eval` output folder)")
    return found


def episode_keys(records: list[EpisodeRecord]) -> list[tuple]:
    return [(r.scene, r.start, r.target) for r in records]


def bootstrap(
    cols: dict[str, np.ndarray], base: str, protocol: str, resamples: int, seed: int
) -> tuple[dict[str, dict[str, list[float]]], dict[str, dict[str, list[float]]]]:
    """95 % percentile intervals of every row's metrics and of each other row's difference from ``base``, over
    ``resamples`` draws of the episodes with replacement, one draw for all rows (the differences are paired).
    ``cols``: row -> columns as :func:`tsnav.metrics.record_columns`, the same episodes in the same order."""
    k = cols[base].shape[1]
    rng = np.random.default_rng(seed)
    draws = {name: [] for name in cols}
    for _ in range(resamples):
        idx = rng.integers(0, k, k)
        for name, c in cols.items():
            draws[name].append(metric_values(*c[:, idx], protocol=protocol))

    def ci(samples) -> dict[str, list[float]]:
        return {m: [float(q) for q in np.percentile(samples[m], [2.5, 97.5])] for m in METRICS}

    per_row = {name: {m: np.array([d[m] for d in ds]) for m in METRICS} for name, ds in draws.items()}
    rows = {name: ci(v) for name, v in per_row.items()}
    deltas = {name: ci({m: v[m] - per_row[base][m] for m in METRICS}) for name, v in per_row.items() if name != base}
    return rows, deltas


def lever_table(
    base: tuple[str, Path], levers: list[tuple[str, Path]], resamples: int = 2000, seed: int = 0
) -> dict[str, dict]:
    """protocol -> {episodes, rows}: the base row, then one row per lever with its ``delta`` from the base; every
    value a fraction with its ``ci95``; L>=5 values beside (no intervals). Only the protocols every folder holds."""
    found = {name: find_records(folder) for name, folder in [base, *levers]}
    protocols = [p for p in PROTOCOLS if all(p in f for f in found.values())]
    if not protocols:
        raise ValueError("the folders share no protocol: " + ", ".join(f"{n}: {sorted(f)}" for n, f in found.items()))
    out = {}
    for proto in protocols:
        recs = {name: read_records(f[proto]) for name, f in found.items()}
        keys = episode_keys(recs[base[0]])
        for name, r in recs.items():
            if episode_keys(r) != keys:
                raise ValueError(
                    f"{name} ({found[name][proto]}): not the base's episodes ({len(r)} against {len(keys)}, or "
                    "another order): evaluate every row on the same episode list"
                )
        cols = {name: record_columns(r) for name, r in recs.items()}
        long_ = np.array([long_episode(r.optimal_length, protocol=proto) for r in recs[base[0]]])
        cis, delta_cis = bootstrap(cols, base[0], proto, resamples, seed)
        value = {name: metric_values(*c, protocol=proto) for name, c in cols.items()}
        rows = []
        for name, c in cols.items():
            v5 = metric_values(*c[:, long_], protocol=proto)
            row = {
                "row": name,
                "ALL": {m: {"value": value[name][m], "ci95": cis[name][m]} for m in METRICS},
                "L>=5": {m: {"value": v5[m]} for m in METRICS},
            }
            if name != base[0]:
                row["delta"] = {
                    m: {"value": value[name][m] - value[base[0]][m], "ci95": delta_cis[name][m]} for m in METRICS
                }
            rows.append(row)
        out[proto] = {"episodes": len(keys), "L>=5 episodes": int(long_.sum()), "rows": rows}
    return out


def format_rows(table: dict[str, dict], metrics: tuple[str, ...] = ("SR", "SPL", "NSNPL")) -> str:
    """A plain-text view: each row's metrics and, for levers, the difference with its interval (percent)."""
    lines = []
    for proto, t in table.items():
        lines.append(f"{proto} ({t['episodes']} episodes)")
        for r in t["rows"]:
            cells = []
            for m in metrics:
                v = r["ALL"][m]["value"] * 100
                cell = f"{m} {v:6.2f}"
                if "delta" in r:
                    d = r["delta"][m]
                    lo, hi = (100 * q for q in d["ci95"])
                    cell += f" ({100 * d['value']:+.2f} [{lo:+.2f}, {hi:+.2f}])"
                cells.append(cell)
            lines.append(f"  {r['row']:<24} " + "  ".join(cells))
    return "\n".join(lines)


def _pair(text: str, what: str) -> tuple[str, Path]:
    if "=" not in text:
        raise SystemExit(f"lever-table: {what} {text!r}: expected NAME=FOLDER")
    name, folder = text.rsplit("=", 1)
    return name, Path(folder)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze lever-table", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--out", required=True, type=Path, help="results JSON to write")
    ap.add_argument("--title", required=True, help="what the rows measure")
    ap.add_argument("--base", required=True, help="NAME=EVAL of the base run")
    ap.add_argument("--lever", action="append", default=[], help="NAME=EVAL of a lever's run (repeatable)")
    ap.add_argument("--setting", action="append", default=[], help="KEY=VALUE, the setting in words (repeatable)")
    ap.add_argument("--resamples", type=int, default=2000, help="bootstrap draws of the episodes (default 2000)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the draws (default 0)")
    a = ap.parse_args(argv)
    if a.resamples < 100:
        raise SystemExit(f"lever-table: --resamples {a.resamples}: at least 100 draws give a 95 % interval")
    base, levers = _pair(a.base, "--base"), [_pair(x, "--lever") for x in a.lever]
    names = [base[0], *(n for n, _ in levers)]
    if len(set(names)) != len(names):
        raise SystemExit(f"lever-table: row names repeat: {names}")
    bad = [x for x in a.setting if "=" not in x]
    if bad:
        raise SystemExit(f"lever-table: --setting {bad[0]!r}: expected KEY=VALUE")
    setting = dict(x.split("=", 1) for x in a.setting)
    try:
        table = lever_table(base, levers, a.resamples, a.seed)
    except (OSError, ValueError) as e:
        print(f"lever-table: {e}", file=sys.stderr)
        return 2
    atomic_write_json(
        a.out,
        {
            "format": "tsnav-lever-table",
            "title": a.title,
            "setting": setting,
            "resamples": a.resamples,
            "seed": a.seed,
            "interval": "95 % percentile bootstrap over the episodes, paired with the base for the differences",
            "folders": {n: str(f) for n, f in [base, *levers]},
            "protocols": table,
        },
    )
    print(format_rows(table))
    print(f"written {a.out}")
    return 0
