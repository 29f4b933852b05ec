"""Which of a learned detector's errors cost a trained agent (issue 23, analysis): tables that mend one kind of error.

From a learned detector's table L and the oracle's table O of the same rooms (both with 64-wide per-class features),
per state and class, with "in view" the oracle's ground truth (the class has pixels in the frame):

- ``NAME-nofp``:   L, with every class not in view removed (score 0, no label, no box): L without false positives;
- ``NAME-recall``: L, with every class in view given O's score, label and box: the oracle's recall and confidence
  on what is there, L's false positives elsewhere;
- ``NAME-both``:   both: O's scores, labels and boxes with L's per-class features;
- ``NAME-score``:  ``recall``'s scores and labels, L's boxes where L has one (O's where it has none);
- ``NAME-raise``:  as ``score`` but never lowering L's score (the larger of the two in view);
- ``NAME-box``:    L's scores and labels, O's box wherever L keeps a detection of a class in view.

O's confidence falls with the true distance (``tsnav.detect.oracle``), so ``recall`` / ``score`` / ``raise`` also
hand the agent a distance-aware score: read their gains as an upper bound of what recall alone is worth.

``--features oracle`` takes O's features in the mended cells too. An agent trained on L is then evaluated on each
(``tsnav eval --run AGENT --detections NAME-...``) to see which kind of error its figures pay for.

Two comparisons that need no oracle: ``--shift B[,B...]`` writes ``NAME-shiftB``, L with every presence logit raised
by B (:func:`shifted`: a raise of absent classes as much as present ones), and ``--features-from TABLE`` writes
``NAME``: L's scores, labels and boxes with TABLE's per-class features (:func:`with_features`: another detector's
scores read by an agent trained on TABLE's features). ``--flip-average MIRROR`` writes ``NAME``: L's presence logits
averaged with those of MIRROR, the same detector run on the frames flipped left to right (``tsnav detect --mirror``
writes it as ``<name>-mirror``): test-time flip augmentation (:func:`flip_averaged`).

    tsnav analyze table-ablation --data WORLD --learned learned4 --oracle oracle --name ab [--split test]
    tsnav analyze table-ablation --data WORLD --split test --recall learned4,learned4pc   # the figures below
    tsnav analyze table-ablation --data WORLD --learned learned4 --name learned4 --shift 1,2,3
    tsnav analyze table-ablation --data WORLD --learned learned6 --features-from learned4 --name l6s
    tsnav analyze table-ablation --data WORLD --learned learned6 --flip-average learned6-mirror --name learned6-tta

``--recall`` writes nothing: per table, over the cells of the room's possible targets, the share of "near" cells (in
view, the oracle scoring >= 0.7) the table scores >= 0.7 and their mean score, the share of "far" cells (in view,
below that) it scores under the oracle's stand-in, and the share of absent cells above 0.7 (:func:`state_recall`).
With ``--curve B[,B...]`` the same figures for the table with every logit raised by each B (:func:`shifted`): recall
against false positives, the way to tell a detector that ranks better from one that only sits at a lower threshold.
``--by-class`` adds the near cells and their recall per class and per band of the target's visible pixels
(:func:`near_recall_by`), and ``--misses PNG`` draws a sheet of near cells the (first) table misses, for
``--misses-class`` (:func:`near_misses`; the frame with the ground-truth box in red, the table's score, the visible
pixels and the distance under it).

    tsnav analyze table-ablation --data WORLD --split val --recall learned4,learned6 --curve=-1,-0.5,0,0.5,1
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import replace

import numpy as np

from ..data.detections import Detections, detections_path, load_detections, write_detections
from ..data.reader import list_scenes, load_scene
from ..detect.oracle import ground_truth
from ..detect.quality import scene_targets

KINDS = ("nofp", "recall", "both", "score", "raise", "box")


def mend(
    learned: Detections, oracle: Detections, present: np.ndarray, kind: str, oracle_features: bool = False
) -> Detections:
    """``learned`` with one kind of error mended (module docstring); ``present`` ``(S, 22)`` bool in-view flags."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    if learned.scores.shape != oracle.scores.shape or not np.array_equal(learned.keys, oracle.keys):
        raise ValueError("the learned and oracle tables are not of the same states")
    if learned.features.shape != oracle.features.shape:
        raise ValueError(f"feature shapes differ: {learned.features.shape} against {oracle.features.shape}")
    scores, labels = learned.scores.copy(), learned.labels.copy()
    boxes, feats = learned.boxes.copy(), learned.features.copy()
    if kind in ("nofp", "both"):
        off = ~present
        scores[off], labels[off], boxes[off] = 0.0, -1, -1.0
        if oracle_features:
            feats[off] = oracle.features[off]
    if kind in ("recall", "both"):
        on = present
        scores[on], labels[on], boxes[on] = oracle.scores[on], oracle.labels[on], oracle.boxes[on]
        if oracle_features:
            feats[on] = oracle.features[on]
    if kind in ("score", "raise"):
        on = present if kind == "score" else present & (oracle.scores > scores)
        scores[on], labels[on] = oracle.scores[on], oracle.labels[on]
        nobox = on & (learned.labels < 0)
        boxes[nobox] = oracle.boxes[nobox]
        if oracle_features:
            feats[on] = oracle.features[on]
    if kind == "box":
        on = present & (learned.labels >= 0)
        boxes[on] = oracle.boxes[on]
    return replace(
        learned,
        scores=scores,
        labels=labels,
        boxes=boxes,
        features=feats,
        config=dict(learned.config, table_ablation={"kind": kind, "oracle_features": oracle_features}),
    )


