"""``tsnav report PATH [--out DIR]``: a self-contained HTML page about a run, an evaluation, an experiment or a
whole demo folder.

The page (``DIR/index.html``, default ``PATH/report/``) links only to PNG files and episode clips written beside
it (relative links; no scripts, no external style sheets or fonts). It shows what it finds under ``PATH``:

* **results**: every evaluation folder (``metrics.json`` + ``records.jsonl``) as one row of a table of SR, SPL,
  SSR, SSSPL and NSNPL for ALL episodes and for ``L* >= 5`` (paper IV-A), in percent;
* **experiments** (folders with ``experiment.json``, :mod:`tsnav.pipeline.experiment`): the paper-style table with
  the mean and 95 % t-interval over seeds, learning curves of every job, and the threshold plot (Fig. 4);
* **training runs** (``config.json`` of format ``tsnav-train-run`` and ``log.jsonl``): learning curves - return
  and reward per term, SR / SPL / SSR / SSSPL / NSNPL of the training episodes on the fly, losses;
* **pretraining runs** (``config.json`` with a ``pretrain`` section): the DE-MAE / MAE reconstruction grid;
* **gallery**: for each evaluation, a few successes and failures - top-down map with the path coloured by
  stage, the searched region and the stage switch (:func:`tsnav.tsrm.plot.draw_episode`) beside the agent's
  first-person frames at key steps, and for the first ``video`` of them a clip of the whole episode
  (:mod:`tsnav.eval.video`: an MP4 or GIF beside the page, shown by a ``<video>`` / ``<img>`` element). Trajectories come from ``trajectories.jsonl`` when the evaluation wrote
  one, else the episodes are re-rolled with the same policy and seed (:mod:`tsnav.report.gallery`).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import html
import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..atomic import atomic_save_figure, atomic_write_text
from ..checkpoint_layout import BrokenCheckpoint, read_progress
from ..errors import CommandError
from ..rl.logger import read_log
from .gallery import write_gallery
from ..metrics import METRICS, format_table
from ..pretrain.encoders import describe_pretraining
from ..eval.runner import eval_trajectories
from ..protocol import protocol_line
from .claims import ALPHA, check_claims, claims_html, plot_claims, summary_line
from .tables import quality_line


#: Folders never searched (checkpoints, TensorBoard, earlier reports, scene folders are recognised by content).
SKIP_DIRS = {"checkpoints", "tb", "report", "__pycache__", "stages", "steps", "videos"}
#: Episodes of each gallery shown as a clip by default (``tsnav report --video``).
VIDEOS = 2
MAX_DEPTH = 5


# ---------------------------------------------------------------------------------------------------------
# Discovery
# ---------------------------------------------------------------------------------------------------------


@dataclass
class Found:
    """What :func:`scan` found under a folder (paths, sorted)."""

    experiments: list[Path] = field(default_factory=list)
    train_runs: list[Path] = field(default_factory=list)
    pretrain_runs: list[Path] = field(default_factory=list)
    evals: list[Path] = field(default_factory=list)

    def empty(self) -> bool:
        return not (self.experiments or self.train_runs or self.pretrain_runs or self.evals)


def _read_json(p: Path):
    try:
        return json.loads(p.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def is_train_run(d: Path) -> bool:
    cfg = _read_json(d / "config.json") if (d / "config.json").exists() else None
    return isinstance(cfg, dict) and cfg.get("format") == "tsnav-train-run"


def is_pretrain_run(d: Path) -> bool:
    cfg = _read_json(d / "config.json") if (d / "config.json").exists() else None
    return isinstance(cfg, dict) and "pretrain" in cfg


def is_eval(d: Path) -> bool:
    m = _read_json(d / "metrics.json") if (d / "metrics.json").exists() else None
    return isinstance(m, dict) and isinstance(m.get("metrics"), dict) and "ALL" in m["metrics"]


def scan(root: str | Path) -> Found:
    """Find experiments, training runs, pretraining runs and evaluations under ``root`` (``root`` included).
    The insides of an experiment folder belong to it and are not listed separately."""
    root = Path(root)
    found = Found()

    def visit(d: Path, depth: int) -> None:
        if (d / "experiment.json").exists():
            found.experiments.append(d)
            return
        if (d / "COMPLETE").exists() or (d / "graph.json").exists():
            return  # a scene folder
        if is_train_run(d):
            found.train_runs.append(d)
        elif is_pretrain_run(d):
            found.pretrain_runs.append(d)
        if is_eval(d):
            found.evals.append(d)
        if depth >= MAX_DEPTH:
            return
        try:
            subs = sorted(
                p for p in d.iterdir() if p.is_dir() and not p.name.startswith(".") and p.name not in SKIP_DIRS
            )
        except OSError:
            return
        for p in subs:
            visit(p, depth + 1)

    visit(root, 0)
    return found


# ---------------------------------------------------------------------------------------------------------
# Plots
# ---------------------------------------------------------------------------------------------------------


def _figure(w: float, h: float, ncols: int):
    fig = Figure(figsize=(w, h), layout="constrained")
    FigureCanvasAgg(fig)
    return fig, fig.subplots(1, ncols, squeeze=False)[0]


def _series(log: list[dict], key: str, x: str = "env_steps") -> tuple[np.ndarray, np.ndarray]:
    pts = [(r[x], r[key]) for r in log if isinstance(r.get(key), (int, float)) and isinstance(r.get(x), (int, float))]
    if not pts:
        return np.zeros(0), np.zeros(0)
    a = np.asarray(pts, dtype=np.float64)
    return a[:, 0], a[:, 1]


def plot_learning_curves(log: list[dict], path: str | Path, title: str = "") -> Path | None:
    """Three panels over environment steps: return and reward per term (mean per training episode), the
    metrics of the training episodes on the fly (percent), and the losses. None when the log is empty."""
    if not log:
        return None
    fig, (a0, a1, a2) = _figure(13.5, 3.4, 3)
    terms = sorted({k for r in log for k in r if k.startswith("reward/")})
    for k in ["return"] + terms:
        x, y = _series(log, k)
        if len(x):
            a0.plot(x, y, lw=1.8 if k == "return" else 1.1, label=k.split("/", 1)[-1])
    a0.set_title("reward per episode (by term)", fontsize=9)
    for k in METRICS:
        x, y = _series(log, k)
        if len(x):
            a1.plot(x, 100 * y, lw=1.3, label=k)
    a1.set_title("training episodes, on the fly (%)", fontsize=9)
    for k in ("policy_loss", "value_loss", "entropy"):
        x, y = _series(log, k)
        if len(x):
            a2.plot(x, y, lw=1.2, label=k)
    a2.set_title("losses", fontsize=9)
    for a in (a0, a1, a2):
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=7)
    return _finish_curves(fig, (a0, a1, a2), path, title)


def plot_experiment_curves(series: list[tuple[str, list[dict]]], path: str | Path, title: str = "") -> Path | None:
    """Return and SR of the training episodes over environment steps for several jobs; jobs sharing a label
    (the seeds of one row) share a colour."""
    series = [(lab, log) for lab, log in series if log]
    if not series:
        return None

    labels = list(dict.fromkeys(lab for lab, _ in series))
    cmap = colormaps["tab10"]
    fig, (a0, a1) = _figure(12, 3.6, 2)
    shown = set()
    for lab, log in series:
        c = cmap(labels.index(lab) % 10)
        kw = {"label": lab} if lab not in shown else {}
        shown.add(lab)
        for a, k, s in ((a0, "return", 1.0), (a1, "SR", 100.0)):
            x, y = _series(log, k)
            if len(x):
                a.plot(x, s * y, color=c, lw=1.1, alpha=0.85, **kw)
    a0.set_title("return per training episode", fontsize=9)
    a1.set_title("SR of training episodes (%)", fontsize=9)
    a1.legend(fontsize=7)
    return _finish_curves(fig, (a0, a1), path, title)


def _finish_curves(fig, axes, path: str | Path, title: str) -> Path:
    """Shared look of the learning-curve figures (x: environment steps), then an atomic PNG write."""
    for a in axes:
        a.set_xlabel("environment steps", fontsize=8)
        a.tick_params(labelsize=7)
        a.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    return atomic_save_figure(fig, path, dpi=90)


# ---------------------------------------------------------------------------------------------------------
# HTML
# ---------------------------------------------------------------------------------------------------------

CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:24px auto;max-width:1320px;color:#222;
line-height:1.4;padding:0 16px}
h1{font-size:24px;margin-bottom:4px}h2{border-bottom:2px solid #ddd;padding-bottom:4px;margin-top:36px}
h3{margin-top:24px}.meta{color:#666;font-size:13px}nav a{margin-right:14px;font-size:14px}
table{border-collapse:collapse;margin:10px 0;font-size:13px}th,td{border:1px solid #ccc;padding:4px 8px;
text-align:right}th{background:#f2f2f2}td.l,th.l{text-align:left}tr:nth-child(even) td{background:#fafafa}
img{max-width:100%;border:1px solid #eee}figure{margin:12px 0}figcaption{font-size:13px;color:#444}
.ep{display:flex;gap:12px;align-items:flex-start;flex-wrap:wrap;border-top:1px solid #eee;padding-top:10px}
.ep .map{flex:0 0 520px}.ep .map img{width:520px}.ep .frames{flex:1 1 560px}.ep .clip{margin-top:8px}
.ep .clip video,.ep .clip img{width:512px;height:320px;display:block;border:1px solid #eee}.ok{color:#1a7f37;font-weight:bold}
.bad{color:#b42318;font-weight:bold}pre{background:#f6f6f6;padding:8px;font-size:12px;overflow-x:auto}
.note{font-size:13px;color:#555}
"""


