"""Can the agent's inputs tell a success state from a near miss? For every state of the rooms of a world and every
target category of that room that the named detection table scores above the switch threshold (C_target, 0.7),
the state is a success state or not under the protocol; this script measures how well the detection's own
numbers (score, box size and position, the camera's horizon) separate the two, per distance of the nearest
instance in view.

    tsnav analyze stop-signal --data WORLD --detections learned4 [--compare oracle] [--protocol lineage]
        [--eval EVAL_FOLDER] [--json OUT.json]

Reported per table: the share of confident states that are success states (what "Done at the first confident
frame" scores), the states by distance band, the area under the ROC curve of single features for success
against not, and of a logistic regression on all of them fitted leave-one-room-out (trained on the other rooms,
scored on the held-out room: no room's own figures are fitted). With ``--compare oracle`` the same on the oracle
table (ground-truth boxes and presence) shows how much of the stop decision better boxes would give. With
``--eval`` (a `tsnav eval` output) the held-out model also scores the last state of each of that agent's episodes
that ended in Done: how many of its successful and failed Dones a stop check at that threshold would refuse.

The ground-truth distances and success flags are read for this analysis only; nothing here reaches an agent.
(docs/RESULTS.md, issue 23: "the stop decision".)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_json
from ..constants import C_TARGET, DONE, TARGET_CATEGORIES
from ..data.detections import load_detections
from ..data.reader import list_scenes, load_scene
from ..protocol import LINEAGE, PROTOCOLS

BANDS = ((0.0, 1.0), (1.0, 1.5), (1.5, 2.0), (2.0, 2.5), (2.5, 99.0))
FEATURES = ("score", "area", "height", "width", "bottom", "top", "horizon")


def auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """Area under the ROC curve: the probability that a random positive scores above a random negative (ties
    count half), by ranks."""
    if not len(pos) or not len(neg):
        return float("nan")
    allv = np.concatenate([pos, neg])
    _, inv, counts = np.unique(allv, return_inverse=True, return_counts=True)
    first = np.cumsum(counts) - counts  # 0-based rank of each distinct value's first occurrence
    ranks = (first + (counts + 1) / 2.0)[inv.reshape(-1)]  # ties share their average 1-based rank
    return float((ranks[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2.0) / (len(pos) * len(neg)))


def auc_reference(pos, neg) -> float:
    """Slow reference of :func:`auc`: every pair compared."""
    if not len(pos) or not len(neg):
        return float("nan")
    p = np.asarray(pos, dtype=float)[:, None]
    n = np.asarray(neg, dtype=float)[None, :]
    return float(((p > n).sum() + 0.5 * (p == n).sum()) / (p.size * n.size))


def _row(s, det, ok, seen, i: int, c: int) -> dict:
    """The features of the table's detection of category ``c`` at state ``i`` of scene ``s``, its success flag
    and the distance of the nearest instance in view (None: none in view)."""
    side = float(det.image_size or s.image_size or 1)
    x0, y0, x1, y1 = (det.boxes[i, c] / side).tolist()
    objs = np.flatnonzero(s.object_category == c)
    vis = seen[i, objs]
    dist = float(s.distance[i, objs][vis].min()) if vis.any() else None
    return {
        "room": s.name,
        "category": TARGET_CATEGORIES[c],
        "success": bool(ok[i, c]),
        "dist": dist,
        "score": float(det.scores[i, c]),
        "area": max(x1 - x0, 0) * max(y1 - y0, 0),
        "height": y1 - y0,
        "width": x1 - x0,
        "bottom": y1,
        "top": y0,
        "horizon": float(s.horizon[i]),
    }


def _scene(scene_dir: Path, detections: str, protocol: str):
    s = load_scene(scene_dir)
    det = load_detections(scene_dir, detections)
    if not np.array_equal(det.keys, s.keys):
        raise ValueError(f"{scene_dir}: the {detections} table was written for other states")
    return s, det, s.success_table(protocol), s.visible_at_any_range()


def confident_rows(data: Path, detections: str, protocol: str, threshold: float) -> list[dict]:
    """One row per (room, state, category) with the table's score above ``threshold``, for the categories the
    room holds (:func:`_row`)."""
    rows = []
    for scene_dir in list_scenes(data):
        s, det, ok, seen = _scene(scene_dir, detections, protocol)
        for c in sorted(set(int(v) for v in s.object_category if v >= 0)):
            rows.extend(_row(s, det, ok, seen, int(i), c) for i in np.flatnonzero(det.scores[:, c] > threshold))
    return rows


def done_rows(data: Path, eval_dir: Path, detections: str, protocol: str) -> list[dict]:
    """One row (:func:`_row`) per episode of a `tsnav eval` output that ended in Done, at its last state."""
    from ..eval.runner import read_trajectories

    scenes, rows = {}, []
    for t in read_trajectories(eval_dir / "trajectories.jsonl"):
        if not t.actions or t.actions[-1] != DONE:
            continue
        if t.scene not in scenes:
            scenes[t.scene] = _scene(data / t.scene, detections, protocol)
        s, det, ok, seen = scenes[t.scene]
        rows.append(_row(s, det, ok, seen, s.index(t.keys[-1]), TARGET_CATEGORIES.index(t.target)))
    return rows


def design(rows: list[dict]) -> np.ndarray:
    """The logistic regression's inputs: the features (area as its square root), standardised later, and one
    indicator per category (its own bias)."""
    cats = {c: k for k, c in enumerate(TARGET_CATEGORIES)}
    x = np.zeros((len(rows), len(FEATURES) + len(cats)))
    for r, row in enumerate(rows):
        x[r, : len(FEATURES)] = [row[f] if f != "area" else np.sqrt(row[f]) for f in FEATURES]
        x[r, len(FEATURES) + cats[row["category"]]] = 1.0
    return x


def fit_logistic(x: np.ndarray, y: np.ndarray, l2: float = 1e-3, iters: int = 200) -> np.ndarray:
    """Weights (with a bias last) of an L2-regularised logistic regression, by Newton's method."""
    xb = np.hstack([x, np.ones((len(x), 1))])
    w = np.zeros(xb.shape[1])
    for _ in range(iters):
        p = 1.0 / (1.0 + np.exp(-np.clip(xb @ w, -30, 30)))
        g = xb.T @ (p - y) / len(y) + l2 * w
        h = (xb * (p * (1 - p))[:, None]).T @ xb / len(y) + l2 * np.eye(len(w))
        step = np.linalg.solve(h, g)
        w -= step
        if np.abs(step).max() < 1e-8:
            break
    return w


