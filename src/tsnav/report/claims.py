"""The paper's claims, read against an experiment's results.

Each claim of the paper's ablation (Table II), pretraining comparison (Table III) and threshold choice (Fig. 4)
is written here as "row B scores higher than row A on these metrics". :func:`check_claims` takes the
``results.json`` of finished experiments (:func:`tsnav.report.tables.aggregate`), computes per claim, metric and
episode subset the difference of the per-seed means and Welch's p-value (:func:`tsnav.report.tables.welch`), puts
the paper's own difference beside it, and gives a verdict:

- ``supported``: same sign as the claim, p < :data:`ALPHA`;
- ``contradicted``: opposite sign, p < :data:`ALPHA`;
- ``same sign, n.s.`` / ``opposite sign, n.s.``: no significant difference either way (``no difference``
  when the means are equal);
- ``one seed``: a difference without a test (fewer than two seeds on a side);
- ``no spread``: every seed of both rows gave the same value (no test possible);
- ``not run``: a row is missing.

The threshold claim (Fig. 4: C_target = 0.7 is best) compares the chosen row with every other row. Its line
shows the difference against the best other row (by that metric's mean) and its p-value is the one of the
whole claim: when 0.7 is ahead of every other row, the largest Welch p over all of them (it is significantly
best only when it is significantly ahead of each one: an intersection-union test); when some row is ahead of
0.7, the smallest Welch p among the rows ahead of it times the number of other rows (Bonferroni: picking the
best of eight rows and testing it alone would call 0.7 "contradicted" far more often than 5 % of the time when
all rows are equal). The 95 % interval stays the one of the difference against the best other row.

Where the paper's text and its tables differ (the text gives SSR +1.49 for the exploration reward on ALL
episodes, Table II 96.63 - 95.49 = +1.14), the tables are used.

``tsnav claims EXP_DIR [EXP_DIR ...]`` prints the table; ``tsnav experiment`` appends its own experiment's part
to ``table.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from html import escape
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy.stats import t as student

from ..atomic import atomic_save_figure, atomic_write_text
from ..errors import CommandError, read_json
from ..metrics import PAPER_METRICS
from ..protocol import DEFAULT_PROTOCOL, PROTOCOLS
from .tables import SUBSETS, finite, welch
from ..settings import add_shared

#: Significance level of the verdicts (two-sided Welch test over the per-seed values).
ALPHA = 0.05
#: The paper's five metrics (:mod:`tsnav.metrics`): the columns of its Table II, compared by the claims below.
METRICS = PAPER_METRICS

#: The paper's published figures (Tables I-III, percent), typed once in ``report/data/paper.json``.
PUBLISHED_FILE = Path(__file__).resolve().parent / "data" / "paper.json"


def published_figures() -> dict:
    """The paper's Tables I-III as printed (``report/data/paper.json``; the results page reads the same file)."""
    return json.loads(PUBLISHED_FILE.read_text())


def _paper_table(key: str) -> dict:
    table = published_figures()[key]
    return {
        rid: {subset: dict(zip(table["columns"], vals)) for subset, vals in row.items()}
        for rid, row in table["rows"].items()
    }


#: The paper's Table II (AI2-THOR, percent): row id -> subset -> metric -> value.
PAPER_TABLE_II = _paper_table("table2")
#: The paper's Table III (AI2-THOR, percent, SR and SPL): row id -> subset -> metric -> value.
PAPER_TABLE_III = _paper_table("table3")
PAPER = {"ablation": PAPER_TABLE_II, "pretraining": PAPER_TABLE_III}


@dataclass(frozen=True)
class Claim:
    """ "Row ``higher`` scores above row ``lower`` on ``metrics``" in experiment ``experiment``; for the
    threshold experiment ``higher`` is the paper's chosen row and ``lower`` is ``"*"``: every other row."""

    id: str
    experiment: str
    text: str
    lower: str
    higher: str
    metrics: tuple[str, ...]