def _e(s) -> str:
    return html.escape(str(s))


def metrics_table_html(rows: list[tuple[str, dict]], subsets: tuple[str, ...] = ("ALL", "L>=5")) -> str:
    """An HTML table with one row per ``(label, summarize() result)``: the success protocol it was counted under
    (:mod:`tsnav.protocol`), then every metric per subset, in percent."""
    head1 = (
        "<tr><th class='l' rowspan='2'>evaluation</th><th rowspan='2'>protocol</th>"
        + "".join(f"<th colspan='{len(METRICS) + 1}'>{_e(s)} (%)</th>" for s in subsets)
        + "</tr>"
    )
    head2 = "<tr>" + "".join("".join(f"<th>{m}</th>" for m in METRICS) + "<th>K</th>" for _ in subsets) + "</tr>"
    body = []
    for label, summ in rows:
        cells = []
        for s in subsets:
            m = summ.get(s, {})
            cells += [
                f"<td>{100 * m[k]:.2f}</td>" if isinstance(m.get(k), (int, float)) else "<td>-</td>" for k in METRICS
            ]
            cells.append(f"<td>{m.get('episodes', '-')}</td>")
        body.append(
            f"<tr><td class='l'>{_e(label)}</td><td>{_e(summ.get('protocol', 'paper'))}</td>{''.join(cells)}</tr>"
        )
    return f"<table>{head1}{head2}{''.join(body)}</table>"


