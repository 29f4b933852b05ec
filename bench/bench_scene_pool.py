"""Detection tables and feature caches of a built world: one process against one process per core.

Copies the world's frames (links) into a scratch folder twice and writes the shipped detector's tables and an
encoder's feature caches into each: once in this process (tables on one thread, features on this process's torch
threads, as before issue 26) and once by ``--workers`` processes of one thread each (:mod:`tsnav.scene_pool`).
Prints seconds and the ratio, and checks that both wrote the same bytes.

    python bench/bench_scene_pool.py --data WORLD --encoder PRETRAIN_RUN [--workers 2] [--threads 2]

WORLD: a 128-px world (e.g. ``tsnav world --preset demo-real-small``); PRETRAIN_RUN: a pretraining run folder
(e.g. the demo's ``out/demo/pretrain/demae``).
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from tsnav.data.reader import list_scenes, load_scene
from tsnav.detect.shipped import shipped_detector
from tsnav.distributed import set_threads
from tsnav.pipeline.detector_steps import write_learned_tables
from tsnav.pretrain.features import cache_features, load_encoder


def link_world(src: Path, dst: Path) -> None:
    """``dst``: the scenes of ``src`` without their feature caches and detection tables (files linked)."""
    dst.mkdir(parents=True)
    for f in src.iterdir():
        if f.is_file():
            (dst / f.name).symlink_to(f.resolve())
    for p in list_scenes(src):
        (dst / p.name).mkdir()
        for f in p.iterdir():
            if not f.name.startswith(("features_", "detections_")):
                (dst / p.name / f.name).symlink_to(f.resolve())


def digest(root: Path, pattern: str) -> str:
    h = hashlib.sha256()
    for p in sorted(root.glob(f"*/{pattern}")):
        with h5py.File(p, "r") as f:
            for k in sorted(f.keys()):
                h.update(np.ascontiguousarray(f[k][()]).tobytes())
    return h.hexdigest()[:16]


def main() -> None:
    ap = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="a built 128-px world")
    ap.add_argument("--encoder", required=True, help="pretraining run folder (encoder.safetensors)")
    ap.add_argument("--workers", type=int, default=2, help="processes of the parallel path (default 2)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads of the in-process features (default 2)")
    args = ap.parse_args()
    src = Path(args.data)
    scenes = list_scenes(src)
    states = sum(load_scene(p).num_states for p in scenes)
    print(f"{len(scenes)} rooms, {states} states")
    set_threads(args.threads)
    rows = {}
    with tempfile.TemporaryDirectory(prefix="bench_scene_pool_") as tmp:
        for label, workers in (("one process", 0), (f"{args.workers} processes", args.workers)):
            dst = Path(tmp) / f"w{workers}"
            link_world(src, dst)
            det = shipped_detector(load_scene(scenes[0]).image_size)
            t = time.perf_counter()
            write_learned_tables(dst, "learned", det, progress=False, say=lambda m: None, workers=max(workers, 1))
            td = time.perf_counter() - t
            enc = load_encoder(args.encoder)
            t = time.perf_counter()
            cache_features(enc, dst, "bench", batch_size=128, progress=False, workers=workers)
            tf = time.perf_counter() - t
            rows[label] = (td, tf, digest(dst, "detections_learned.hdf5"), digest(dst, "features_bench.hdf5"))
            shutil.rmtree(dst)
    (d0, f0, dd0, fd0), (d1, f1, dd1, fd1) = rows.values()
    print(f"{'':<14} {'tables s':>9} {'features s':>11}")
    for label, (td, tf, _, _) in rows.items():
        print(f"{label:<14} {td:9.1f} {tf:11.1f}")
    print(f"ratio          {d0 / d1:8.2f}x {f0 / f1:10.2f}x")
    print(f"same bytes: tables {dd0 == dd1}, features {fd0 == fd1}")


if __name__ == "__main__":
    main()
