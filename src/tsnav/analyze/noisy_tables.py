"""Detection tables of the shipped detector on frames with Gaussian pixel noise (issue 23, analysis).

The shipped detector was trained on the 80 training rooms, so its tables there are cleaner than on rooms it never saw
(learned4: presence AP 0.826 and false-positive states above 0.7 0.94 % on the training rooms, 0.743 and 2.19 % on
val). An agent trained on the clean tables learns to trust detections more than it should at test time. This script
writes tables whose errors are the same detector's, made on perturbed frames, so that the training rooms' tables look
like the val rooms' (tune ``--sigma`` with ``python -m tsnav.detect.quality --split train``), and links the clean
tables of the other splits under the new name, so that an agent trains on the noisy tables and is selected and
tested on the clean ones:

    tsnav analyze noisy-tables --data WORLD --from learned4 --name learned4n --sigma 16 [--workers 2]

Each scene's noise comes from its own generator (seed, scene name), so the tables are the same on every run; the
table's config records the noise. A scene whose table exists is skipped.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np


def noisy_table(scene_dir: str, sigma: float, seed: int, shipped: str, name: str) -> str:
    from dataclasses import replace

    from ..distributed import set_threads

    set_threads(1)
    from ..data.detections import detections_path, write_detections
    from ..data.reader import load_scene
    from ..detect.shipped import shipped_detector

    scene = load_scene(scene_dir)
    if detections_path(scene_dir, name).exists():
        return f"{scene.name}: exists"
    det = shipped_detector(scene.image_size, shipped)
    digest = hashlib.sha256(f"{seed}:{scene.name}".encode()).digest()
    rng = np.random.default_rng(int.from_bytes(digest[:8], "little"))

    def noisy(img: np.ndarray) -> np.ndarray:
        x = img.astype(np.float32) + rng.normal(0.0, sigma, img.shape).astype(np.float32)
        return np.clip(np.rint(x), 0, 255).astype(np.uint8)

    table = det.detect_scene(scene, chunk=1024, transform=noisy)
    cfg = dict(table.config, frame_noise={"sigma": sigma, "seed": seed, "kind": "gaussian, per pixel and channel"})
    write_detections(scene_dir, name, replace(table, config=cfg))
    return f"{scene.name}: written"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze noisy-tables", description=__doc__.splitlines()[0]
    )
    p.add_argument("--data", required=True, help="world folder (120 rooms)")
    p.add_argument("--from", dest="source", default="learned4", help="clean table linked into the other splits")
    p.add_argument("--shipped", default="learned4", help="shipped detector that writes the noisy tables")
    p.add_argument("--name", required=True, help="name of the new tables")
    p.add_argument("--sigma", type=float, required=True, help="noise std in pixel values (0-255)")
    p.add_argument("--split", default="train", help="split whose tables are made noisy (default train)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2)
    a = p.parse_args(argv)
    from ..data.detections import detections_path, load_detections, write_detections
    from ..data.reader import list_scenes

    if not a.sigma >= 0:
        print(f"error: --sigma must be >= 0, got {a.sigma}", file=sys.stderr)
        return 2
    if a.name == a.source:
        print("error: --name must differ from --from", file=sys.stderr)
        return 2
    noisy = list_scenes(a.data, a.split)
    others = [s for s in list_scenes(a.data) if s not in noisy]
    if not noisy:
        print(f"error: no {a.split} scenes in {a.data}", file=sys.stderr)
        return 2
    for s in others:  # the clean tables of the other splits, rewritten under the new name
        src, dst = detections_path(s, a.source), detections_path(s, a.name)
        if not src.exists():
            print(f"error: {s.name} has no {src.name}", file=sys.stderr)
            return 2
        if not dst.exists():
            write_detections(s, a.name, load_detections(s, a.source))
    args = (
        [str(s) for s in noisy],
        [a.sigma] * len(noisy),
        [a.seed] * len(noisy),
        [a.shipped] * len(noisy),
        [a.name] * len(noisy),
    )
    if a.workers > 1:
        with ProcessPoolExecutor(a.workers) as pool:
            for msg in pool.map(noisy_table, *args):
                print(msg, flush=True)
    else:
        for msg in map(noisy_table, *args):
            print(msg, flush=True)
    return 0