CLAIMS = (
    Claim(
        "exploration",
        "ablation",
        "exploration reward raises search success and efficiency (SSR, SSSPL)",
        "baseline",
        "explore",
        ("SSR", "SSSPL"),
    ),
    Claim(
        "distance",
        "ablation",
        "distance reward raises pathfinding efficiency (NSNPL)",
        "baseline",
        "distance",
        ("NSNPL",),
    ),
    Claim(
        "complement-explore",
        "ablation",
        "both rewards beat the exploration reward alone (complementarity)",
        "explore",
        "tsrm",
        METRICS,
    ),
    Claim(
        "complement-distance",
        "ablation",
        "both rewards beat the distance reward alone (complementarity)",
        "distance",
        "tsrm",
        METRICS,
    ),
    Claim(
        "demae-alone", "ablation", "DE-MAE alone brings modest gains over the baseline", "baseline", "demae", METRICS
    ),
    Claim("demae-with-tsrm", "ablation", "DE-MAE with TSRM beats TSRM with ResNet18", "tsrm", "tsrm_demae", METRICS),
    Claim("tsrm-with-demae", "ablation", "DE-MAE with TSRM beats DE-MAE alone", "demae", "tsrm_demae", METRICS),
    Claim(
        "mae-over-resnet",
        "pretraining",
        "standard MAE on the training rooms beats ResNet18",
        "resnet18",
        "mae",
        ("SR", "SPL"),
    ),
    Claim("demae-over-mae", "pretraining", "depth (DE-MAE) beats standard MAE", "mae", "demae", ("SR", "SPL")),
    Claim(
        "crop-hurts", "pretraining", "random cropping in DE-MAE pretraining hurts", "demae_crop", "demae", ("SR", "SPL")
    ),
    Claim(
        "threshold-0.7", "threshold", "C_target = 0.7 is the best dividing point (Fig. 4)", "*", "c70", ("SR", "SPL")
    ),
)


def verdict(diff: float | None, p: float | None, seeds: int = 2) -> str:
    """The verdict of a difference ``higher - lower`` (percentage points), its p-value and the smaller number
    of seeds of the two sides."""
    if diff is None:
        return "not run"
    if p is None:
        return "one seed" if seeds < 2 else "no spread"
    if p < ALPHA and diff != 0:
        return "supported" if diff > 0 else "contradicted"
    return "same sign, n.s." if diff > 0 else "opposite sign, n.s." if diff < 0 else "no difference"


def welch_interval(lower, higher) -> float | None:
    """Half-width of the 95 % confidence interval of ``mean(higher) - mean(lower)`` (Welch-Satterthwaite degrees
    of freedom); None with fewer than two values on a side or no spread."""
    a, b = finite(lower), finite(higher)
    if len(a) < 2 or len(b) < 2:
        return None
    va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    if va + vb == 0:
        return None
    df = (va + vb) ** 2 / (va**2 / (len(a) - 1) + vb**2 / (len(b) - 1))
    return float(student.ppf(0.975, df) * math.sqrt(va + vb))


def _values(rows: dict, rid: str, subset: str, metric: str) -> list[float] | None:
    entry = ((rows.get(rid) or {}).get("metrics", {}).get(subset) or {}).get(metric) or {}
    vals = entry.get("values") or []
    return vals if len(finite(vals)) else None


def _paper_diff(experiment: str, lower: str, higher: str, subset: str, metric: str) -> float | None:
    table = PAPER.get(experiment, {})
    try:
        return round(table[higher][subset][metric] - table[lower][subset][metric], 2)
    except KeyError:
        return None


def _check_pair(c: Claim, rows: dict, lower: str, subset: str, metric: str) -> dict:
    lo, hi = _values(rows, lower, subset, metric), _values(rows, c.higher, subset, metric)
    diff, p = welch(lo, hi) if lo is not None and hi is not None else (None, None)
    mean = lambda v: None if v is None else float(finite(v).mean())  # noqa: E731
    n = [0 if lo is None else len(finite(lo)), 0 if hi is None else len(finite(hi))]
    label = lambda rid: rows.get(rid, {}).get("label", rid)  # noqa: E731
    return {
        "claim": c.id,
        "experiment": c.experiment,
        "text": c.text,
        "lower": lower,
        "higher": c.higher,
        "lower_label": label(lower),
        "higher_label": label(c.higher),
        "subset": subset,
        "metric": metric,
        "lower_mean": mean(lo),
        "higher_mean": mean(hi),
        "n": n,
        "diff": diff,
        "ci95": welch_interval(lo, hi) if diff is not None else None,
        "p": p,
        "paper_diff": _paper_diff(c.experiment, lower, c.higher, subset, metric),
        "verdict": verdict(diff, p, min(n)),
    }


