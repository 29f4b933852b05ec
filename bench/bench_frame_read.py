"""What compressed frames cost the consumers that read them (pretraining data, feature caching, detector
tables, the gym env's frame cache): frames/s of reading every frame of a few scenes, raw files (as built
before compression) against gzip-1 copies of the same frames (the writers' default), each read with plain
``f[key][()]`` (today's readers: :func:`tsnav.data.reader.read_stack_reference`) and with
:func:`tsnav.data.reader.read_stack` (h5py's low-level calls), in one run.

    .venv/bin/python bench/bench_frame_read.py --data RAW_WORLD --out SCRATCH [--scenes 3] [--repeats 2]
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path

import h5py

from tsnav.data.reader import list_scenes, load_scene, read_stack, read_stack_reference
from tsnav.data.writer import FrameWriter


def main() -> None:
    ap = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="a world built with raw frames (--no-compression or before)")
    ap.add_argument("--out", required=True, help="scratch folder for the gzip copies (removed afterwards)")
    ap.add_argument("--scenes", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    scenes = list_scenes(args.data)[: args.scenes]
    out = Path(args.out)
    copies = []
    for p in scenes:  # gzip copies of the same frames, written by the writers' default settings
        keys = load_scene(p).keys
        with h5py.File(p / "images.hdf5", "r") as fi, h5py.File(p / "depth.hdf5", "r") as fd:
            rgb, depth = read_stack(fi, keys), read_stack(fd, keys)
            if fi[str(keys[0])].compression is not None:
                raise SystemExit(f"{p}: frames are already compressed; give a raw world")
        d = out / p.name
        d.mkdir(parents=True, exist_ok=True)
        with FrameWriter(d, str(depth.dtype)) as w:
            w.add_many(keys, rgb, depth)
        copies.append((p, d, keys))
    n = sum(len(k) for _, _, k in copies)
    raw_b = sum((p / f).stat().st_size for p, _, _ in copies for f in ("images.hdf5", "depth.hdf5"))
    gz_b = sum((d / f).stat().st_size for _, d, _ in copies for f in ("images.hdf5", "depth.hdf5"))
    print(
        f"{len(copies)} scenes, {n:,} states (rgb + depth): raw {raw_b / 1e6:.0f} MB, gzip-1 {gz_b / 1e6:.0f} MB; "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    rates = {}
    for rep in range(args.repeats):
        for files in ("raw", "gzip-1"):
            for reader, fn in (("f[key][()]", read_stack_reference), ("read_stack", read_stack)):
                t = time.perf_counter()
                for p, d, keys in copies:
                    base = p if files == "raw" else d
                    with h5py.File(base / "images.hdf5", "r") as fi, h5py.File(base / "depth.hdf5", "r") as fd:
                        a, b = fn(fi, keys), fn(fd, keys)
                        assert a.shape[0] == b.shape[0] == len(keys)
                rate = n / (time.perf_counter() - t)
                rates[(files, reader)] = max(rates.get((files, reader), 0.0), rate)
    print("\n| files | reader | states/s (rgb + depth), best of repeats | vs raw + f[key][()] (today) |")
    print("| --- | --- | --- | --- |")
    base = rates[("raw", "f[key][()]")]
    for (files, reader), r in rates.items():
        print(f"| {files} | {reader} | {r:,.0f} | {r / base:.2f}x |")
    print(f"load average {os.getloadavg()[0]:.1f}")
    shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
