"""Complete an experiment's table with rows another experiment already trained, when the run folders are gone and
only the results are left.

Table III's "Baseline (ResNet18)" and "DE-MAE (ViT) w/o crop" rows are, job for job, Table II's "baseline" and
"+ DE-MAE alone" rows (the same encoder, reward, budget and seeds). ``tsnav experiment --reuse-from`` copies such
jobs from another experiment folder; when that folder no longer exists but its ``results.json`` (or the copy
committed under ``docs/results/``) does, this script copies the rows' per-seed figures instead:

    tsnav analyze merge-rows --into T3 --from docs/results/table2_lineage_2026-12-03.json \\
        --map resnet18=baseline --map demae=demae --out T3_FULL

``--into``: an experiment folder (or its ``results.json``) that ran the other rows (``tsnav experiment pretraining
... --rows mae,demae_crop``). The result in ``--out`` is an experiment-like folder (``results.json``, ``table.md``)
that ``tsnav claims`` reads. Every protocol the two files share is merged. Refused, in one line: a row whose seed
count differs from the target's rows, results of another protocol or other detections, a row named twice.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

from ..atomic import atomic_write_json, atomic_write_text
from ..pipeline.config import EXPERIMENT_INFO, experiment_rows
from ..pipeline.experiment import claims_text, welch_text
from ..report.tables import markdown_table, welch_against


def _load(path: Path) -> dict:
    p = path / "results.json" if path.is_dir() else path
    try:
        d = json.loads(p.read_text())
    except FileNotFoundError:
        raise ValueError(f"{p}: no such results file") from None
    except (OSError, ValueError) as e:
        raise ValueError(f"{p}: unreadable results file ({e})") from None
    if not isinstance(d, dict) or not isinstance(d.get("rows"), list) or "metrics" not in d:
        raise ValueError(f"{p}: not an experiment's results.json (no rows / metrics)")
    return d


def _mapping(pairs: list[str]) -> dict[str, str]:
    out = {}
    for s in pairs:
        dst, sep, src = s.partition("=")
        if not sep or not dst or not src:
            raise ValueError(f"--map {s!r}: expected TARGET_ROW=SOURCE_ROW")
        if dst in out:
            raise ValueError(f"--map: row {dst!r} named twice")
        out[dst] = src
    return out


def _merge_one(into: dict, src: dict, mapping: dict[str, str], order: list, where: str) -> dict:
    """``into`` with the rows of ``src`` named by ``mapping`` added (metrics and subsets restricted to ``into``'s),
    in the experiment's row order, and Welch's tests against its baseline recomputed."""
    out = copy.deepcopy(into)
    have = {r["row"]: r for r in out["rows"] if r.get("n")}
    srows = {r["row"]: r for r in src["rows"]}
    seeds = {r["n"] for r in have.values()}
    for dst, s in mapping.items():
        if dst in have:
            raise ValueError(f"{where}: row {dst!r} is already in the target's results")
        if s not in srows:
            raise ValueError(f"{where}: no row {s!r} in the source (its rows: {', '.join(srows)})")
        if seeds and srows[s]["n"] not in seeds:
            raise ValueError(f"{where}: source row {s!r} has {srows[s]['n']} seeds, the target's rows {sorted(seeds)}")
    rows = {r.id: r for r in order}
    merged = []
    for r in order:
        if r.id in mapping:
            sr = srows[mapping[r.id]]
            missing = [
                (sub, m) for sub in out["subsets"] for m in out["metrics"] if m not in sr["metrics"].get(sub, {})
            ]
            if missing:
                raise ValueError(f"{where}: source row {mapping[r.id]!r} lacks {missing[0][1]} on {missing[0][0]}")
            merged.append(
                {
                    "row": r.id,
                    "label": r.label,
                    "flags": r.flags,
                    "c_target": r.c_target,
                    "encoder": r.encoder,
                    "reward": r.reward,
                    "detections": r.detections,
                    "n": sr["n"],
                    "metrics": {sub: {m: sr["metrics"][sub][m] for m in out["metrics"]} for sub in out["subsets"]},
                    "merged_from": {
                        "row": mapping[r.id],
                        "label": sr.get("label"),
                        "experiment": src.get("experiment"),
                    },
                }
            )
        elif r.id in have:
            merged.append(have[r.id])
    unknown = [d for d in mapping if d not in rows]
    if unknown:
        raise ValueError(f"{where}: no row {unknown[0]!r} in the {out.get('experiment')} experiment")
    out["rows"] = merged
    return out


def merge(into: dict, src: dict, mapping: dict[str, str]) -> dict:
    """The merged results (see the module docstring)."""
    exp = into.get("experiment")
    if exp not in EXPERIMENT_INFO:
        raise ValueError(f"the target's results name no known experiment ({exp!r})")
    for k in ("protocol", "detections"):
        if into.get(k) != src.get(k):
            raise ValueError(f"the source's {k} is {src.get(k)!r}, the target's {into.get(k)!r}")
    order = experiment_rows(exp)
    base = EXPERIMENT_INFO[exp]["baseline_row"]
    out = _merge_one(into, src, mapping, order, "results")
    out["welch"] = welch_against(out, base)
    others = {}
    for p, res in (into.get("other_protocols") or {}).items():
        sres = (src.get("other_protocols") or {}).get(p)
        if sres is None:
            continue
        res = dict(res, experiment=exp)
        m = _merge_one(res, sres, mapping, order, f"protocol {p}")
        m["welch"] = welch_against(m, base)
        others[p] = m
    out["other_protocols"] = others
    out["merged"] = {"rows": mapping, "source_experiment": src.get("experiment"), "source_note": src.get("note")}
    return out


def table_text(res: dict) -> str:
    exp = res["experiment"]
    text = (
        f"## {exp}: {EXPERIMENT_INFO[exp]['description']}\n\nSuccess protocol `{res['protocol']}`. Rows "
        + ", ".join(f"'{r['label']}'" for r in res["rows"] if "merged_from" in r)
        + f" copied from the {res['merged']['source_experiment']} experiment's rows "
        + ", ".join(f"'{r['merged_from']['label']}'" for r in res["rows"] if "merged_from" in r)
        + " (same training configuration and seeds).\n\n"
        + markdown_table(res)
        + "\nValues in percent: mean over seeds ± half-width of the 95 % t-interval. "
        + f"Detections: {res['detections']}.\n"
    )
    if res["welch"]:
        text += welch_text(
            res,
            f"Differences against '{res['welch']['baseline']}' in percentage points, Welch's "
            "t-test p-value over the per-seed values",
        )
    text += claims_text(exp, res, "Against the paper's claims (`tsnav claims`)")
    for p, r in res["other_protocols"].items():
        text += f"\n### The same agents under the `{p}` protocol\n\n" + markdown_table(r)
        if r["welch"]:
            text += welch_text(r, f"Differences against '{r['welch']['baseline']}' under `{p}`")
        text += claims_text(exp, r, f"Against the paper's claims under `{p}`")
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze merge-rows", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--into", required=True, type=Path, help="experiment folder or results.json with the other rows")
    ap.add_argument("--from", dest="src", required=True, type=Path, help="results.json holding the rows to copy")
    ap.add_argument(
        "--map",
        action="append",
        default=[],
        required=True,
        metavar="TARGET=SOURCE",
        help="a row of the target's experiment and the source row it is (repeatable)",
    )
    ap.add_argument("--out", required=True, type=Path, help="folder to write results.json and table.md into")
    args = ap.parse_args(argv)
    try:
        res = merge(_load(args.into), _load(args.src), _mapping(args.map))
        if args.out.exists() and not args.out.is_dir():
            raise ValueError(f"--out {args.out}: exists and is not a folder")
    except ValueError as e:
        print(f"merge_rows: {e}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.out / "results.json", res)
    text = table_text(res)
    atomic_write_text(args.out / "table.md", text)
    print(text)
    return 0