def experiment_table_html(results: dict) -> str:
    """The table of an experiment's ``results.json``: per row, mean and 95 % interval (half-width) over seeds."""
    subsets = results.get("subsets", ["ALL", "L>=5"])
    metrics = results.get("metrics", list(METRICS))
    flags = results.get("flag_columns", [])
    rows = results.get("rows", [])
    head1 = (
        "<tr><th class='l' rowspan='2'>row</th>"
        + "".join(f"<th rowspan='2'>{_e(f)}</th>" for f in flags)
        + "<th rowspan='2'>seeds</th>"
        + "".join(f"<th colspan='{len(metrics)}'>{_e(s)} (%)</th>" for s in subsets)
        + "</tr>"
    )
    head2 = "<tr>" + "".join(f"<th>{_e(m)}</th>" for _ in subsets for m in metrics) + "</tr>"
    body = []
    for r in rows:
        cells = "".join(f"<td>{'&#10003;' if r.get('flags', {}).get(f) else ''}</td>" for f in flags)
        cells += f"<td>{r.get('n', 0)}</td>"
        for s in subsets:
            for m in metrics:
                v = r.get("metrics", {}).get(s, {}).get(m)
                if not v or v.get("mean") is None:
                    cells += "<td>-</td>"
                else:
                    ci = v.get("ci95")
                    cells += f"<td>{v['mean']:.2f}" + (f" &plusmn; {ci:.2f}" if ci is not None else "") + "</td>"
        body.append(f"<tr><td class='l'>{_e(r.get('label', r.get('row')))}</td>{cells}</tr>")
    return f"<table>{head1}{head2}{''.join(body)}</table>"


