"""Collect convergence runs and their test evaluations into one JSON file for docs/results/.

Each ``--run NAME=DIR`` names a ``tsnav convergence`` output folder (its ``curve.json`` is copied: the validation
points and the chosen milestone). Each ``--eval NAME:TAG=DIR`` names a ``tsnav eval`` output folder whose figures
(``metrics.json``: ALL and L>=5; ``outcomes.json``: how the episodes ended, after the switch) are filed under run
NAME as TAG. ``--setting KEY=VALUE`` records the setting in words (world, features, commands), as a reader needs it.

    tsnav analyze collect-runs --out docs/results/X.json --title "..." \\
        --setting "command=tsnav convergence ..." --run learned4-s0=OUT0 --eval learned4-s0:lineage=EVAL0 ...

``--table`` prints the test SR / SPL per (run, tag) and the mean over runs sharing a prefix before ``-s``.
The output is written atomically; nothing is written when a folder is missing or unreadable.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

from ..atomic import atomic_write_json
from ..errors import CommandError, read_json
from ..metrics import METRICS


def _pair(text: str, what: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key or not value:
        raise SystemExit(f"{what} {text!r}: expected KEY=VALUE")
    return key, value


def _read(path: Path) -> dict:
    try:
        return read_json(path, missing="no such file")
    except CommandError as e:
        raise SystemExit(str(e)) from None


def eval_figures(folder: Path) -> dict:
    """Test figures of one ``tsnav eval`` folder: metrics of ALL and L>=5, episodes, protocol, outcomes."""
    m = _read(folder / "metrics.json")
    out = {
        sub: {k: round(float(m["metrics"][sub][k]), 6) for k in METRICS if k in m["metrics"][sub]}
        for sub in ("ALL", "L>=5")
    }
    out.update(
        K=m["metrics"]["ALL"].get("K"),
        protocol=m.get("protocol"),
        trained_protocol=m.get("trained_protocol"),
        checkpoint=m.get("checkpoint"),
        sample=m.get("sample"),
    )
    o = folder / "outcomes.json"
    if o.exists():
        oc = _read(o)
        out["outcomes"] = {k: oc[k] for k in ("counts", "after_switch", "action_shares") if k in oc}
    return out


def collect(runs: dict[str, Path], evals: dict[tuple[str, str], Path]) -> dict:
    missing = [n for n, _ in evals if n not in runs]
    if missing:
        raise SystemExit(f"--eval names runs not given with --run: {', '.join(sorted(set(missing)))}")
    out = {}
    for name, folder in runs.items():
        curve = _read(folder / "curve.json")
        out[name] = {"folder": str(folder), "curve": curve, "test": {}}
    for (name, tag), folder in evals.items():
        out[name]["test"][tag] = eval_figures(folder)
    return out


def table(runs: dict) -> str:
    """Per (run, tag) SR / SPL, then means over runs whose names share the part before ``-s<seed>``."""
    lines = [f"{'run':32s} {'tag':24s} {'SR':>7s} {'SPL':>7s} {'SSR':>7s}"]
    groups = defaultdict(lambda: defaultdict(list))
    for name, r in runs.items():
        base = name.rsplit("-s", 1)[0] if "-s" in name else name
        for tag, t in r["test"].items():
            a = t["ALL"]
            lines.append(
                f"{name:32s} {tag:24s} {100 * a['SR']:7.2f} {100 * a['SPL']:7.2f} {100 * a.get('SSR', 0):7.2f}"
            )
            groups[base][tag].append((a["SR"], a["SPL"]))
    lines.append("means over seeds:")
    for base, tags in groups.items():
        for tag, v in tags.items():
            sr = 100 * sum(x for x, _ in v) / len(v)
            spl = 100 * sum(y for _, y in v) / len(v)
            lines.append(f"{base:32s} {tag:24s} {sr:7.2f} {spl:7.2f}   ({len(v)} runs)")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze collect-runs", description=__doc__.splitlines()[0]
    )
    p.add_argument("--out", required=True, help="JSON file to write")
    p.add_argument("--title", required=True, help="what the runs measure")
    p.add_argument("--setting", action="append", default=[], help="KEY=VALUE, the setting in words (repeatable)")
    p.add_argument("--run", action="append", default=[], help="NAME=DIR of a tsnav convergence output (repeatable)")
    p.add_argument("--eval", action="append", default=[], help="NAME:TAG=DIR of a tsnav eval output (repeatable)")
    p.add_argument("--table", action="store_true", help="also print the test figures")
    a = p.parse_args(argv)
    if not a.run:
        raise SystemExit("give at least one --run NAME=DIR")
    runs = {}
    for text in a.run:
        k, v = _pair(text, "--run")
        runs[k] = Path(v)
    evals = {}
    for text in a.eval:
        k, v = _pair(text, "--eval")
        name, sep, tag = k.partition(":")
        if not sep or not tag:
            raise SystemExit(f"--eval {text!r}: expected NAME:TAG=DIR")
        evals[(name, tag)] = Path(v)
    collected = collect(runs, evals)
    doc = {"experiment": a.title, "setting": dict(_pair(s, "--setting") for s in a.setting), "runs": collected}
    atomic_write_json(a.out, doc)
    if a.table:
        print(table(collected))
    print(f"wrote {a.out}", file=sys.stderr)
    return 0
