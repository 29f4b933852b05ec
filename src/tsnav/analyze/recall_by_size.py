"""How large must a target show for the switch to fire: detection tables' recall at C_target by the target's pixels in
view (issue 46, analysis).

The stage switch fires when the detector scores the target above C_target (paper III-B). A target that is in view in
many states but only ever as a few pixels (RoboTHOR's SprayBottle: at most about 400 of a 128-px frame's 16,384) is
missed unless the detector fires on small views. For each class and each band of pixels in view (ground truth, the
class's largest visible instance: :func:`tsnav.detect.oracle.ground_truth`) this counts the states of a split where
the class is in view and the share of them whose table scores it above ``--c-target``, for each table given; the
largest view a class ever shows is printed beside it.

    tsnav analyze recall-by-size --data WORLD --split val --tables robothor5 robothor5hr [--bands 100,200,400,800] \\
        [--c-target 0.7] [--json OUT] [--picture PNG --class SprayBottle [--frames robothor5hr=DIR256]]

``--picture`` draws ``--examples`` states where ``--class`` is in view, one column per table: the frame (the table's
own ``--frames`` folder when given, a build of the same states at the side that detector reads, else the world's
frames), the ground-truth box in green and the table's box in red with its score. The states are drawn at random
(``--seed``) among those showing at least ``--min-pixels`` of the class; the picture changes no figure.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_text
from ..constants import C_TARGET, class_set
from ..errors import CommandError

#: Default upper edges of the pixel bands (the last band is open).
BANDS = (100, 200, 400, 800)


def band_labels(edges) -> list[str]:
    """``["<100", "100-200", ..., ">=800"]`` for upper edges ``edges``."""
    lo = [0, *edges]
    return [f"<{edges[0]}"] + [f"{a}-{b}" for a, b in zip(lo[1:], edges[1:])] + [f">={edges[-1]}"]


def recall_counts(present: np.ndarray, pixels: np.ndarray, scores: np.ndarray, edges, c_target: float) -> np.ndarray:
    """``(C, B, 2)`` counts per class and pixel band: states where the class is in view, and of them those scored above
    ``c_target``. ``present``, ``pixels``, ``scores``: ``(S, C)`` of one scene."""
    C, B = present.shape[1], len(edges) + 1
    band = np.searchsorted(np.asarray(edges), pixels, side="right")  # band b holds edges[b-1] <= px < edges[b]
    out = np.zeros((C, B, 2), np.int64)
    s, c = np.nonzero(present)
    np.add.at(out, (c, band[s, c], 0), 1)
    hit = scores[s, c] > c_target
    np.add.at(out, (c[hit], band[s, c][hit], 1), 1)
    return out


def recall_counts_reference(present, pixels, scores, edges, c_target: float) -> np.ndarray:
    """Slow reference for :func:`recall_counts`: one state and class at a time."""
    S, C = present.shape
    out = np.zeros((C, len(edges) + 1, 2), np.int64)
    for s in range(S):
        for c in range(C):
            if not present[s, c]:
                continue
            b = sum(int(pixels[s, c]) >= e for e in edges)
            out[c, b, 0] += 1
            out[c, b, 1] += int(scores[s, c] > c_target)
    return out


def measure(folders: list[Path], tables: list[str], edges, c_target: float) -> dict:
    """Counts of every table over ``folders`` (one scene folder each), by class: ``{"classes": {name: {"bands":
    [[n, hits per table...], ...], "max_pixels": int}}}``, classes in view somewhere only."""
    from ..data.detections import load_detections
    from ..data.reader import load_scene
    from ..detect.oracle import ground_truth

    counts, largest, names = None, None, None
    for p in folders:
        scene = load_scene(p)
        gt = ground_truth(scene)
        per = []
        for t in tables:
            try:
                det = load_detections(p, t)
            except FileNotFoundError:
                raise CommandError(f"{p}: no detections_{t}.hdf5") from None
            if not np.array_equal(det.keys, scene.keys):
                raise CommandError(f"{p}/detections_{t}.hdf5: its states are not the scene's")
            per.append(recall_counts(gt.present, gt.pixels, det.scores, edges, c_target))
        names = names or list(class_set(scene.class_set).categories)
        got = np.stack([per[0][..., 0]] + [q[..., 1] for q in per], -1)  # (C, B, 1 + tables)
        counts = got if counts is None else counts + got
        big = np.where(gt.present, gt.pixels, 0).max(0)
        largest = big if largest is None else np.maximum(largest, big)
    return {
        "classes": {
            n: {"bands": counts[c].tolist(), "max_pixels": int(largest[c])}
            for c, n in enumerate(names)
            if counts[c, :, 0].sum()
        }
    }


def format_table(doc: dict) -> str:
    """One row per class: each band's state count and each table's recall in percent."""
    tables, labels = doc["tables"], band_labels(doc["bands"])
    cells = lambda row: [f"{row[0]}: " + " / ".join(f"{100 * h / row[0]:.0f}" if row[0] else "-" for h in row[1:])]  # noqa: E731
    lines = [
        f"recall at C_target {doc['c_target']:g} by pixels in view, {doc['split']} scenes of {doc['data']} "
        f"(states in view: {' / '.join(tables)} in %)",
        "| class | largest view (px) | " + " | ".join(labels) + " |",
        "|---|---|" + "---|" * len(labels),
    ]
    for name, c in doc["classes"].items():
        lines.append(f"| {name} | {c['max_pixels']} | " + " | ".join(cells(r)[0] for r in c["bands"]) + " |")
    return "\n".join(lines)


def draw(
    folders: list[Path],
    tables: list[str],
    frames: dict[str, Path],
    cls: str,
    examples: int,
    min_pixels: int,
    seed: int,
    path: Path,
) -> int:
    """The picture of ``--picture`` (module docstring); returns the number of states drawn."""
    from PIL import Image, ImageDraw

    from ..data.detections import detections_path, load_detections
    from ..data.reader import load_scene
    from ..detect.data import frame_twins
    from ..detect.oracle import ground_truth
    from ..eval.video import _font
    from ..world.show import frame_images

    rng = np.random.default_rng(seed)
    pool = []
    for p in folders:
        scene = load_scene(p)
        names = list(class_set(scene.class_set).categories)
        if cls not in names:
            raise CommandError(f"--class {cls}: not a class of {scene.class_set} ({', '.join(names)})")
        c = names.index(cls)
        gt = ground_truth(scene)
        pool += [(p, c, int(s)) for s in np.flatnonzero(gt.present[:, c] & (gt.pixels[:, c] >= min_pixels))]
    if not pool:
        raise CommandError(f"--class {cls}: in view with at least {min_pixels} px in no state of these scenes")
    pick = [pool[i] for i in sorted(rng.choice(len(pool), min(examples, len(pool)), replace=False))]
    side = 256
    cap = 30
    sheet = Image.new("RGB", (len(tables) * side, len(pick) * (side + cap)), "white")
    font = _font(11)
    for row, (p, c, s) in enumerate(pick):
        scene = load_scene(p)
        gt = ground_truth(scene)
        for col, t in enumerate(tables):
            src = scene
            if t in frames:  # the frames and boxes its detector read: the same states at another side
                ((_, q, _, _),) = frame_twins([p], frames[t], f"--frames {t}={frames[t]}")
                if not detections_path(q, t).exists():
                    raise CommandError(f"--frames {t}={frames[t]}: {p.name} has no detections_{t}.hdf5 there")
                src = load_scene(q)
            det = load_detections(src.path, t)
            frame = frame_images(src, [scene.keys[s]])[0]
            k = side / frame.shape[0]
            tile = Image.fromarray(frame).resize((side, side), Image.NEAREST)
            d = ImageDraw.Draw(tile)
            g = gt.boxes[s, c] * (side / scene.image_size)
            step = side / scene.image_size
            d.rectangle([g[0], g[1], g[2] + step - 1, g[3] + step - 1], outline=(0, 220, 0), width=2)
            if det.labels[s, c] >= 0:
                b = det.boxes[s, c] * k
                d.rectangle([b[0], b[1], b[2] + k - 1, b[3] + k - 1], outline=(255, 0, 0), width=2)
            x, y = col * side, row * (side + cap)
            sheet.paste(tile, (x, y))
            d = ImageDraw.Draw(sheet)
            d.text((x + 3, y + side + 2), f"{t} ({frame.shape[0]} px): {det.scores[s, c]:.2f}", fill="black", font=font)
            d.text(
                (x + 3, y + side + 15),
                f"{p.name.replace('FloorPlan_', '')}, {int(gt.pixels[s, c])} px in view",
                fill=(90, 90, 90),
                font=font,
            )
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial.png")
    sheet.save(tmp)
    tmp.replace(path)
    return len(pick)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="tsnav analyze recall-by-size", description=__doc__.split("\n\n")[0], allow_abbrev=False
    )
    ap.add_argument("--data", type=Path, required=True, help="world folder holding the tables")
    ap.add_argument("--split", default="val", help="the scenes measured (default val)")
    ap.add_argument("--tables", nargs="+", required=True, help="detection table names (detections_NAME.hdf5)")
    ap.add_argument("--c-target", type=float, default=C_TARGET, help=f"the switch's threshold (default {C_TARGET})")
    ap.add_argument(
        "--bands", default=",".join(map(str, BANDS)), help="upper edges of the pixel bands (default 100,200,400,800)"
    )
    ap.add_argument("--json", type=Path, default=None, help="write the counts here")
    ap.add_argument("--picture", type=Path, default=None, help="draw examples of --class into this PNG")
    ap.add_argument("--class", dest="cls", default=None, help="the class the picture shows")
    ap.add_argument(
        "--frames",
        action="append",
        default=[],
        metavar="TABLE=DIR",
        help="the picture draws TABLE's column on DIR's frames and boxes (the build of the same states its detector "
        "read, tsnav detect --frames); repeatable",
    )
    ap.add_argument("--examples", type=int, default=6, help="states in the picture (default 6)")
    ap.add_argument("--min-pixels", type=int, default=60, help="the picture's states show at least this (default 60)")
    ap.add_argument("--seed", type=int, default=0, help="the picture's draw (default 0)")
    a = ap.parse_args(argv)

    from ..data.reader import list_scenes

    try:
        edges = sorted({int(x) for x in a.bands.split(",") if x.strip()})
    except ValueError:
        raise CommandError(f"--bands {a.bands}: give increasing whole pixel counts, e.g. 100,200,400") from None
    if not edges or edges[0] <= 0:
        raise CommandError(f"--bands {a.bands}: give positive pixel counts, e.g. 100,200,400")
    if not 0.0 <= a.c_target < 1.0:
        raise CommandError(f"--c-target {a.c_target}: must lie in [0, 1)")
    if a.picture is not None and a.cls is None:
        raise CommandError("--picture draws one class: give --class NAME")
    if not 1 <= a.examples <= 64:
        raise CommandError(f"--examples {a.examples}: between 1 and 64")
    frames = {}
    for item in a.frames:
        t, sep, d = item.partition("=")
        if not sep or t not in a.tables:
            raise CommandError(f"--frames {item}: give TABLE=DIR with TABLE one of --tables")
        if not Path(d).is_dir():
            raise CommandError(f"--frames {item}: no such folder {d}")
        frames[t] = Path(d)
    if not a.data.is_dir():
        raise CommandError(f"--data {a.data}: no such world folder")
    folders = list_scenes(a.data, split=a.split)
    if not folders:
        raise CommandError(f"--data {a.data}: no complete {a.split} scene")
    doc = {
        "data": str(a.data),
        "split": a.split,
        "scenes": len(folders),
        "tables": list(a.tables),
        "c_target": a.c_target,
        "bands": edges,
        "band_labels": band_labels(edges),
        "columns": ["states in view"] + [f"above C_target: {t}" for t in a.tables],
        **measure(folders, list(a.tables), edges, a.c_target),
    }
    print(format_table(doc))
    if a.json is not None:
        atomic_write_text(a.json, json.dumps(doc, indent=1) + "\n")
        print(f"wrote {a.json}")
    if a.picture is not None:
        n = draw(folders, list(a.tables), frames, a.cls, a.examples, a.min_pixels, a.seed, a.picture)
        print(f"wrote {a.picture} ({n} states)")
    return 0