def _check_best(c: Claim, rows: dict, subset: str, metric: str) -> dict:
    """Row ``c.higher`` against every other row with values: the line of the best other row (by mean), with the
    p-value of the whole claim (module docstring: intersection-union when ahead of all, Bonferroni otherwise)."""
    others = {rid: v for rid in rows if rid != c.higher for v in [_values(rows, rid, subset, metric)] if v is not None}
    if not others:
        return _check_pair(c, rows, "(none)", subset, metric)
    best = max(others, key=lambda rid: (float(finite(others[rid]).mean()), rid))
    k = _check_pair(c, rows, best, subset, metric)
    hi = _values(rows, c.higher, subset, metric)
    if k["diff"] is None or k["diff"] == 0 or hi is None or len(others) == 1:
        return k
    tests = [welch(v, hi) for v in others.values()]  # (higher - other, p) per other row
    seeds = min(len(finite(v)) for v in [hi, *others.values()])
    if k["diff"] > 0:  # ahead of every other row: significant only when ahead of each one
        ps = [p for _, p in tests]
        p = None if any(x is None for x in ps) else max(ps)
    else:  # some row ahead: the most significant of them, corrected for the number of rows looked at
        ps = [p for d, p in tests if d < 0 and p is not None]
        p = min(1.0, len(others) * min(ps)) if ps else None
    return dict(k, p=p, verdict=verdict(k["diff"], p, seeds))


def check_claims(results: dict[str, dict], subsets=SUBSETS) -> list[dict]:
    """One dict per (claim, metric, subset) of the experiments in ``results`` (experiment name ->
    ``results.json`` content); claims of experiments not given are left out. For the threshold claim the
    comparison is the chosen row against the best other row by that metric's mean (``lower`` names it), its p
    the one of the whole claim against every other row (module docstring)."""
    out = []
    for c in CLAIMS:
        res = results.get(c.experiment)
        if res is None:
            continue
        rows = {r["row"]: r for r in res["rows"]}
        for subset in subsets:
            for metric in c.metrics:
                out.append(
                    _check_best(c, rows, subset, metric)
                    if c.lower == "*"
                    else _check_pair(c, rows, c.lower, subset, metric)
                )
    return out


def _num(v: float | None, signed: bool = False) -> str:
    return "-" if v is None else (f"{v:+.1f}" if signed else f"{v:.1f}")


def _cell(text: str) -> str:
    """``text`` safe inside a Markdown table cell (a ``|`` would end the cell)."""
    return str(text).replace("|", "\\|")


def claims_markdown(checks: list[dict]) -> str:
    """``checks`` (:func:`check_claims`) as Markdown: per claim a line naming it and its rows, then a table with
    a line per metric and, per subset, the paper's difference, ours (lower -> higher means and difference), the
    p-value and the verdict."""
    if not checks:
        return ""
    subsets = list(dict.fromkeys(k["subset"] for k in checks))
    out = []
    for cid in dict.fromkeys(k["claim"] for k in checks):
        ks = [k for k in checks if k["claim"] == cid]
        first = ks[0]
        wildcard = next(c.lower for c in CLAIMS if c.id == cid) == "*"
        against = "the best other row" if wildcard else _cell(first["lower_label"])
        seeds = sorted({tuple(k["n"]) for k in ks})
        out.append(
            f"**{_cell(first['text'])}**: {_cell(first['higher_label'])} against {against} "
            f"(seeds {', '.join(f'{a}/{b}' for a, b in seeds)})\n"
        )
        head = "| metric | " + " | ".join(f"{s} paper | {s} here | {s} p | {s} verdict" for s in subsets) + " |"
        out += [head, "| --- |" + " ---: | --- | ---: | --- |" * len(subsets)]
        for metric in dict.fromkeys(k["metric"] for k in ks):
            cells = []
            for s in subsets:
                k = next((k for k in ks if k["metric"] == metric and k["subset"] == s), None)
                if k is None:
                    cells.append("- | - | - | -")
                    continue
                p = "-" if k["p"] is None else ("<0.01" if k["p"] < 0.01 else f"{k['p']:.2f}")
                here = (
                    "-"
                    if k["diff"] is None
                    else (f"{_num(k['lower_mean'])} -> {_num(k['higher_mean'])} ({_num(k['diff'], True)})")
                )
                if wildcard and k["diff"] is not None:
                    here = f"{_cell(k['lower_label'])}: " + here
                cells.append(f"{_num(k['paper_diff'], True)} | {here} | {p} | {k['verdict']}")
            out.append(f"| {metric} | " + " | ".join(cells) + " |")
        out.append("")
    return "\n".join(out)


