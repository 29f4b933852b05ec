"""Per-class calibration of a learned detector's tables (issue 23, analysis): can the stage switch reach the small
classes' targets by recalibrating, without retraining, and at what cost in false switches?

The shipped detector's scores come from one temperature fitted on all (state, class) pairs of the val rooms; the
pairs below 0.1 decide it. Per class, the top of the curve is under-confident for some classes (Plate, CellPhone,
RemoteControl peak below C_target = 0.7 in rooms where they are in view) and over-confident for others. This script
fits, per class, an affine map of the table's logit (Platt scaling, ``sigmoid(a * logit(s) + b)``, with a weak prior
towards the identity) on the states of the ``--fit-split`` rooms whose room type can ask for that class, and reports
the switch figures of :func:`tsnav.detect.quality.switch_report` before and after, with the fit-split figures
cross-fitted (two folds of rooms: each half's tables recalibrated with the other half's fit) so that they are not
in-sample:

    tsnav analyze class-calibration --data WORLD --from learned4 --fit-split val --json OUT.json \\
        [--name learned4pc]

With ``--name`` the map fitted on all fit-split rooms is applied to every room's table and written under that name
(scores replaced; a class whose new score falls below the detector's ``min_score`` loses its label and box, one that
rises above it keeps none, as the table has no box for it), so that ``tsnav eval`` can run the explorer or an agent
on it. Classes with fewer than ``--min-positives`` in-view states in the fit rooms keep the identity map.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_json
from ..data.detections import detections_path, load_detections, write_detections
from ..data.reader import list_scenes, load_scene
from ..detect.oracle import ground_truth
from ..detect.quality import scene_targets, switch_report

EPS = 1e-6


def logit(s: np.ndarray) -> np.ndarray:
    s = np.clip(np.asarray(s, np.float64), EPS, 1.0 - EPS)
    return np.log(s) - np.log1p(-s)


def sigmoid(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float64)
    e = np.exp(-np.abs(x))  # never overflows
    return np.where(x >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


def fit_platt(z: np.ndarray, y: np.ndarray, prior: float = 1.0, iters: int = 50) -> tuple[float, float]:
    """``(a, b)`` minimising the log loss of ``sigmoid(a z + b)`` against ``y`` plus ``prior/2 * ((a-1)^2 + b^2)``
    (Newton's method; the prior keeps classes with few positives near the identity)."""
    z = np.asarray(z, np.float64)
    y = np.asarray(y, np.float64)
    w = np.array([1.0, 0.0])
    X = np.stack([z, np.ones_like(z)], 1)
    for _ in range(iters):
        p = sigmoid(X @ w)
        g = X.T @ (p - y) + prior * (w - np.array([1.0, 0.0]))
        H = (X * (p * (1 - p))[:, None]).T @ X + prior * np.eye(2)
        step = np.linalg.solve(H, g)
        w = w - step
        if np.abs(step).max() < 1e-9:
            break
    return float(w[0]), float(w[1])


def fit_platt_reference(z, y, prior: float = 1.0) -> tuple[float, float]:
    """Slow reference of :func:`fit_platt`: the same objective minimised by a generic optimiser."""
    from scipy.optimize import minimize

    z = np.asarray(z, np.float64)
    y = np.asarray(y, np.float64)

    def f(w):
        m = w[0] * z + w[1]
        return float(np.sum(np.logaddexp(0.0, m) - y * m) + prior / 2 * ((w[0] - 1) ** 2 + w[1] ** 2))

    r = minimize(
        f, np.array([1.0, 0.0]), method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 20000}
    )
    return float(r.x[0]), float(r.x[1])


