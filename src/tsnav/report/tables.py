"""Tables and plots of an experiment: mean and 95 % t-interval over seeds, ``results.json`` content, the
Markdown and long-format CSV tables, and the threshold figure (paper Fig. 4)."""

from __future__ import annotations

import csv
import io
import math
import warnings
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy.stats import t, ttest_ind

from ..atomic import atomic_save_figure


SUBSETS = ("ALL", "L>=5")
"""Episode subsets of every table: all episodes, and those with optimal length of at least 5 actions."""


def finite(values) -> np.ndarray:
    """The finite, non-None entries of ``values`` as float64 (missing seeds and undefined metrics dropped)."""
    return np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=np.float64)


def mean_ci(values) -> tuple[float | None, float | None]:
    """Mean and half-width of the 95 % confidence interval of the mean (Student t, n-1 degrees of freedom);
    half-width None with fewer than two values, both None with none."""
    v = finite(values)
    if len(v) == 0:
        return None, None
    if len(v) == 1:
        return float(v[0]), None

    half = float(t.ppf(0.975, len(v) - 1) * v.std(ddof=1) / math.sqrt(len(v)))
    return float(v.mean()), half


def aggregate(rows: list, per_row: dict[str, list[dict]], metrics: list[str], flags: list[str]) -> dict:
    """``results.json`` content: per row and subset and metric, the per-seed values (percent), mean and 95 %
    half-width. ``per_row[row.id]`` holds the :func:`~tsnav.metrics.summarize` results of its seeds."""
    out_rows = []
    for r in rows:
        sums = per_row.get(r.id, [])
        ms = {}
        for s in SUBSETS:
            ms[s] = {}
            for m in metrics:
                vals = [100.0 * x[s][m] for x in sums if s in x]
                mean, half = mean_ci(vals)
                ms[s][m] = {"mean": mean, "ci95": half, "values": vals}
        out_rows.append(
            {
                "row": r.id,
                "label": r.label,
                "flags": r.flags,
                "c_target": r.c_target,
                "encoder": r.encoder,
                "reward": r.reward,
                "detections": getattr(r, "detections", None),
                "n": len(sums),
                "metrics": ms,
            }
        )
    return {"subsets": list(SUBSETS), "metrics": metrics, "flag_columns": flags, "rows": out_rows}


def welch(a, b) -> tuple[float | None, float | None]:
    """Difference of means ``mean(b) - mean(a)`` and the two-sided p-value of Welch's t-test (unequal
    variances); p None with fewer than two values on either side or no spread at all."""
    a, b = finite(a), finite(b)
    if len(a) == 0 or len(b) == 0:
        return None, None
    diff = float(b.mean() - a.mean())
    if len(a) < 2 or len(b) < 2 or (a.var(ddof=1) == 0 and b.var(ddof=1) == 0):
        return diff, None
    with warnings.catch_warnings():  # scipy warns of precision loss when seeds agree to many digits; p stays valid
        warnings.simplefilter("ignore", RuntimeWarning)
        return diff, float(ttest_ind(b, a, equal_var=False).pvalue)


def welch_against(results: dict, baseline: str) -> dict:
    """Every other row against row ``baseline``: per subset and metric, the difference of the per-seed means
    (percentage points) and Welch's p-value. ``{}`` when the baseline row is not in the results."""
    rows = {r["row"]: r for r in results["rows"]}
    if baseline not in rows:
        return {}
    base = rows[baseline]
    out = {}
    for r in results["rows"]:
        if r["row"] == baseline:
            continue
        out[r["row"]] = {
            s: {
                m: dict(zip(("diff", "p"), welch(base["metrics"][s][m]["values"], r["metrics"][s][m]["values"])))
                for m in results["metrics"]
            }
            for s in results["subsets"]
        }
    return {"baseline": baseline, "rows": out}


def welch_markdown(results: dict, subset: str = "ALL") -> str:
    """The :func:`welch_against` part of ``results`` (``results["welch"]``) as a Markdown table for one subset:
    ``+diff (p)`` per metric, or "" when there is none."""
    w = results.get("welch") or {}
    if not w.get("rows"):
        return ""
    labels = {r["row"]: r["label"] for r in results["rows"]}
    metrics = results["metrics"]
    lines = [
        f"| {subset}: row vs {labels.get(w['baseline'], w['baseline'])} | " + " | ".join(metrics) + " |",
        "| --- |" + " ---: |" * len(metrics),
    ]

    def cell(v):
        if v["diff"] is None:
            return "-"
        p = "-" if v["p"] is None else ("<0.01" if v["p"] < 0.01 else f"{v['p']:.2f}")
        return f"{v['diff']:+.1f} (p {p})"

    for rid, by_subset in w["rows"].items():
        lines.append(f"| {labels.get(rid, rid)} | " + " | ".join(cell(by_subset[subset][m]) for m in metrics) + " |")
    return "\n".join(lines) + "\n"


