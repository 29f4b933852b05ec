"""Tile PNG pictures (e.g. the per-scene maps of ``tsnav world fidelity``) into one sheet, row by row.

    python scripts/tile_pngs.py --out SHEET.png [--cols 2] [--scale 0.75] A.png B.png ...

Each picture keeps its aspect ratio and is scaled by ``--scale``; the cell size is the largest picture's.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from PIL import Image

from tsnav.atomic import atomic_path


def tile(paths: list[Path], cols: int, scale: float) -> Image.Image:
    images = [Image.open(p).convert("RGB") for p in paths]
    images = [im.resize((max(1, round(im.width * scale)), max(1, round(im.height * scale))), Image.LANCZOS)
              for im in images]
    w, h = max(im.width for im in images), max(im.height for im in images)
    rows = math.ceil(len(images) / cols)
    sheet = Image.new("RGB", (cols * w, rows * h), "white")
    for i, im in enumerate(images):
        sheet.paste(im, ((i % cols) * w, (i // cols) * h))
    return sheet


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pictures", nargs="+", type=Path)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--cols", type=int, default=2)
    ap.add_argument("--scale", type=float, default=0.75)
    args = ap.parse_args(argv)
    missing = [str(p) for p in args.pictures if not p.is_file()]
    if missing:
        print(f"tile_pngs: no such picture: {missing[0]}", file=sys.stderr)
        return 2
    if args.cols < 1 or not args.scale > 0:
        print("tile_pngs: --cols must be >= 1 and --scale positive", file=sys.stderr)
        return 2
    with atomic_path(args.out) as tmp:
        tile(args.pictures, args.cols, args.scale).save(tmp, format="PNG", optimize=True)
    print(f"{args.out}: {len(args.pictures)} pictures")
    return 0


if __name__ == "__main__":
    sys.exit(main())