class _Assets:
    """Copies / writes PNGs into the report folder under unique names."""

    def __init__(self, out: Path):
        self.out = out
        self.used: set[str] = set()

    def name(self, stem: str, ext: str = ".png") -> Path:
        base = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in stem).strip("_") or "img"
        cand, k = base, 1
        while cand + ext in self.used:
            k += 1
            cand = f"{base}_{k}"
        self.used.add(cand + ext)
        return self.out / (cand + ext)

    def copy(self, src: Path, stem: str) -> str:
        dst = self.name(stem, src.suffix or ".png")
        shutil.copyfile(src, dst)
        return dst.name


def _label(path: Path, root: Path) -> str:
    try:
        rel = path.resolve().relative_to(root.resolve())
        return str(rel) if str(rel) != "." else path.name
    except ValueError:
        return str(path)


def _eval_label(d: Path, root: Path) -> str:
    m = _read_json(d / "metrics.json") or {}
    return str(m.get("label") or _label(d, root))


def _train_caption(d: Path) -> str:
    cfg = (_read_json(d / "config.json") or {}).get("train", {})
    parts = [f"{k} {cfg[k]}" for k in ("reward", "features", "algo", "detections", "c_target", "seed") if k in cfg]
    return ", ".join(parts)


def build_report(
    path: str | Path,
    out: str | Path | None = None,
    gallery: int = 6,
    title: str | None = None,
    max_gallery_evals: int = 4,
    progress: bool = False,
    video: int = VIDEOS,
    gallery_evals: list[Path] | None = None,
) -> Path:
    """Write the report of ``path`` into ``out`` (default ``path/report``) and return ``out/index.html``; the
    first ``video`` episodes of each gallery get a clip. The galleries are those of ``gallery_evals`` (evaluation
    folders; those that are not found under ``path`` are left out), else of the first ``max_gallery_evals``
    evaluations found."""
    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such folder")
    found = scan(root)
    if found.empty():
        raise ValueError(f"{root}: nothing to report (no evaluation, training run, pretraining run or experiment)")
    out = Path(out) if out is not None else root / "report"
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("*.png"):
        old.unlink()
    for old in out.glob("gallery_*"):
        if old.is_dir():
            shutil.rmtree(old)
    assets = _Assets(out)
    say = print if progress else (lambda *a, **k: None)
    sections: list[tuple[str, str, str]] = []  # (anchor, heading, html)

    if found.evals:
        sections.append(("results", "Results", _results_html(found.evals, root)))
    for d in found.experiments:
        say(f"report: experiment {d}")
        sections.append(_experiment_section(d, root, assets, gallery, video))
    if found.train_runs:
        sections.append(("training", "Training", _training_html(found.train_runs, root, assets)))
    if found.pretrain_runs:
        sections.append(("pretraining", "Pretraining", _pretrain_html(found.pretrain_runs, root, assets)))
    if found.evals and gallery > 0:
        parts = []
        known = {e.resolve(): e for e in found.evals}
        shown = (
            [known[p.resolve()] for p in map(Path, gallery_evals) if p.resolve() in known]
            if gallery_evals is not None
            else found.evals[:max_gallery_evals]
        )
        for d in shown:
            say(f"report: gallery of {d}")
            parts.append(_gallery_html(d, _eval_label(d, root), assets, gallery, video))
        sections.append(("gallery", "Episode gallery", "".join(parts)))

    title = title or f"tsnav report: {root.resolve().name}"
    nav = "".join(f"<a href='#{a}'>{_e(h)}</a>" for a, h, _ in sections)
    when = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    doc = (
        f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>{_e(title)}</title>"
        f"<style>{CSS}</style></head><body><h1>{_e(title)}</h1>"
        f"<p class='meta'>{_e(root.resolve())} &middot; written {when}</p><nav>{nav}</nav>"
        + "".join(f"<section id='{a}'><h2>{_e(h)}</h2>{b}</section>" for a, h, b in sections)
        + "</body></html>\n"
    )
    index = out / "index.html"
    atomic_write_text(index, doc)
    return index


