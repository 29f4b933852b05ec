"""``tsnav demo``: the main job on the embedded world.

Builds the `demo` world (or reuses it), then runs every stage that is available, each reusing what an
earlier run already produced, and prints the results.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def build_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="out/demo", help="folder for the world, runs and report (default out/demo)")
    p.add_argument("--workers", type=int, default=2, help="worker processes for world building")


def run(args) -> int:
    import numpy as np

    from .data.reader import list_scenes, load_scene
    from .world.build import build_dataset

    out = Path(args.out)
    world = out / "world"
    print(f"[1] world: building the `demo` preset into {world} (finished scenes are reused)")
    build_dataset(world, "demo", workers=args.workers)
    rows = []
    for p in list_scenes(world):
        s = load_scene(p)
        succ = s.category_visible_within(1.0)
        cats = s.categories_present()
        rows.append((s.name, s.room_type, s.meta.get("split"), s.num_states, len(s.object_ids), len(cats),
                     float(np.mean(succ[:, cats].mean(0))) if cats else 0.0))
    print(f"{'scene':<14}{'room':<13}{'split':<7}{'states':>7}{'targets':>8}{'cats':>5}{'succ%':>7}")
    for r in rows:
        print(f"{r[0]:<14}{r[1]:<13}{r[2]:<7}{r[3]:>7}{r[4]:>8}{r[5]:>5}{100 * r[6]:>7.1f}")
    print(f"{len(rows)} scenes, {sum(r[3] for r in rows)} states; `tsnav show {world}/FloorPlan1` draws one.")
    return 0
