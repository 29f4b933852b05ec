"""How soon must the stage switch recognise the target (issue 46, analysis): the searching stage against the switch's reach.

The searching stage ends when the detector scores the target above C_target (paper III-B). In a large apartment the
target often shows in the frame long before it is near, as a few pixels; whether the switch fires then decides how
long the search lasts. This analysis measures that with tables whose reach is known:

- ``presence-N`` (one per N of ``--min-pixels``): the oracle's table (:mod:`tsnav.detect.oracle`) with every score
  set to 1 where an instance of the class shows at least N visible pixels in the frame (:func:`presence_table`; N may
  be below the scene's ``min_pixels``, the ground truth's presence rule) and 0 elsewhere: a detector that recognises every target from N pixels on and never fires falsely;
- the oracle's own table, whose score falls with distance and size;
- ``--detections TABLE`` at each ``--c-target``: a learned detector's table.

The scripted explorer (``tsnav eval --policy explorer``) is evaluated on each on the same episode list. Once switched
it walks the true shortest path to the target, so for the presence tables its figures are what recognising the
target from N pixels on is worth to a policy that walks perfectly afterwards. A learned table's false positives cost
the explorer only the search they cut short (it walks to the true target anyway), so its figures at a low C_target
flatter the table: read them beside the table's per-cell precision and recall (:func:`cell_precision_recall`, over
each room's target classes: precision the share of cells above the threshold whose class shows in the frame, recall
the share of cells showing at least ``--recall-pixels`` pixels that score above it).

    tsnav analyze switch-reach --data WORLD --episodes VAL.json --detections robothor2 --min-pixels 1,10,40,160 \\
        --c-target 0.5,0.7 --work DIR --out reach.json

The tables are written into the world's scenes (``detections_presence-N.hdf5``) and the evaluations into ``--work``.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_text
from ..data.detections import Detections, load_detections, write_detections
from ..data.reader import Scene, load_scene
from ..detect.quality import scene_targets
from ..errors import CommandError


def class_pixels(scene: Scene) -> np.ndarray:
    """``(S, C)`` int32: per state and class, the most visible pixels any instance of the class shows (0 when none;
    below the scene's ``min_pixels`` too, unlike the ground truth's presence)."""
    out = np.zeros((scene.num_states, scene.num_categories), np.int32)
    px = np.maximum(scene.pixels, 0)
    for c in range(scene.num_categories):
        cols = np.flatnonzero(scene.object_category == c)
        if len(cols):
            out[:, c] = px[:, cols].max(1)
    return out


def presence_table(oracle: Detections, pixels: np.ndarray, min_pixels: int) -> Detections:
    """``oracle`` with every score 1 where the class shows at least ``min_pixels`` visible pixels (``pixels``:
    :func:`class_pixels`) and 0 elsewhere; the class's label where it scores 1, the oracle's box where it has one
    (features as the oracle's)."""
    if min_pixels < 1:
        raise ValueError(f"min_pixels must be >= 1, got {min_pixels}")
    if oracle.scores.shape != pixels.shape:
        raise ValueError(f"the table's {oracle.scores.shape} cells are not the scene's {pixels.shape}")
    on = pixels >= min_pixels
    classes = np.broadcast_to(np.arange(pixels.shape[1]), pixels.shape)
    return replace(
        oracle,
        scores=on.astype(np.float32),
        labels=np.where(on, classes, -1).astype(oracle.labels.dtype),
        boxes=np.where(on[..., None], oracle.boxes, -1.0).astype(oracle.boxes.dtype),
        detector="presence",
        config={"presence": {"min_pixels": int(min_pixels), "from": "the renderer's visible pixel counts"}},
        fingerprint=f"presence-{int(min_pixels)}-{oracle.fingerprint}",
    )


def cell_precision_recall(
    scenes: list[Scene], tables: list[Detections], thresholds, recall_pixels: int = 10
) -> list[dict]:
    """Per threshold t, over every state and each room's target classes: ``precision`` the share of cells scored
    above t whose class shows at least one pixel, ``recall`` the share of cells showing at least ``recall_pixels``
    pixels that are scored above t (``cells_above``, ``cells_showing`` the counts)."""
    pix = [class_pixels(s) for s in scenes]
    out = []
    for t in thresholds:
        above = true_above = showing = showing_hit = 0
        for s, d, px in zip(scenes, tables, pix):
            targets = scene_targets(s)[None, :]
            fired = (d.scores > t) & targets
            big = (px >= recall_pixels) & targets
            above += int(fired.sum())
            true_above += int((fired & (px > 0)).sum())
            showing += int(big.sum())
            showing_hit += int((big & fired).sum())
        out.append(
            {
                "threshold": float(t),
                "precision": true_above / above if above else None,
                "recall": showing_hit / showing if showing else None,
                "cells_above": above,
                "cells_showing": showing,
            }
        )
    return out


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def _row(rule: str, metrics: dict, outcomes: dict | None) -> dict:
    m = metrics["metrics"]
    return {
        "switch": rule,
        "episodes": m["ALL"]["episodes"],
        "metrics": {s: dict(m[s]) for s in ("ALL", "L>=5")},
        "never_switched": (outcomes or {}).get("counts", {}).get("step limit, never switched"),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze switch-reach", description=__doc__.splitlines()[0]
    )
    p.add_argument("--data", required=True, help="world folder holding the episode list's scenes and oracle tables")
    p.add_argument("--episodes", required=True, help="episode list (tsnav episodes / tsnav thor challenge-episodes)")
    p.add_argument("--detections", default=None, help="a learned table to read beside the presence tables")
    p.add_argument("--c-target", default="0.7", help="thresholds of --detections (comma-separated; default 0.7)")
    p.add_argument("--min-pixels", default="1,10,40,160", help="N of the presence-N tables (comma-separated)")
    p.add_argument("--recall-pixels", type=int, default=10, help="pixels a cell must show to count in recall")
    p.add_argument("--max-steps", type=int, default=100)
    p.add_argument("--work", required=True, help="folder of the evaluations")
    p.add_argument("--out", required=True, help="results JSON to write")
    args = p.parse_args(argv)
    from ..eval.runner import evaluate_to_folder
    from ..sim.episodes import read_episodes

    data, work = Path(args.data), Path(args.work)
    if not data.is_dir():
        raise CommandError(f"--data {data}: no such folder")
    episodes, meta = read_episodes(args.episodes)
    names = sorted({e.scene for e in episodes})
    missing = [n for n in names if not (data / n).is_dir()]
    if missing:
        raise CommandError(f"--data {data} lacks {len(missing)} scenes of the episode list, e.g. {missing[0]}")
    pixels = [int(x) for x in _floats(args.min_pixels)]
    thresholds = _floats(args.c_target)
    scenes = [load_scene(data / n) for n in names]
    oracles = [load_detections(s.path, "oracle") for s in scenes]
    for s, o in zip(scenes, oracles):
        px = class_pixels(s)
        for n in pixels:
            write_detections(s.path, f"presence-{n}", presence_table(o, px, n))

    def explorer(table: str, c: float, tag: str) -> dict:
        folder = work / tag
        evaluate_to_folder(
            folder, data, args.episodes, "explorer", detections=table, c_target=c, max_steps=args.max_steps
        )
        metrics = json.loads((folder / "metrics.json").read_text())
        outcomes = json.loads((folder / "outcomes.json").read_text()) if (folder / "outcomes.json").exists() else None
        return metrics, outcomes

    rows = []
    for n in pixels:
        rows.append(_row(f"target shows >= {n} px", *explorer(f"presence-{n}", 0.5, f"presence-{n}")))
        print(f"presence-{n}: SR {100 * rows[-1]['metrics']['ALL']['SR']:.2f}", flush=True)
    rows.append(_row("oracle score > 0.7", *explorer("oracle", 0.7, "oracle-0.7")))
    precision = []
    if args.detections:
        for c in thresholds:
            rows.append(
                _row(f"{args.detections} score > {c:g}", *explorer(args.detections, c, f"{args.detections}-{c:g}"))
            )
        learned = [load_detections(s.path, args.detections) for s in scenes]
        precision = cell_precision_recall(scenes, learned, thresholds, args.recall_pixels)
    result = {
        "format": "tsnav-switch-reach",
        "episodes_file": str(Path(args.episodes).resolve()),
        "protocol": meta.get("protocol"),
        "image_size": int(scenes[0].image_size),
        "policy": "scripted explorer (the true shortest path once switched)",
        "max_steps": args.max_steps,
        "rows": rows,
        "table": args.detections,
        "recall_pixels": args.recall_pixels,
        "cells": precision,
    }
    atomic_write_text(Path(args.out), json.dumps(result, indent=1) + "\n")
    for r in rows:
        a = r["metrics"]["ALL"]
        print(f"{r['switch']:<32} SR {100 * a['SR']:6.2f}  SPL {100 * a['SPL']:6.2f}  SSR {100 * a['SSR']:6.2f}")
    for c in precision:
        print(f"{args.detections} > {c['threshold']:g}: precision {c['precision']:.3f}, recall {c['recall']:.3f}")
    print(f"wrote {args.out}")
    return 0