def claims_html(checks: list[dict]) -> str:
    """``checks`` as one HTML table (claim, rows, subset, metric, paper, here, p, verdict), verdicts coloured."""
    colour = {"supported": "#d7f0d2", "contradicted": "#f6d2d2"}
    head = (
        "<tr><th class='l'>claim</th><th class='l'>rows (lower &rarr; higher)</th><th>subset</th><th>metric</th>"
        "<th>paper</th><th>here</th><th>95 % interval</th><th>p</th><th>seeds</th><th>verdict</th></tr>"
    )
    body = []
    for k in checks:
        p = "-" if k["p"] is None else ("&lt;0.01" if k["p"] < 0.01 else f"{k['p']:.2f}")
        here = (
            "-"
            if k["diff"] is None
            else f"{_num(k['lower_mean'])} &rarr; {_num(k['higher_mean'])} ({_num(k['diff'], True)})"
        )
        ci = "-" if k.get("ci95") is None else f"&plusmn;{k['ci95']:.1f}"
        rows = f"{escape(k['lower_label'])} &rarr; {escape(k['higher_label'])}"
        style = f" style='background:{colour[k['verdict']]}'" if k["verdict"] in colour else ""
        body.append(
            f"<tr><td class='l'>{escape(k['text'])}</td><td class='l'>{rows}</td><td>{escape(k['subset'])}</td>"
            f"<td>{escape(k['metric'])}</td><td>{_num(k['paper_diff'], True)}</td><td>{here}</td><td>{ci}</td>"
            f"<td>{p}</td><td>{k['n'][0]}/{k['n'][1]}</td><td{style}>{escape(k['verdict'])}</td></tr>"
        )
    return f"<table>{head}{''.join(body)}</table>"


def summary_line(checks: list[dict]) -> str:
    """How many (claim, metric, subset) checks got each verdict, e.g. ``supported 3, same sign, n.s. 5``."""
    counts: dict[str, int] = {}
    for k in checks:
        counts[k["verdict"]] = counts.get(k["verdict"], 0) + 1
    return ", ".join(f"{v} {n}" for v, n in sorted(counts.items(), key=lambda kv: -kv[1]))