def _results_html(evals: list[Path], root: Path) -> str:
    """The results of plain evaluations: one metrics table, its note, and per room type under each."""
    rows = []
    for d in evals:
        m = json.loads((d / "metrics.json").read_text())
        rows.append((_eval_label(d, root), m["metrics"]))
    body = metrics_table_html(rows)
    body += (
        "<p class='note'>SR, SPL (Anderson et al.), SSR (share of episodes that entered the pathfinding "
        "stage), SSSPL (searching success weighted by searching path length), NSNPL (pathfinding "
        "efficiency over the episodes that entered that stage); paper IV-A. K = episodes. "
        "L&ge;5: episodes whose optimal path has at least 5 actions. Protocol: paper = Done succeeds "
        "with the target in view within 1.0 m; lineage = the target listed in the 1.5 m visibility map, "
        "start-success episodes kept, SPL and L&ge;5 counted as the lineage's evaluator does "
        "(tsnav.protocol).</p>"
    )
    details = []
    for d in evals:
        m = json.loads((d / "metrics.json").read_text())
        details.append(
            f"<details><summary>{_e(_eval_label(d, root))}: per room type</summary>"
            f"<pre>{_e(format_table(m['metrics'], m.get('trained_protocol')))}</pre></details>"
        )
    return body + "".join(details)


def _training_html(runs: list[Path], root: Path, assets: "_Assets") -> str:
    """Learning curves and a summary line of each training run."""
    parts = []
    for d in runs:
        log = read_log(d)
        lab = _label(d, root)
        png = plot_learning_curves(log, assets.name(f"curves_{lab}"), title=f"{lab}: {_train_caption(d)}")
        last = log[-1] if log else {}
        summary = (
            f"{last.get('update', 0)} updates, {last.get('env_steps', 0):,} environment steps, "
            f"{last.get('episodes', 0):,} episodes, {last.get('seconds', 0) / 60:.1f} min"
            if log
            else "no log lines yet"
        )
        parts.append(
            f"<h3>{_e(lab)}</h3><p class='meta'>{_e(_train_caption(d))}; {_e(summary)}</p>"
            + (
                f"<figure><img src='{png.name}' alt='learning curves'><figcaption>Return and reward per "
                "term of the training episodes, their SR / SPL / SSR / SSSPL / NSNPL on the fly "
                "(training episodes are cut at 30 steps, so these run below the test figures), "
                "and the actor-critic losses.</figcaption></figure>"
                if png
                else ""
            )
        )
    return "".join(parts)


def _pretrain_progress(d: Path) -> dict:
    """:func:`~tsnav.checkpoint_layout.read_progress` of a pretraining run ({} when there is none or it does not
    read); JSON only, so that reports need no torch."""
    try:
        return read_progress(d) or {}
    except BrokenCheckpoint:
        return {}


def _pretrain_html(runs: list[Path], root: Path, assets: _Assets) -> str:
    parts = []
    for d in runs:
        cfg = (_read_json(d / "config.json") or {}).get("pretrain", {})
        prog = _pretrain_progress(d)
        lab = _label(d, root)
        loss = prog.get("loss")
        arch = describe_pretraining(cfg)
        info = (
            f"method {cfg.get('method')}, {arch}, "
            f"{cfg.get('img_size')}px, {prog.get('step', 0)}/{prog.get('total_steps', '?')} steps"
            + (f", last loss {loss:.4f}" if isinstance(loss, (int, float)) else "")
        )
        img = ""
        if (d / "recon.png").exists():
            name = assets.copy(d / "recon.png", f"recon_{lab}")
            img = (
                f"<figure><img src='{name}' alt='reconstructions' style='max-width:640px'><figcaption>"
                "Validation frames, one per row: input, masked input (75 % of patches hidden), RGB "
                "reconstruction (visible patches pasted back), predicted depth (DE-MAE; grey for MAE), "
                "true depth.</figcaption></figure>"
            )
        parts.append(f"<h3>{_e(lab)}</h3><p class='meta'>{_e(info)}</p>{img}")
    return "".join(parts)


