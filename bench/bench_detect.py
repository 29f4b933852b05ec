"""Learned detector throughput on this machine: states per second of `LearnedDetector.detect_scene` (frames read
from images.hdf5, network, table), and the projected time to run it over every state of a world.

The projection multiplies the measured seconds per state by the states of the world: the scenes present under
--data, scaled to the preset's scene count (`--preset-scenes`, 120 for `ithor`) by their mean states per scene.
Goal (issue #14): every state of the `ithor` world within an hour.

    .venv/bin/python bench/bench_detect.py --data DIR --checkpoint CKPT [--scenes 3] [--threads 1]
"""

from __future__ import annotations

import argparse
import time

import torch

from tsnav.data.reader import list_scenes, load_scene
from tsnav.detect.learned import LearnedDetector


def main() -> None:
    ap = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--split", default="val", help="scenes timed (default val)")
    ap.add_argument("--scenes", type=int, default=3, help="scenes timed (default 3)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--preset-scenes", type=int, default=120, help="scenes of the whole world (ithor: 120)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    det = LearnedDetector.load(args.checkpoint)
    all_paths = list_scenes(args.data)
    states = [load_scene(p).num_states for p in all_paths]
    paths = list_scenes(args.data, split=args.split)[: args.scenes]
    n, t = 0, 0.0
    for p in paths:
        s = load_scene(p)
        t0 = time.perf_counter()
        det.detect_scene(s)
        dt = time.perf_counter() - t0
        n += s.num_states
        t += dt
        print(f"{s.name}: {s.num_states} states in {dt:.1f} s ({s.num_states / dt:.0f} states/s)")
    per_state = t / n
    world = sum(states) / len(states) * args.preset_scenes
    cfg = det.model.cfg
    print(
        f"model: {cfg.image_size}px, stem {cfg.stem}, widths {list(cfg.widths)}, dim {cfg.dim}; threads {args.threads}"
    )
    print(
        f"{n / t:.0f} states/s; {len(states)} scenes here average {sum(states) / len(states):.0f} states -> "
        f"{world:.0f} states for {args.preset_scenes} scenes: {world * per_state / 60:.1f} minutes"
    )


if __name__ == "__main__":
    main()