def plot_claims(checks: list[dict], path: str | Path, subset: str = "ALL") -> Path | None:
    """A forest plot of ``checks`` for one subset: per claim and metric our difference (percentage points, dot
    with its 95 % Welch interval; filled when p < :data:`ALPHA`) and the paper's (red cross); None when there is
    nothing to draw."""
    ks = [k for k in checks if k["subset"] == subset and (k["diff"] is not None or k["paper_diff"] is not None)]
    if not ks:
        return None
    fig = Figure(figsize=(7.5, 0.28 * len(ks) + 1.2), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    y = np.arange(len(ks))[::-1]
    for yi, k in zip(y, ks):
        if k["diff"] is not None:
            sig = k["p"] is not None and k["p"] < ALPHA
            ax.errorbar(
                [k["diff"]],
                [yi],
                xerr=[[k["ci95"] or 0.0], [k["ci95"] or 0.0]],
                fmt="o",
                ms=5,
                capsize=2,
                color="#1f77b4",
                mfc="#1f77b4" if sig else "white",
                lw=1.2,
            )
        if k["paper_diff"] is not None:
            ax.plot([k["paper_diff"]], [yi], "x", color="#d62728", ms=6, mew=1.6)
    ax.axvline(0.0, color="0.4", lw=0.8)
    ax.set_yticks(y, [f"{k['higher']} vs {k['lower']}: {k['metric']}" for k in ks], fontsize=7)
    ax.set_xlabel(f"difference, percentage points ({subset}); red x: the paper; filled: p < {ALPHA}", fontsize=8)
    ax.tick_params(axis="x", labelsize=7)
    ax.grid(axis="x", alpha=0.3)
    return atomic_save_figure(fig, path, dpi=110)


def load_results(exp_dir: str | Path) -> dict:
    """``EXP_DIR/results.json``, with a one-line error when it is missing or not an experiment's results."""
    path = Path(exp_dir) / "results.json"
    if not path.is_file():
        raise CommandError(f"{exp_dir}: no results.json (run `tsnav experiment ... --out {exp_dir}` first)")
    res = read_json(path)
    if not isinstance(res, dict) or not isinstance(res.get("rows"), list) or "experiment" not in res:
        raise CommandError(f"{path}: not an experiment's results (no 'rows' / 'experiment')")
    bad = _bad_row(res["rows"])
    if bad is not None:
        raise CommandError(f"{path}: a row without 'row' / 'metrics' ({str(res['rows'][bad])[:60]})")
    return res


def _bad_row(rows: list) -> int | None:
    """The index of the first entry of a results table's ``rows`` that is not a row (a dict with 'row' and
    'metrics'), else None."""
    return next(
        (
            i
            for i, r in enumerate(rows)
            if not isinstance(r, dict) or "row" not in r or not isinstance(r.get("metrics"), dict)
        ),
        None,
    )


def results_under(res: dict, protocol: str | None, exp_dir: str | Path = "") -> dict:
    """An experiment's results under ``protocol`` (None: its own): the main results when it trained under that
    protocol, else the evaluation of the same checkpoints under it (``other_protocols``); one-line error when the
    experiment was not evaluated under it."""
    own = res.get("protocol", DEFAULT_PROTOCOL)
    if protocol is None or protocol == own:
        return res
    others = res.get("other_protocols")
    other = others.get(protocol) if isinstance(others, dict) else None
    if not isinstance(other, dict) or not isinstance(other.get("rows"), list) or _bad_row(other["rows"]) is not None:
        raise CommandError(
            f"{exp_dir}: no results under the {protocol} protocol (trained under {own}; running "
            f"`tsnav experiment` again on this folder evaluates its finished jobs under {protocol})"
        )
    return other


def build_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "experiments",
        nargs="+",
        metavar="EXP_DIR",
        help="experiment folders (`tsnav experiment ... --out EXP_DIR`) holding results.json",
    )
    p.add_argument("--subset", choices=(*SUBSETS, "both"), default="both", help="episode subset(s) to check")
    add_shared(
        p,
        "protocol",
        choices=PROTOCOLS,
        default=None,
        help="success protocol whose results to check (default: each experiment's own, the one it trained "
        "under; the other is read from results.json's other_protocols)",
    )
    p.add_argument("--out", help="also write the table (Markdown) to this file")
    p.add_argument("--json", dest="json_out", help="also write the checks as JSON to this file")
    p.add_argument(
        "--plot",
        help="also draw the checks of the first subset (ALL unless --subset L>=5) as a forest plot "
        "(.png, .pdf or .svg) to this file",
    )


def run(args) -> int:
    for out in (args.out, args.json_out, args.plot):  # checked before anything is written
        if out and Path(out).is_dir():
            raise CommandError(f"{out}: is a folder; give a file name")
    if args.plot and Path(args.plot).suffix.lower() not in (".png", ".pdf", ".svg"):
        raise CommandError(f"{args.plot}: the plot is written as .png, .pdf or .svg")
    results: dict[str, dict] = {}
    for d in args.experiments:
        res = results_under(load_results(d), getattr(args, "protocol", None), d)
        if res["experiment"] in results:
            raise CommandError(f"{d}: a second '{res['experiment']}' experiment (give one folder per experiment)")
        results[res["experiment"]] = res
    subsets = SUBSETS if args.subset == "both" else (args.subset,)
    checks = check_claims(results, subsets)
    if not checks:
        raise CommandError("none of the paper's claims concerns these experiments")
    text = claims_markdown(checks) + f"\n{summary_line(checks)} (alpha {ALPHA}, Welch's t-test)\n"
    print(text, end="")
    if args.out:
        atomic_write_text(Path(args.out), text)
    if args.json_out:
        atomic_write_text(Path(args.json_out), json.dumps(checks, indent=1) + "\n")
    if args.plot and plot_claims(checks, args.plot, subsets[0]) is None:
        print(f"nothing to plot for {subsets[0]}: {args.plot} not written", file=sys.stderr)
    return 0