def collect(scenes, tables, size: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per class of the scenes' class set (``size`` classes): (logits, in-view flags) over the states of the rooms
    that can ask for it."""
    zs = [[] for _ in range(size)]
    ys = [[] for _ in range(size)]
    for s, d in zip(scenes, tables):
        present = ground_truth(s).present
        tgt = scene_targets(s)
        for c in np.flatnonzero(tgt):
            zs[c].append(logit(d.scores[:, c]))
            ys[c].append(present[:, c])
    return [
        (np.concatenate(z) if z else np.zeros(0), np.concatenate(y) if y else np.zeros(0, bool)) for z, y in zip(zs, ys)
    ]


def fit_maps(scenes, tables, min_positives: int, prior: float, size: int) -> np.ndarray:
    """``(size, 2)`` (the classes of the scenes' class set): per class ``(a, b)``; the identity where the fit rooms
    hold too few positives (or none: an empty fold)."""
    maps = np.tile([1.0, 0.0], (size, 1))
    for c, (z, y) in enumerate(collect(scenes, tables, size)):
        if int(y.sum()) >= min_positives and int((~y).sum()) >= min_positives:
            maps[c] = fit_platt(z, y, prior)
    return maps


def apply_maps(det, maps: np.ndarray, min_score: float):
    """``det`` with its scores mapped per class (labels and boxes dropped below ``min_score``)."""
    z = logit(det.scores)
    new = sigmoid(z * maps[None, :, 0] + maps[None, :, 1]).astype(np.float32)
    low = new < min_score
    labels = np.where(low, -1, det.labels).astype(det.labels.dtype)
    boxes = np.where(low[..., None], -1.0, det.boxes).astype(det.boxes.dtype)
    return replace(det, scores=new, labels=labels, boxes=boxes)


def _figures(rep, categories) -> dict:
    return {
        "reach": [rep.reached, rep.pairs],
        "episode_reach": [rep.episode_reached, rep.episode_pairs],
        "fp_state_target": {str(k): v for k, v in rep.fp_state_target.items()},
        "class_reached": {
            name: [int(rep.class_reached[c]), int(rep.class_pairs[c])]
            for c, name in enumerate(categories)
            if rep.class_pairs[c]
        },
    }


def _line(name: str, f: dict) -> str:
    fp = f["fp_state_target"]
    return (
        f"{name}: reach {f['reach'][0]}/{f['reach'][1]}, episode pairs {f['episode_reach'][0]}/"
        f"{f['episode_reach'][1]}, false-positive states (targets) > 0.5 / 0.7 / 0.9: "
        + " / ".join(f"{100 * fp[k]:.2f}" for k in sorted(fp))
        + " %"
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze class-calibration", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--data", required=True, type=Path, help="a built world")
    ap.add_argument("--from", dest="source", default="learned4", help="the tables to recalibrate")
    ap.add_argument("--fit-split", default="val", help="rooms the maps are fitted on (default val)")
    ap.add_argument("--report-split", action="append", default=[], help="also report these splits (e.g. test)")
    ap.add_argument("--min-positives", type=int, default=50)
    ap.add_argument("--prior", type=float, default=1.0)
    ap.add_argument("--min-score", type=float, default=0.05)
    ap.add_argument("--name", default=None, help="write the recalibrated tables of every room under this name")
    ap.add_argument(
        "--write-split",
        action="append",
        default=[],
        help="with --name: write the tables of these splits only (repeatable; default every room)",
    )
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    if a.name is not None and a.name == a.source:
        print("class_calibration: --name must differ from --from", file=sys.stderr)
        return 2
    try:
        fit_dirs = list_scenes(a.data, a.fit_split)
        if not fit_dirs:
            raise ValueError(f"{a.data}: no {a.fit_split} rooms")
        fit_scenes = [load_scene(p) for p in fit_dirs]
        fit_tables = [load_detections(p, a.source) for p in fit_dirs]
    except (OSError, ValueError) as e:
        print(f"class_calibration: {e}", file=sys.stderr)
        return 2
    classes = fit_scenes[0].class_set
    if any(t.class_set != classes.name for t in fit_tables):
        print(f"class_calibration: {a.source}'s tables are not for class set {classes.name}", file=sys.stderr)
        return 2
    out = {
        "source": a.source,
        "fit_split": a.fit_split,
        "class_set": classes.name,
        "prior": a.prior,
        "min_positives": a.min_positives,
    }
    out[f"{a.fit_split}_before"] = _figures(switch_report(fit_scenes, fit_tables), classes.categories)
    print(_line(f"{a.fit_split}, {a.source}", out[f"{a.fit_split}_before"]))
    folds = [list(range(0, len(fit_dirs), 2)), list(range(1, len(fit_dirs), 2))]
    crossed = [None] * len(fit_dirs)
    for k, fold in enumerate(folds):
        other = folds[1 - k]
        maps = fit_maps(
            [fit_scenes[i] for i in other], [fit_tables[i] for i in other], a.min_positives, a.prior, classes.size
        )
        for i in fold:
            crossed[i] = apply_maps(fit_tables[i], maps, a.min_score)
    out[f"{a.fit_split}_crossfit"] = _figures(switch_report(fit_scenes, crossed), classes.categories)
    print(_line(f"{a.fit_split}, per-class maps (two folds, each fitted on the other)", out[f"{a.fit_split}_crossfit"]))
    maps = fit_maps(fit_scenes, fit_tables, a.min_positives, a.prior, classes.size)
    out["maps"] = {
        name: [round(float(maps[c, 0]), 4), round(float(maps[c, 1]), 4)] for c, name in enumerate(classes.categories)
    }
    for split in a.report_split:
        dirs = list_scenes(a.data, split)
        sc = [load_scene(p) for p in dirs]
        tb = [load_detections(p, a.source) for p in dirs]
        out[f"{split}_before"] = _figures(switch_report(sc, tb), classes.categories)
        after = [apply_maps(t, maps, a.min_score) for t in tb]
        out[f"{split}_after"] = _figures(switch_report(sc, after), classes.categories)
        print(_line(f"{split}, {a.source}", out[f"{split}_before"]))
        print(_line(f"{split}, per-class maps fitted on {a.fit_split}", out[f"{split}_after"]))
    if a.name:
        dirs = [p for sp in a.write_split for p in list_scenes(a.data, sp)] if a.write_split else list_scenes(a.data)
        for p in dirs:
            if not detections_path(p, a.name).exists():
                d = load_detections(p, a.source)
                d = apply_maps(d, maps, a.min_score)
                write_detections(
                    p,
                    a.name,
                    replace(
                        d,
                        config=dict(
                            d.config,
                            class_calibration={"from": a.source, "fit_split": a.fit_split, "maps": out["maps"]},
                        ),
                    ),
                )
        print(f"wrote {a.name} tables in {a.data}")
    if a.json:
        atomic_write_json(a.json, out)
    print(json.dumps(out["maps"]))
    return 0
