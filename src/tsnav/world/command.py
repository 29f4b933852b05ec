"""``tsnav world``: build an offline dataset of procedurally generated houses."""

from __future__ import annotations

import argparse
import os

from ..errors import CommandError
from ..render.gl import RendererUnavailable
from .build import BuildConfig, build_dataset
from .presets import PRESETS


def build_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", default="tiny", help=f"scene set: {', '.join(PRESETS)} (default tiny)")
    p.add_argument("--out", required=True, help="dataset folder (one sub-folder per scene)")
    p.add_argument("--scenes", default=None, help="comma-separated scene names instead of the preset's")
    p.add_argument("--size", type=int, default=None, help="image side in pixels (default: the preset's)")
    p.add_argument("--no-images", action="store_true", help="do not store images.hdf5 / depth.hdf5")
    p.add_argument("--no-compression", action="store_true",
                   help="store frames raw (default: gzip level 1, about 4.5x smaller at 128 px; stock h5py reads both)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="worker processes")
    p.add_argument("--seed", type=int, default=0, help="world seed (same name + seed = same scene)")
    p.add_argument("--compact", action="store_true", default=None, help="small rooms (default: the preset's)")


def run(args) -> int:
    if args.preset not in PRESETS:
        raise CommandError(f"unknown preset {args.preset!r} (choose from {', '.join(PRESETS)})")
    cfg = BuildConfig.from_preset(args.preset, store_images=not args.no_images, seed=args.seed,
                                  **({"compression": None} if args.no_compression else {}),
                                  **({"image_size": args.size} if args.size else {}),
                                  **({"compact": True} if args.compact else {}))
    if cfg.image_size < 16 or cfg.image_size > 1024:
        raise CommandError(f"--size {cfg.image_size} is out of range (16..1024)")
    if args.workers < 1:
        raise CommandError("--workers must be at least 1")
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()] if args.scenes else None
    try:
        stats = build_dataset(args.out, args.preset, scenes, cfg, workers=args.workers)
    except RendererUnavailable as e:
        raise CommandError(str(e)) from None
    built = [s for s in stats if not s.skipped]
    print(f"{len(stats)} scenes in {args.out}: {len(built)} built, {len(stats) - len(built)} already complete")
    if built:
        states = sum(s.states for s in built)
        print(f"{states} states, {sum(s.positions for s in built)} positions, "
              f"{sum(s.objects for s in built)} target objects; render {sum(s.render_s for s in built):.1f}s, "
              f"write {sum(s.write_s for s in built):.1f}s")
    return 0