def _clip_html(src: str) -> str:
    """An episode clip on the page: MP4 as a muted, looping ``<video>`` with controls; GIF as an image."""
    if src.endswith(".gif"):
        return f"<div class='clip'><img src='{_e(src)}' alt='episode clip'></div>"
    return (
        f"<div class='clip'><video src='{_e(src)}' width='512' height='320' controls muted loop autoplay "
        "playsinline preload='auto'>episode clip (MP4)</video></div>"
    )


def _gallery_html(eval_dir: Path, label: str, assets: _Assets, n: int, videos: int = 0) -> str:
    try:
        bank, records, trajectories, c_target = eval_trajectories(eval_dir)
    except (OSError, ValueError, KeyError, ImportError) as e:
        return f"<h3>{_e(label)}</h3><p class='note'>no gallery: {_e(e)}</p>"
    sub = assets.name(f"gallery_{label}", "")
    sub.mkdir(parents=True, exist_ok=True)
    items = write_gallery(
        bank, records, trajectories, sub, n=n, c_target=c_target, relative_to=assets.out, videos=videos
    )
    parts = [
        f"<h3>{_e(label)}</h3><p class='note'>Blue: searching stage and the searched region RG (union of the "
        "observed trapezoids, clipped to the floor); red: pathfinding stage; gold star: the stage switch "
        f"(first frame with target confidence above C_target = {c_target:g}); green X: instances of the target."
        + (
            " Clips: the first-person frame beside the map at every step, with the action taken and the "
            "target's score against C_target written above them (gold border: the switching frame)."
            if any(it.clip for it in items)
            else ""
        )
        + "</p>"
    ]
    for it in items:
        cls, word = ("ok", "success") if it.success else ("bad", "failure")
        frames = (
            f"<img src='{it.frames_png}' alt='first-person frames'>"
            if it.frames_png
            else "<p class='note'>no first-person frames (no images.hdf5 and no renderer)</p>"
        )
        clip = _clip_html(it.clip) if it.clip else ""  # under the frame strip, beside the map
        parts.append(
            f"<div class='ep'><div class='map'><img src='{it.map_png}' alt='top-down map'></div>"
            f"<div class='frames'><p><span class='{cls}'>{word}</span> {_e(it.caption)}</p>{frames}"
            f"{clip}</div></div>"
        )
    return "".join(parts)


