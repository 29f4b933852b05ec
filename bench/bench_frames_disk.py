"""Frames at a fraction of the disk: builds the same ``ithor-real`` rooms with the default gzip frame files
and raw (``--no-compression``) in one run, at each size, and prints wall time and disk use of each, their
ratio, CPU seconds (this process and its workers: the robust figure on a shared machine), and the
extrapolation to the 120 rooms (by state count: 377,536 states). Builds alternate between
the two settings so that machine load hits both alike. Goal (issue 26): the 120 rooms at 128 px in <= 8 GB,
build time within 1.2x of raw.

    .venv/bin/python bench/bench_frames_disk.py --out DIR [--sizes 64,128] [--scenes FloorPlan1,...]
        [--before-src OLD_CHECKOUT/src]

``raw`` is this checkout's writer with compression off; ``--before-src`` adds builds by another checkout's
code (``tsnav world`` run with that ``src`` first on the path), e.g. the commit before compression, as
"today's" writer.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

from tsnav.world.build import BuildConfig, build_dataset

#: two rooms of each type, small and large (the 120 rooms hold 377,536 states)
SCENES = [
    "FloorPlan5",
    "FloorPlan12",
    "FloorPlan203",
    "FloorPlan216",
    "FloorPlan305",
    "FloorPlan313",
    "FloorPlan405",
    "FloorPlan414",
]
ALL_STATES = 377_536


def _cpu() -> float:
    """CPU seconds of this process and its finished children (the build's workers, a subprocess build)."""
    return sum(
        getattr(resource.getrusage(who), f)
        for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
        for f in ("ru_utime", "ru_stime")
    )


def disk(path: Path, pattern: str = "*") -> int:
    """Bytes of the files matching ``pattern`` in the scene folders under ``path``."""
    return sum(f.stat().st_size for f in path.glob(f"*/{pattern}") if f.is_file())


def main() -> None:
    ap = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="scratch folder (emptied of its builds afterwards unless --keep)")
    ap.add_argument("--sizes", default="64,128")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--keep", action="store_true")
    ap.add_argument("--before-src", default=None, help="another checkout's src folder: its raw writer as 'before'")
    args = ap.parse_args()
    scenes = args.scenes.split(",")
    out = Path(args.out)
    print(f"{len(scenes)} ithor-real rooms, {args.workers} workers; load average {os.getloadavg()[0]:.1f}")
    print("| size | frames | states | wall s | CPU s | images + depth | all files | 120 rooms (extrapolated) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for size in (int(s) for s in args.sizes.split(",")):
        res = {}
        order = [("gzip-1", "gzip"), ("raw", None)] + ([("before", "src")] if args.before_src else [])
        for i, (tag, comp) in enumerate(order + order[::-1]):  # A B C C B A: each setting once early, once late
            d = out / f"{size}-{tag}-{i}"
            shutil.rmtree(d, ignore_errors=True)
            t, c = time.perf_counter(), _cpu()
            if comp == "src":
                subprocess.run(
                    [
                        sys.executable,
                        "-m",
                        "tsnav",
                        "world",
                        "--preset",
                        "ithor-real",
                        "--scenes",
                        ",".join(scenes),
                        "--out",
                        str(d),
                        "--size",
                        str(size),
                        "--workers",
                        str(args.workers),
                    ],
                    env={**os.environ, "PYTHONPATH": args.before_src},
                    check=True,
                    capture_output=True,
                )
                states = sum(json.loads((d / n / "scene.json").read_text())["num_states"] for n in scenes)
            else:
                cfg = BuildConfig.from_preset("ithor-real", image_size=size, compression=comp)
                stats = build_dataset(d, "ithor-real", scenes, cfg, workers=args.workers, progress=False)
                states = sum(s.states for s in stats)
            wall, cpu = time.perf_counter() - t, _cpu() - c
            frames, total = disk(d, "*.hdf5") - disk(d, "states.hdf5"), disk(d)
            w, cp, _, _ = res.get(tag, (0.0, 0.0, 0, 0))
            res[tag] = (w + wall / 2, cp + cpu / 2, frames, total)
            if not args.keep:
                shutil.rmtree(d)
        for tag, (wall, cpu, frames, total) in res.items():
            print(
                f"| {size} | {tag} | {states:,} | {wall:.1f} | {cpu:.1f} | {frames / 1e9:.2f} GB | {total / 1e9:.2f} GB | "
                f"{total / states * ALL_STATES / 1e9:.1f} GB |"
            )
        for base in ("raw", "before"):
            if base in res:
                (wg, cg, _, tg), (wr, cr, _, tr) = res["gzip-1"], res[base]
                print(
                    f"| {size} | gzip-1 / {base} | | {wg / wr:.2f}x | {cg / cr:.2f}x | | {tg / tr:.2f}x | |", flush=True
                )
    print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
