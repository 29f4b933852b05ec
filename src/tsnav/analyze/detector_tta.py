"""Flip test-time augmentation of a shipped detector, measured on a split's rooms (analysis; not part of the tool).

For every state, the detector's presence logits on the frame and on its mirror image are combined, either
averaged (``flip-mean``) or the smaller taken (``flip-min``: a class must be seen in both), then turned into scores
with the detector's own temperature; boxes are the plain frame's. Printed beside the plain table: presence AP
(mean over the 22 classes), reach of C_target over (scene, target) pairs and false-positive states
(:mod:`tsnav.detect.quality`), as ``python -m tsnav.detect.quality`` reports them.

    tsnav analyze detector-tta --data WORLD --split val --shipped learned4 [--threads 1]

The plain row is the rooms' stored table (``--table``), checked against the detector's own scores on the frames.
It reads the frames of every state of the split once (about 15 minutes for the 20 val rooms at 128 px on one
thread of this machine) and writes nothing.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
from tqdm import tqdm

from ..data.detections import Detections, load_detections
from ..data.reader import list_scenes, load_scene
from ..detect.data import read_images
from ..detect.evaluate import evaluate_detections
from ..distributed import set_threads
from ..detect.learned import LearnedDetector
from ..detect.quality import switch_report
from ..detect.shipped import shipped_detector
from ..detect.train import predict


def tables(det: LearnedDetector, scene, plain: Detections, chunk: int = 2048) -> dict[str, Detections]:
    """The plain, flip-mean and flip-min tables of one scene (scores only differ; boxes are the plain ones).
    ``plain`` is the scene's stored table of the same detector: its scores must be the frames' own."""
    lg = np.empty((scene.num_states, plain.scores.shape[1]), np.float64)
    lf = np.empty_like(lg)
    for a in range(0, scene.num_states, chunk):
        img = read_images(scene.path, scene.keys[a : a + chunk])
        lg[a : a + len(img)] = predict(det.model, img)[0]
        lf[a : a + len(img)] = predict(det.model, np.ascontiguousarray(img[:, :, ::-1]))[0]

    def scored(logits):
        return replace(plain, scores=(1.0 / (1.0 + np.exp(-logits / det.temperature))).astype(np.float32))

    again = scored(lg).scores
    if not np.allclose(again, plain.scores, atol=1e-4):
        raise SystemExit(
            f"{scene.name}: the stored table's scores are not this detector's on these frames "
            f"(max difference {np.abs(again - plain.scores).max():.3g}); name the right --table"
        )

    return {"plain": plain, "flip-mean": scored((lg + lf) / 2), "flip-min": scored(np.minimum(lg, lf))}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze detector-tta", description=__doc__.splitlines()[0]
    )
    p.add_argument("--data", required=True, help="world with the split's rooms at the detector's frame size")
    p.add_argument("--split", default="val")
    p.add_argument("--shipped", default="learned4", help="shipped detector name (tsnav.detect.shipped)")
    p.add_argument("--table", default=None, help="the rooms' stored table of that detector (default: --shipped)")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    set_threads(a.threads)
    folders = list_scenes(a.data, a.split)
    if not folders:
        raise SystemExit(f"--data {a.data}: no {a.split} scenes")
    det = shipped_detector(None, a.shipped)
    scenes, out = [], {"plain": [], "flip-mean": [], "flip-min": []}
    for f in tqdm(folders, desc=f"{a.split} rooms", unit="room"):
        s = load_scene(f)
        scenes.append(s)
        for k, t in tables(det, s, load_detections(f, a.table or a.shipped)).items():
            out[k].append(t)
    for k, tabs in out.items():
        r = switch_report(scenes, tabs)
        e = evaluate_detections(scenes, tabs)
        fp = ", ".join(f"> {t:g}: {100 * v:.2f} %" for t, v in r.fp_state_any.items())
        print(
            f"{k:10s} presence AP {np.nanmean(e.presence_ap):.3f}; reach {r.reached}/{r.pairs} "
            f"(episode pairs {r.episode_reached}/{r.episode_pairs}); false-positive states {fp}"
        )
    return 0