def _experiment_section(d: Path, root: Path, assets: _Assets, gallery: int, video: int = 0) -> tuple[str, str, str]:
    exp = _read_json(d / "experiment.json") or {}
    results = _read_json(d / "results.json") or {}
    name = exp.get("experiment", d.name)
    lab = _label(d, root)
    parts = [
        f"<p class='meta'>{_e(exp.get('description', ''))} Scale {_e(exp.get('scale', '?'))}, "
        f"{_e(exp.get('seeds', '?'))} seed(s); success protocol "
        f"{_e(exp.get('config', {}).get('protocol', 'paper'))}; {_e(lab)}</p>"
    ]
    done = sum(1 for j in exp.get("jobs", []) if (d / j["dir"] / "DONE").exists())
    total = len(exp.get("jobs", []))
    parts.append(f"<p class='meta'>{done} of {total} jobs finished.</p>")
    if results.get("rows"):
        parts.append(experiment_table_html(results))
        parts.append(
            "<p class='note'>Mean over seeds &plusmn; half-width of the 95 % t-interval (none with one "
            "seed), in percent. Files: "
            + ", ".join(f"<code>{_e(f)}</code>" for f in ("table.md", "table.csv", "results.json") if (d / f).exists())
            + ".</p>"
        )
    for p, other in (results.get("other_protocols") or {}).items():
        if not isinstance(other, dict) or not other.get("rows"):
            continue
        short = other.get("incomplete_rows") or []
        parts.append(
            f"<h3>The same agents under the {_e(p)} protocol</h3><p class='meta'>"
            f"{_e(protocol_line(p, other.get('trained_protocol')))}; the checkpoints chosen under "
            f"{_e(other.get('trained_protocol', '?'))}"
            + (f". Fewer seeds than above: {_e(', '.join(short))}" if short else "")
            + ".</p>"
            + experiment_table_html(other)
        )
    checks = check_claims({name: results}) if results.get("rows") else []
    if checks:
        parts.append(
            "<h3>Against the paper's claims</h3><p class='note'>Per claim of the paper, our difference "
            "(percentage points, per-seed means) beside the paper's, with the 95 % Welch interval and p; "
            f"verdicts at p &lt; {ALPHA} ({_e(summary_line(checks))}).</p>" + claims_html(checks)
        )
        png = plot_claims(checks, assets.name(f"claims_{lab}"))
        if png:
            parts.append(
                f"<figure><img src='{png.name}' alt='claims' style='max-width:800px'><figcaption>Our "
                f"differences (dots, 95 % Welch interval; filled when p &lt; {ALPHA}) and the paper's (red "
                "crosses), ALL episodes.</figcaption></figure>"
            )
    quality = results.get("detector_quality") or {}
    if quality:
        parts.append(
            "<p class='note'>Detection tables (agents' input and stage switch; rows marked "
            "&lsquo;oracle switch&rsquo; read the oracle's), measured on the val rooms:</p><ul>"
            + "".join(f"<li>{_e(quality_line(q))}</li>" for q in quality.values())
            + "</ul>"
        )
    if (d / "threshold.png").exists():
        name_png = assets.copy(d / "threshold.png", f"threshold_{lab}")
        parts.append(
            f"<figure><img src='{name_png}' alt='threshold sweep' style='max-width:1100px'><figcaption>"
            "Each metric over the stage-switch threshold C_target on the validation episodes; the red star "
            "marks the best value (paper Fig. 4).</figcaption></figure>"
        )
    pre_dir = Path(exp.get("config", {}).get("pretrain_dir") or d / "pretrain")
    pre_runs = scan(pre_dir).pretrain_runs if pre_dir.is_dir() else []
    if pre_runs:
        parts.append(
            "<h3>Encoders</h3>"
            + _pretrain_html(pre_runs, root, assets).replace("<h3>", "<h4>").replace("</h3>", "</h4>")
        )
    series = []
    for j in exp.get("jobs", []):
        run = d / j["dir"] / "train"
        if run.exists():
            series.append((j.get("label", j["row"]), read_log(run)))
    png = plot_experiment_curves(series, assets.name(f"curves_{lab}"), title=f"{name}: training curves")
    if png:
        parts.append(
            f"<figure><img src='{png.name}' alt='training curves'><figcaption>Training curves of every job "
            "(seeds of a row share a colour).</figcaption></figure>"
        )
    if gallery > 0:
        show = [j for j in exp.get("jobs", []) if (d / j["dir"] / "eval" / "metrics.json").exists()]
        if show:
            j = (
                show[-1]
                if not exp.get("gallery_row")
                else next((x for x in show if x["row"] == exp["gallery_row"]), show[-1])
            )
            parts.append(
                _gallery_html(
                    d / j["dir"] / "eval",
                    f"{name}: {j.get('label', j['row'])} (seed {j.get('seed')})",
                    assets,
                    gallery,
                    video,
                )
            )
    return (f"exp-{name}", f"Experiment: {name}", "".join(parts))


# ---------------------------------------------------------------------------------------------------------
# Command
# ---------------------------------------------------------------------------------------------------------


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", help="a training run, evaluation, experiment or demo folder")
    parser.add_argument("--out", default=None, help="report folder (default: PATH/report)")
    parser.add_argument("--gallery", type=int, default=6, help="episodes shown per evaluation (default 6; 0: none)")
    parser.add_argument("--title", default=None, help="page title")
    parser.add_argument(
        "--video",
        type=int,
        default=VIDEOS,
        metavar="N",
        help=f"episodes of each gallery also shown as a clip (default {VIDEOS}; 0: none)",
    )


def run(args: argparse.Namespace) -> int:
    if args.gallery < 0:
        raise CommandError("--gallery must be >= 0")
    if args.video < 0:
        raise CommandError("--video must be >= 0")
    if not Path(args.path).is_dir():
        raise CommandError(f"{args.path}: no such folder")
    index = build_report(args.path, args.out, gallery=args.gallery, title=args.title, progress=True, video=args.video)
    print(f"wrote {index}")
    return 0