def _fmt(v: dict) -> str:
    if v.get("mean") is None:
        return "-"
    return f"{v['mean']:.2f}" + (f" ± {v['ci95']:.2f}" if v.get("ci95") is not None else "")


def markdown_table(results: dict) -> str:
    """A Markdown table: row label, check-mark columns, seeds, then ``subset metric`` columns (mean ± 95 %)."""
    flags, subsets, metrics = results["flag_columns"], results["subsets"], results["metrics"]
    head = ["row"] + flags + ["seeds"] + [f"{s} {m}" for s in subsets for m in metrics]
    lines = [
        "| " + " | ".join(head) + " |",
        "|" + "|".join([" --- "] * (1 + len(flags) + 1) + [" ---: "] * (len(subsets) * len(metrics))) + "|",
    ]
    for r in results["rows"]:
        cells = [r["label"]] + ["✓" if r["flags"].get(f) else "" for f in flags] + [str(r["n"])]
        cells += [_fmt(r["metrics"][s][m]) for s in subsets for m in metrics]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


CSV_FIELDS = ("row", "label", "subset", "metric", "mean", "ci95", "ci_low", "ci_high", "n_seeds", "values")


def csv_table(results: dict) -> str:
    """Long-format CSV, one line per (row, subset, metric): mean, 95 % half-width and bounds, seeds, values."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_FIELDS, lineterminator="\n")
    w.writeheader()
    for r in results["rows"]:
        for s in results["subsets"]:
            for m in results["metrics"]:
                v = r["metrics"][s][m]
                mean, half = v["mean"], v["ci95"]
                w.writerow(
                    {
                        "row": r["row"],
                        "label": r["label"],
                        "subset": s,
                        "metric": m,
                        "mean": "" if mean is None else f"{mean:.4f}",
                        "ci95": "" if half is None else f"{half:.4f}",
                        "ci_low": "" if half is None else f"{mean - half:.4f}",
                        "ci_high": "" if half is None else f"{mean + half:.4f}",
                        "n_seeds": r["n"],
                        "values": " ".join(f"{x:.4f}" for x in v["values"]),
                    }
                )
    return buf.getvalue()


def _episode_reach(q: dict) -> str:
    """`` (a/b of the pairs episodes ask for)`` when the record has the episode reach (records written before it
    do not)."""
    if "episode_pairs" not in q:
        return ""
    return f" ({q['episode_reached']}/{q['episode_pairs']} of the pairs episodes ask for)"


def quality_line(q: dict) -> str:
    """One line of a :func:`detection_quality` record (percent)."""
    fp = " / ".join(f"{100 * v:.2f}" for v in q["fp_states"].values())
    return (
        f"detections_{q['name']} on {q['scenes']} {q['split']} rooms: presence AP {q['presence_ap']:.3f}, box "
        f"AP@0.5 {q['box_ap50']:.3f}, ECE {100 * q['ece']:.2f} %, reach of {q['c_target']:g}: {q['reached']}/"
        f"{q['pairs']} pairs ({100 * q['reach']:.1f} %){_episode_reach(q)}, false-positive states > "
        f"{' / '.join(q['fp_states'])}: {fp} %"
    )


def plot_threshold(results: dict, path: str | Path) -> Path | None:
    """Paper Fig. 4: each metric over C_target (mean with 95 % interval; ALL solid, L>=5 dashed), the best
    mean of each metric (ALL) marked with a red star."""
    rows = [r for r in results["rows"] if r["n"] > 0]
    if not rows:
        return None

    metrics = results["metrics"]
    fig = Figure(figsize=(3.1 * len(metrics), 3.2), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(metrics), squeeze=False)[0]
    xs = np.array([r["c_target"] for r in rows])
    for ax, m in zip(axes, metrics):
        for s, style in zip(SUBSETS, ("-", "--")):
            mean = np.array(
                [np.nan if r["metrics"][s][m]["mean"] is None else r["metrics"][s][m]["mean"] for r in rows]
            )
            half = np.array([0.0 if r["metrics"][s][m]["ci95"] is None else r["metrics"][s][m]["ci95"] for r in rows])
            ax.errorbar(
                xs,
                mean,
                yerr=half,
                fmt="o" + style,
                ms=3,
                lw=1.3,
                capsize=2,
                alpha=1.0 if s == "ALL" else 0.55,
                color="#1f77b4",
                label=s,
            )
            if s == "ALL" and np.isfinite(mean).any():
                b = int(np.nanargmax(mean))
                ax.scatter([xs[b]], [mean[b]], marker="*", s=220, color="red", zorder=5, label=f"best {xs[b]:.1f}")
        ax.set_title(m, fontsize=10)
        ax.set_xlabel("C_target", fontsize=8)
        ax.set_xticks(np.round(np.arange(0.1, 0.91, 0.2), 1))
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    axes[0].set_ylabel("%", fontsize=8)
    return atomic_save_figure(fig, path, dpi=100)
