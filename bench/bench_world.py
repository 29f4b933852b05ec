"""Dataset-building throughput: states per second at 64, 128 and 224 pixels, render and write separately.

Builds four full-size kitchens with two worker processes (both cores busy) into a temporary folder and
prints, per image size, the end-to-end rate, and the render-only and write-only rates summed over workers;
then the time of the scenes' state tables (poses, keys, graph edges) in array form against the per-state loop.
Run: .venv/bin/python bench/bench_world.py [--sizes 64 128 224] [--scenes 4]
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np

from tsnav.constants import HORIZONS, ROTATIONS
from tsnav.world.build import BuildConfig, build_dataset
from tsnav.world.navgrid import build_graph, graph_edges, reachable_positions, state_keys, state_poses
from tsnav.world.presets import scene_spec


def state_tables(names: list[str]) -> None:
    """Print the time of the build's state tables, array form against the per-state reference loop."""
    grids = [reachable_positions(scene_spec(n)) for n in names]
    t = time.perf_counter()
    for positions, move in grids:
        np.array([(x, z, r, h) for x, z in positions for r in ROTATIONS for h in HORIZONS], dtype=np.float64)
        build_graph(positions, move)
    ref = time.perf_counter() - t
    t = time.perf_counter()
    for positions, move in grids:
        keys = state_keys(positions)
        state_poses(positions)
        src, dst = graph_edges(move)
        list(zip(keys[src].tolist(), keys[dst].tolist()))
    fast = time.perf_counter() - t
    states = sum(len(p) for p, _ in grids) * len(ROTATIONS) * len(HORIZONS)
    print(f"state tables of {states} states: per-state loop {ref * 1e3:.0f} ms, arrays {fast * 1e3:.0f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(allow_abbrev=False)
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 224])
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args()
    names = [f"FloorPlan{i}" for i in range(1, a.scenes + 1)]
    print(
        f"{'size':>5} {'states':>7} {'wall s':>7} {'states/s':>9} {'render/s':>9} {'write/s':>9}  (workers={a.workers})"
    )
    for size in a.sizes:
        with tempfile.TemporaryDirectory() as d:
            t = time.perf_counter()
            stats = build_dataset(d, scenes=names, cfg=BuildConfig(image_size=size), workers=a.workers, progress=False)
            wall = time.perf_counter() - t
        n = sum(s.states for s in stats)
        render = sum(s.render_s for s in stats)
        write = sum(s.write_s for s in stats)
        # per-worker busy times are summed; divide by workers for the rate with all workers busy
        print(
            f"{size:>5} {n:>7} {wall:>7.1f} {n / wall:>9.0f} {n / render * a.workers:>9.0f} {n / write * a.workers:>9.0f}"
        )
    state_tables(names)


if __name__ == "__main__":
    main()