def _logit(scores: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Presence logits of ``scores`` (float64, clipped to [eps, 1 - eps])."""
    p = np.clip(scores.astype(np.float64), eps, 1 - eps)
    return np.log(p) - np.log1p(-p)


def _sigmoid(z: np.ndarray) -> np.ndarray:
    return (1.0 / (1.0 + np.exp(-z))).astype(np.float32)


def shifted(table: Detections, b: float, eps: float = 1e-6) -> Detections:
    """``table`` with every presence logit raised by ``b`` (labels and boxes as they were)."""
    return replace(table, scores=_sigmoid(_logit(table.scores, eps) + b), config=dict(table.config, logit_shift=b))


def with_features(table: Detections, features_of: Detections) -> Detections:
    """``table``'s scores, labels and boxes with the per-class features of ``features_of`` (the same states)."""
    if not np.array_equal(table.keys, features_of.keys):
        raise ValueError("the two tables are not of the same states")
    return replace(table, features=features_of.features, config=dict(table.config, features_from=features_of.config))


def flip_averaged(table: Detections, mirror: Detections, eps: float = 1e-6) -> Detections:
    """Test-time flip augmentation: ``table``'s presence logits averaged with those of ``mirror``, the same detector's
    table of the frames flipped left to right (``tsnav detect --mirror``; presence does not depend on the flip).
    Labels, boxes and features stay ``table``'s; a class gets a label where either table kept one."""
    if not np.array_equal(table.keys, mirror.keys) or table.scores.shape != mirror.scores.shape:
        raise ValueError("the table and its mirror table are not of the same states")
    if not mirror.config.get("mirror"):
        raise ValueError("the second table was not made from flipped frames (tsnav detect --mirror)")
    scores = _sigmoid((_logit(table.scores, eps) + _logit(mirror.scores, eps)) / 2)
    labels = np.where((table.labels < 0) & (mirror.labels >= 0), mirror.labels, table.labels)
    return replace(table, scores=scores, labels=labels, config=dict(table.config, flip_average=True))


def _truths(scenes, truths):
    """The scenes' ground truths (:func:`~tsnav.detect.oracle.ground_truth`), or ``truths`` when the caller has them."""
    return truths if truths is not None else [ground_truth(s) for s in scenes]


def state_recall(scenes, tables, oracles, truths=None) -> dict:
    """Per-state recall of the targets in view, against the oracle's stand-in score (module docstring)."""
    t = dict(near=0, near_hit=0, near_sum=0.0, far=0, far_below=0, absent=0, absent_fp=0)
    for s, d, o, g in zip(scenes, tables, oracles, _truths(scenes, truths)):
        present = g.present
        targets = scene_targets(s)[None, :]
        near = present & targets & (o.scores >= 0.7)
        far = present & targets & (o.scores < 0.7)
        absent = ~present & targets
        t["near"] += int(near.sum())
        t["near_hit"] += int((near & (d.scores >= 0.7)).sum())
        t["near_sum"] += float(d.scores[near].sum())
        t["far"] += int(far.sum())
        t["far_below"] += int((far & (d.scores < o.scores)).sum())
        t["absent"] += int(absent.sum())
        t["absent_fp"] += int((absent & (d.scores > 0.7)).sum())
    return {
        "near_cells": t["near"],
        "near_recall": t["near_hit"] / max(t["near"], 1),
        "near_mean_score": t["near_sum"] / max(t["near"], 1),
        "far_cells": t["far"],
        "far_below_oracle": t["far_below"] / max(t["far"], 1),
        "absent_above": t["absent_fp"] / max(t["absent"], 1),
    }


#: Bands of the target's visible pixels (the frame's, at its own size) for :func:`near_recall_by`.
PIXEL_BANDS = (0, 50, 100, 200, 400, 800, 1600)


def near_recall_by(scenes, tables, oracles, truths=None) -> dict:
    """Near cells (as :func:`state_recall`) and those the table scores >= 0.7, per class ``(22,)`` and per band of
    :data:`PIXEL_BANDS` of the ground-truth instance's visible pixels (the last band open above)."""
    out = {k: np.zeros((22,), np.int64) for k in ("class_near", "class_hit")}
    out.update({k: np.zeros((len(PIXEL_BANDS),), np.int64) for k in ("band_near", "band_hit")})
    for s, d, o, g in zip(scenes, tables, oracles, _truths(scenes, truths)):
        near = g.present & scene_targets(s)[None, :] & (o.scores >= 0.7)
        hit = near & (d.scores >= 0.7)
        out["class_near"] += near.sum(0)
        out["class_hit"] += hit.sum(0)
        band = np.searchsorted(PIXEL_BANDS, g.pixels, side="right") - 1
        out["band_near"] += np.bincount(band[near], minlength=len(PIXEL_BANDS))
        out["band_hit"] += np.bincount(band[hit], minlength=len(PIXEL_BANDS))
    return out


def near_misses(scenes, tables, oracles, category: int, per_room: int = 3, seed: int = 0, truths=None) -> list[tuple]:
    """Up to ``per_room`` random (scene, state) near cells of ``category`` per room that the table scores < 0.7:
    ``(scene, state, score, pixels, distance, box)``."""
    rng = np.random.default_rng(seed)
    out = []
    for s, d, o, g in zip(scenes, tables, oracles, _truths(scenes, truths)):
        if not scene_targets(s)[category]:
            continue
        miss = np.flatnonzero(g.present[:, category] & (o.scores[:, category] >= 0.7) & (d.scores[:, category] < 0.7))
        for i in sorted(rng.choice(miss, min(per_room, len(miss)), replace=False)) if len(miss) else []:
            out.append(
                (
                    s,
                    int(i),
                    float(d.scores[i, category]),
                    int(g.pixels[i, category]),
                    float(g.distance[i, category]),
                    g.boxes[i, category],
                )
            )
    return out


def draw_misses(misses, path, columns: int = 6, limit: int = 24, scale: int = 2) -> int:
    """A sheet of up to ``limit`` of :func:`near_misses`' frames (written atomically); returns how many it holds."""
    from PIL import Image, ImageDraw

    from ..detect.data import read_images

    misses = misses[:limit]
    if not misses:
        return 0
    frames = [read_images(m[0].path, m[0].keys[m[1] : m[1] + 1])[0] for m in misses]
    side = frames[0].shape[0] * scale
    rows = (len(frames) + columns - 1) // columns
    sheet = Image.new("RGB", (columns * (side + 4), rows * (side + 16)), "white")
    for k, (m, f) in enumerate(zip(misses, frames)):
        im = Image.fromarray(f).resize((side, side), Image.NEAREST)
        b = m[5] * scale
        ImageDraw.Draw(im).rectangle([b[0], b[1], b[2] + scale - 1, b[3] + scale - 1], outline=(255, 0, 0))
        x, y = (k % columns) * (side + 4), (k // columns) * (side + 16)
        sheet.paste(im, (x, y))
        ImageDraw.Draw(sheet).text(
            (x, y + side + 2), f"{m[0].name} s={m[2]:.2f} px={m[3]} d={m[4]:.1f}m", fill=(0, 0, 0)
        )
    tmp = f"{path}.tmp.png"
    sheet.save(tmp)
    os.replace(tmp, path)
    return len(frames)


def _print_by(name: str, by: dict) -> None:
    from ..constants import TARGET_CATEGORIES

    order = np.argsort(-(by["class_near"] - by["class_hit"]), kind="stable")
    cls = [
        f"{TARGET_CATEGORIES[c]} {100 * by['class_hit'][c] / by['class_near'][c]:.1f} % of {by['class_near'][c]}"
        for c in order
        if by["class_near"][c]
    ]
    print(f"  {name} per class (most misses first): " + "; ".join(cls))
    edges = list(PIXEL_BANDS) + [None]
    bands = [
        f"{edges[i]}-{edges[i + 1] if edges[i + 1] else ''} px "
        f"{100 * by['band_hit'][i] / by['band_near'][i]:.1f} % "
        f"of {by['band_near'][i]}"
        for i in range(len(PIXEL_BANDS))
        if by["band_near"][i]
    ]
    print(f"  {name} per band of visible pixels: " + "; ".join(bands))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze table-ablation", description=__doc__.splitlines()[0]
    )
    p.add_argument("--data", required=True)
    p.add_argument("--learned", default="learned4")
    p.add_argument("--oracle", default="oracle")
    p.add_argument("--name", default="ab")
    p.add_argument("--split", default=None, help="only these rooms (default: every room of --data)")
    p.add_argument("--features", choices=("learned", "oracle"), default="learned")
    p.add_argument(
        "--band",
        default=None,
        metavar="LO,HI",
        help="mend only the in-view cells whose oracle score lies in [LO, HI) (e.g. 0.7,1.01: the ones "
        "the oracle would switch on)",
    )
    p.add_argument("--kinds", default=",".join(KINDS), help="tables to write (default all)")
    p.add_argument(
        "--recall",
        default=None,
        metavar="TABLE[,TABLE...]",
        help="only report these tables' per-state recall against --oracle (writes nothing)",
    )
    p.add_argument(
        "--curve",
        default=None,
        metavar="B[,B...]",
        help="with --recall: the figures of each table with its logits raised by each B (0: as it is; "
        "write --curve=-1,0,1 when the first is negative)",
    )
    p.add_argument(
        "--misses",
        default=None,
        metavar="PNG",
        help="with --recall: draw near cells of --misses-class the first table scores < 0.7 in this PNG",
    )
    p.add_argument("--misses-class", default="Laptop", help="target class of --misses (default Laptop)")
    p.add_argument(
        "--by-class",
        action="store_true",
        help="with --recall: near cells and recall per class and per band of visible pixels",
    )
    p.add_argument(
        "--shift",
        default=None,
        metavar="B[,B...]",
        help="only write --learned with its logits raised by B, as NAME-shiftB (no oracle needed)",
    )
    p.add_argument(
        "--flip-average",
        default=None,
        metavar="MIRROR_TABLE",
        help="only write --learned's presence logits averaged with MIRROR_TABLE's (the same detector on "
        "the flipped frames: `tsnav detect --mirror` writes it as <name>-mirror), as NAME",
    )
    p.add_argument(
        "--features-from",
        default=None,
        metavar="TABLE",
        help="only write --learned's scores with TABLE's per-class features, as NAME (no oracle needed)",
    )
    a = p.parse_args(argv)
    dirs = list_scenes(a.data, a.split) if a.split else list_scenes(a.data)
    if not dirs:
        print(f"table_ablation: --data {a.data}: no rooms", file=sys.stderr)
        return 2
    if (a.curve or a.by_class or a.misses) and not a.recall:
        print(
            "table_ablation: --curve, --by-class and --misses report on --recall TABLE[,TABLE...]; give it",
            file=sys.stderr,
        )
        return 2
    if a.recall:
        try:
            curve = [float(x) for x in a.curve.split(",")] if a.curve else [0.0]
        except ValueError:
            print(f"table_ablation: --curve {a.curve!r}: expected numbers separated by commas", file=sys.stderr)
            return 2
        from ..constants import CATEGORY_INDEX

        if a.misses and a.misses_class not in CATEGORY_INDEX:
            print(f"table_ablation: --misses-class {a.misses_class!r}: not a target class", file=sys.stderr)
            return 2
        category = CATEGORY_INDEX.get(a.misses_class)
        try:
            scenes = [load_scene(d) for d in dirs]
            oracles = [load_detections(d, a.oracle) for d in dirs]
            truths = [ground_truth(s) for s in scenes]  # once, for every table and shift below
            names = [n.strip() for n in a.recall.split(",") if n.strip()]
            for name in names:
                tables = [load_detections(d, name) for d in dirs]
                for b in curve:
                    r = state_recall(scenes, [shifted(t, b) for t in tables] if b else tables, oracles, truths)
                    label = name if not b else f"{name} {b:+g}"
                    print(
                        f"{label}: near cells {r['near_cells']} scoring >= 0.7 {100 * r['near_recall']:.1f} % (mean "
                        f"{r['near_mean_score']:.3f}); far cells {r['far_cells']} under the oracle's score "
                        f"{100 * r['far_below_oracle']:.1f} %; absent target cells above 0.7 "
                        f"{100 * r['absent_above']:.2f} %"
                    )
                if a.by_class:
                    _print_by(name, near_recall_by(scenes, tables, oracles, truths))
                if a.misses and name == names[0]:
                    n = draw_misses(near_misses(scenes, tables, oracles, category, truths=truths), a.misses)
                    print(f"{name}: {n} missed near {a.misses_class} cells drawn in {a.misses}")
        except (OSError, ValueError) as e:
            print(f"table_ablation: {e}", file=sys.stderr)
            return 2
        return 0
    if a.shift or a.features_from or a.flip_average:
        try:
            shifts = [float(x) for x in a.shift.split(",")] if a.shift else []
        except ValueError:
            print(f"table_ablation: --shift {a.shift!r}: expected numbers separated by commas", file=sys.stderr)
            return 2
        try:
            for d in dirs:
                L = load_detections(d, a.learned)
                for b in shifts:
                    name = f"{a.name}-shift{b:g}".replace(".", "p")
                    if not detections_path(d, name).exists():
                        write_detections(d, name, shifted(L, b))
                if a.flip_average and not detections_path(d, a.name).exists():
                    write_detections(d, a.name, flip_averaged(L, load_detections(d, a.flip_average)))
                if a.features_from and not detections_path(d, a.name).exists():
                    write_detections(d, a.name, with_features(L, load_detections(d, a.features_from)))
        except (OSError, ValueError) as e:
            print(f"table_ablation: {e}", file=sys.stderr)
            return 2
        print(f"wrote the tables of {len(dirs)} rooms")
        return 0
    kinds = [k.strip() for k in a.kinds.split(",") if k.strip()]
    bad = [k for k in kinds if k not in KINDS]
    if bad:
        print(f"table_ablation: --kinds: unknown {bad[0]!r} (known: {', '.join(KINDS)})", file=sys.stderr)
        return 2
    band = None
    if a.band:
        try:
            band = tuple(float(x) for x in a.band.split(","))
        except ValueError:
            band = ()
        if len(band) != 2 or not band[0] < band[1]:
            print(f"table_ablation: --band {a.band!r}: expected LO,HI with LO < HI", file=sys.stderr)
            return 2
    n = 0
    for d in dirs:
        todo = [k for k in kinds if not detections_path(d, f"{a.name}-{k}").exists()]
        if not todo:
            continue
        try:
            L, O = load_detections(d, a.learned), load_detections(d, a.oracle)
        except (OSError, ValueError) as e:
            print(f"table_ablation: {e}", file=sys.stderr)
            return 2
        present = ground_truth(load_scene(d)).present
        if band is not None:
            present = present & (O.scores >= band[0]) & (O.scores < band[1])
        for k in todo:
            write_detections(d, f"{a.name}-{k}", mend(L, O, present, k, a.features == "oracle"))
        n += 1
    print(f"wrote {', '.join(f'{a.name}-{k}' for k in kinds)} in {n} of {len(dirs)} rooms")
    return 0
