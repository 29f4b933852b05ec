"""Zoomed crops at test time for a shipped detector's small objects, measured on a split's rooms (issue 23, analysis).

The shipped detectors see a 128-px frame through a space-to-depth stem, so a remote control or a cell phone covers a
few cells of their grid, and the small classes are where their presence AP is lowest. Here every frame is also cut
into five 64-px crops (the four quadrants and the centre), each enlarged 2x to 128 px (bilinear) and run through the
same detector: an object appears at twice its size. The presence logit of a class is then combined over the frame and
its crops (the largest, optionally with the crops' logits lowered by a margin, since five more looks are five more
chances of a false positive), and turned into a score with the detector's own temperature; boxes stay the plain
frame's. Printed per combination: presence AP (all, and for small objects), reach of C_target over (scene, target)
pairs and false-positive states (:mod:`tsnav.detect.quality`).

    tsnav analyze detector-zoom --data WORLD --split val --shipped learned4 --cache DIR [--margin 0 0.5 1 2]

The logits of every state are kept in ``--cache`` (one ``.npz`` per room), so a second call with other margins reads
no frame. It reads the frames of the split once and runs the detector six times per state (about 6x the cost of a
table). It writes no table (the combination was not worth one: docs/RESULTS.md, "zoomed crops").
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..atomic import atomic_write_json
from ..data.detections import Detections, load_detections
from ..data.reader import list_scenes, load_scene
from ..detect.data import read_images
from ..detect.evaluate import evaluate_detections
from ..detect.quality import subset_report, switch_report
from ..detect.shipped import shipped_detector
from ..detect.train import predict
from ..distributed import set_threads

CROPS = ((0, 0), (0, 1), (1, 0), (1, 1), (0.5, 0.5))  # (row, column) of a crop, in half-frame units


def zoom_crops(img: np.ndarray) -> np.ndarray:
    """``(N, 5, S, S, 3)`` uint8: the five half-size crops of ``(N, S, S, 3)`` frames, each enlarged 2x (bilinear)."""
    n, s = img.shape[0], img.shape[1]
    h = s // 2
    x = torch.from_numpy(np.ascontiguousarray(img)).permute(0, 3, 1, 2).float()
    out = []
    for r, c in CROPS:
        y0, x0 = int(round(r * h)), int(round(c * h))
        crop = x[:, :, y0 : y0 + h, x0 : x0 + h]
        up = torch.nn.functional.interpolate(crop, size=(s, s), mode="bilinear", align_corners=False)
        out.append(up.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy())
    return np.stack(out, axis=1).reshape(n, len(CROPS), s, s, 3)


def scene_logits(det, scene, chunk: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """Plain ``(S, 22)`` and crop ``(S, 5, 22)`` presence logits of every state of ``scene``."""
    plain = np.empty((scene.num_states, 22), np.float32)
    crops = np.empty((scene.num_states, len(CROPS), 22), np.float32)
    for a in range(0, scene.num_states, chunk):
        img = read_images(scene.path, scene.keys[a : a + chunk])
        m = len(img)
        plain[a : a + m] = predict(det.model, img)[0]
        z = zoom_crops(img)
        crops[a : a + m] = predict(det.model, z.reshape(-1, *z.shape[2:]))[0].reshape(m, len(CROPS), 22)
    return plain, crops


def combine(plain: np.ndarray, crops: np.ndarray, margin: float | None) -> np.ndarray:
    """The combined logit: the plain one (``margin`` None) or the largest of the plain one and the crops' lowered by
    ``margin``."""
    if margin is None:
        return plain
    return np.maximum(plain, crops.max(axis=1) - margin)


def scored(table: Detections, logits: np.ndarray, temperature: float) -> Detections:
    return replace(table, scores=(1.0 / (1.0 + np.exp(-logits.astype(np.float64) / temperature))).astype(np.float32))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze detector-zoom", description=__doc__.splitlines()[0]
    )
    p.add_argument("--data", required=True, help="world with the split's rooms at the detector's frame size")
    p.add_argument("--split", default="val")
    p.add_argument("--shipped", default="learned4", help="shipped detector name (tsnav.detect.shipped)")
    p.add_argument("--table", default=None, help="the rooms' stored table of that detector (default: --shipped)")
    p.add_argument("--cache", required=True, type=Path, help="folder for the rooms' logits (read when present)")
    p.add_argument("--margin", type=float, nargs="*", default=[0.0, 0.5, 1.0, 2.0])
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    set_threads(a.threads)
    folders = list_scenes(a.data, a.split)
    if not folders:
        print(f"detector_zoom: --data {a.data}: no {a.split} rooms", file=sys.stderr)
        return 2
    det = shipped_detector(None, a.shipped)
    a.cache.mkdir(parents=True, exist_ok=True)
    scenes, tables, logits = [], [], []
    for f in tqdm(folders, desc=f"{a.split} rooms", unit="room"):
        s = load_scene(f)
        t = load_detections(f, a.table or a.shipped)
        c = a.cache / f"{s.name}.npz"
        if c.exists():
            z = np.load(c)
            pl, cr = z["plain"], z["crops"]
        else:
            pl, cr = scene_logits(det, s)
            tmp = c.with_suffix(".tmp.npz")
            np.savez(tmp, plain=pl, crops=cr)
            tmp.replace(c)
        again = scored(t, pl, det.temperature).scores
        if not np.allclose(again, t.scores, atol=1e-4):
            print(
                f"detector_zoom: {s.name}: the stored table's scores are not this detector's on these frames "
                f"(max difference {np.abs(again - t.scores).max():.3g}); name the right --table",
                file=sys.stderr,
            )
            return 2
        scenes.append(s)
        tables.append(t)
        logits.append((pl, cr))
    out = {"split": a.split, "shipped": a.shipped, "crops": [list(c) for c in CROPS], "rows": {}}
    for margin in [None] + list(a.margin):
        name = "plain" if margin is None else f"zoom max, crops -{margin:g}"
        tabs = [scored(t, combine(pl, cr, margin), det.temperature) for t, (pl, cr) in zip(tables, logits)]
        r = switch_report(scenes, tabs)
        e = evaluate_detections(scenes, tabs)
        sub = subset_report(scenes, tabs)
        small = next(iter(sub.values()))["mean_presence_ap"]
        fp = {f"{t:g}": round(100 * v, 2) for t, v in r.fp_state_any.items()}
        out["rows"][name] = {
            "presence_ap": float(np.nanmean(e.presence_ap)),
            "small_ap": small,
            "reach": [r.reached, r.pairs],
            "episode_reach": [r.episode_reached, r.episode_pairs],
            "fp_states_percent": fp,
        }
        print(
            f"{name:22s} presence AP {np.nanmean(e.presence_ap):.3f} (small {small:.3f}); reach {r.reached}/"
            f"{r.pairs} (episode pairs {r.episode_reached}/{r.episode_pairs}); false-positive states "
            + ", ".join(f"> {k}: {v:.2f} %" for k, v in fp.items()),
            flush=True,
        )
    if a.json:
        atomic_write_json(a.json, out)
    print(json.dumps(out["rows"]["plain"]))
    return 0