def leave_one_room_out(rows: list[dict], others: list[dict] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Held-out probability of success for every row of ``rows`` and of ``others`` (default none): each row is
    scored by a model fitted on the rows of ``rows`` from the other rooms."""
    others = others or []
    x, y = design(rows), np.array([r["success"] for r in rows], dtype=float)
    xo = design(others) if others else np.zeros((0, x.shape[1]))
    rooms = np.array([r["room"] for r in rows])
    rooms_o = np.array([r["room"] for r in others])
    out, out_o = np.zeros(len(rows)), np.zeros(len(others))
    for room in np.unique(np.concatenate([rooms, rooms_o])):
        tr, te, te_o = rooms != room, rooms == room, rooms_o == room
        mu, sd = x[tr].mean(0), x[tr].std(0) + 1e-9
        w = fit_logistic((x[tr] - mu) / sd, y[tr])
        for src, sel, dst in ((x, te, out), (xo, te_o, out_o)):
            dst[sel] = 1.0 / (1.0 + np.exp(-(np.hstack([(src[sel] - mu) / sd, np.ones((sel.sum(), 1))]) @ w)))
    return out, out_o


def summary(rows: list[dict], dones: list[dict] | None = None, threshold: float = C_TARGET) -> dict:
    """The figures of the module docstring over ``rows`` (:func:`confident_rows`); with ``dones``
    (:func:`done_rows`), the share of an agent's successful and failed Dones that the held-out model would
    reject at each threshold."""
    y = np.array([r["success"] for r in rows])
    bands = {}
    for lo, hi in BANDS:
        sel = [r for r in rows if r["dist"] is not None and (lo == 0 or lo < r["dist"]) and r["dist"] <= hi]
        bands[f"{lo:g}-{hi:g} m" if hi < 99 else f"> {lo:g} m"] = {
            "states": len(sel),
            "success": int(sum(r["success"] for r in sel)),
        }
    bands["not in view"] = {
        "states": sum(r["dist"] is None for r in rows),
        "success": int(sum(r["success"] for r in rows if r["dist"] is None)),
    }
    aucs = {
        f: auc(np.array([r[f] for r in rows if r["success"]]), np.array([r[f] for r in rows if not r["success"]]))
        for f in FEATURES
    }
    out = {
        "confident_states": len(rows),
        "success_share": float(y.mean()) if len(y) else float("nan"),
        "bands": bands,
        "auc": aucs,
    }
    if len(rows) and 0 < y.sum() < len(y) and len({r["room"] for r in rows}) > 1:
        p, pd = leave_one_room_out(rows, dones)
        out["auc"]["logistic, leave one room out"] = auc(p[y], p[~y])
        yd = np.array([r["success"] for r in dones or []], dtype=bool)
        near = np.array([r["dist"] is not None and 1.5 < r["dist"] <= 2.5 and not r["success"] for r in rows])
        for keep in (0.9, 0.95):  # the threshold that keeps this share of success states
            t = np.quantile(p[y], 1.0 - keep)
            out[f"keeping {keep:.0%} of success states"] = {
                "threshold": float(t),
                "near misses 1.5-2.5 m rejected": float((p[near] < t).mean()) if near.any() else float("nan"),
                "non-success rejected": float((p[~y] < t).mean()),
            }
            if dones:
                out[f"keeping {keep:.0%} of success states"].update(
                    {
                        "agent's successful Dones rejected": int((pd[yd] < t).sum()),
                        "agent's failed Dones rejected": int((pd[~yd] < t).sum()),
                    }
                )
        if dones:
            out["agent's Dones"] = {
                "successful": int(yd.sum()),
                "failed": int((~yd).sum()),
                "failed, below the switch threshold": int(
                    sum(r["score"] <= threshold for r in dones if not r["success"])
                ),
            }
    return out


def show(name: str, s: dict) -> None:
    print(
        f"{name}: {s['confident_states']} confident (state, category) pairs, {100 * s['success_share']:.1f} % are "
        f"success states"
    )
    print(
        "  nearest instance in view: "
        + ", ".join(f"{k} {v['states']} ({v['success']} success)" for k, v in s["bands"].items())
    )
    print("  AUC success vs not: " + ", ".join(f"{k} {v:.3f}" for k, v in s["auc"].items()))
    for k, v in s.items():
        if k.startswith("keeping"):
            ok_r, bad_r = v.get("agent's successful Dones rejected"), v.get("agent's failed Dones rejected")
            extra = f"; the agent's Dones rejected: {ok_r} successful, {bad_r} failed" if bad_r is not None else ""
            print(
                f"  {k}: near misses rejected {100 * v['near misses 1.5-2.5 m rejected']:.1f} %, all non-success "
                f"rejected {100 * v['non-success rejected']:.1f} %{extra}"
            )
    if "agent's Dones" in s:
        d = s["agent's Dones"]
        print(
            f"  the agent's Dones: {d['successful']} successful, {d['failed']} failed "
            f"({d['failed, below the switch threshold']} of them with the target scored at or below the threshold)"
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze stop-signal", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--data", required=True, type=Path, help="a built world (scene folders with states.hdf5)")
    ap.add_argument("--detections", required=True, help="the detection table the agent reads (e.g. learned4)")
    ap.add_argument("--compare", default=None, help="a second table, e.g. oracle")
    ap.add_argument("--protocol", default=LINEAGE, choices=PROTOCOLS)
    ap.add_argument("--threshold", type=float, default=C_TARGET)
    ap.add_argument(
        "--eval",
        type=Path,
        default=None,
        dest="eval_dir",
        help="a `tsnav eval` output (trajectories.jsonl) whose Done states are scored too",
    )
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    if not a.data.is_dir():
        print(f"stop_signal: {a.data} is not a folder", file=sys.stderr)
        return 2
    if a.eval_dir is not None and not (a.eval_dir / "trajectories.jsonl").is_file():
        print(f"stop_signal: {a.eval_dir} has no trajectories.jsonl (a `tsnav eval` output folder)", file=sys.stderr)
        return 2
    result = {
        "data": str(a.data),
        "eval": str(a.eval_dir) if a.eval_dir else None,
        "protocol": a.protocol,
        "threshold": a.threshold,
        "tables": {},
    }
    for name in [a.detections] + ([a.compare] if a.compare else []):
        dones = done_rows(a.data, a.eval_dir, name, a.protocol) if a.eval_dir else None
        s = summary(confident_rows(a.data, name, a.protocol, a.threshold), dones, a.threshold)
        result["tables"][name] = s
        show(name, s)
    if a.json:
        atomic_write_json(a.json, result)
    return 0
