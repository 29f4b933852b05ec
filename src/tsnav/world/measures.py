"""Per-room-type measures of the ``ithor-real`` world against its metadata and the procedural ``ithor`` world.

    python -m tsnav.world.measures --real DIR [--scenes FloorPlan1,...] [--out FILE.md]

``DIR`` is an ``ithor-real`` dataset built by ``tsnav world --preset ithor-real`` (its ``scene.json``,
``grid.json`` and ``visible_object_map_1.5.json`` are read). The metadata side comes from the packaged layouts
(floor box, recorded objects, target categories present); the procedural side is generated and laid out
(:func:`~tsnav.world.house.generate`, :func:`~tsnav.world.navgrid.reachable_positions`) without rendering.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
from tqdm import tqdm
from shapely.geometry import Polygon
from shapely.ops import unary_union

from ..atomic import atomic_write_text
from ..constants import ROOM_TARGETS, ROOM_TYPES
from ..data.names import ithor_scenes, scene_info
from .house import generate
from .layouts import load_layout
from .navgrid import reachable_positions


def _area(polys) -> float:
    return float(unary_union([Polygon(p) for p in polys]).area)


def real_measures(scene_dir: Path) -> dict:
    """Measures of one built ``ithor-real`` scene and of its recorded layout."""
    meta = json.loads((scene_dir / "scene.json").read_text())
    grid = json.loads((scene_dir / "grid.json").read_text())
    seen = {k for k, v in json.loads((scene_dir / "visible_object_map_1.5.json").read_text()).items() if v}
    lay = load_layout(meta["name"])
    fx, _, fz = lay.floor.aabb_size
    rt = meta["room_type"]
    recorded = {o.object_type for o in lay.objects}
    ids = {o["objectId"]: o["objectType"] for o in meta["objects"]}
    return {
        "room_type": rt,
        "floor_box_area": fx * fz,
        "room_area": _area(meta["floor"]),
        "positions": len(grid),
        "objects_recorded": len(lay.objects) - 1,
        "objects": len({f["id"] for f in meta["furniture"]}) + len(ids),
        "blocking": len({f["id"] for f in meta["furniture"] if f["blocks"]})
        + sum(o["support"] == "floor" for o in meta["objects"]),
        "target_objects": len(ids),
        "targets_meta": sorted(c for c in ROOM_TARGETS[rt] if c in recorded),
        "targets_scene": sorted({ids[i] for i in ids} & set(ROOM_TARGETS[rt])),
        "targets_seen": sorted({ids[i] for i in seen if i in ids} & set(ROOM_TARGETS[rt])),
    }


def procedural_measures(name: str) -> dict:
    """The same measures for the procedural ``ithor`` scene of that name (generated, not rendered)."""
    spec = generate(name)
    pos, _ = reachable_positions(spec)
    rt = spec.room_type
    present = {o.objectType for o in spec.objects}
    return {
        "room_type": rt,
        "room_area": _area(spec.floor),
        "positions": len(pos),
        "objects": len(spec.furniture) + len(spec.objects),
        "blocking": sum(f.blocks for f in spec.furniture) + sum(o.support == "floor" for o in spec.objects),
        "target_objects": len(spec.objects),
        "targets_scene": sorted(present & set(ROOM_TARGETS[rt])),
    }


def table(real: list[dict], proc: list[dict]) -> str:
    """Markdown tables: per room type means (real / metadata / procedural) and target presence per category."""
    by = defaultdict(list)
    pby = defaultdict(list)
    for m in real:
        by[m["room_type"]].append(m)
    for m in proc:
        pby[m["room_type"]].append(m)

    def mean(rows, key, f=len):
        vals = [(f(r[key]) if isinstance(r[key], list) else r[key]) for r in rows]
        return float(np.mean(vals)) if vals else float("nan")

    lines = [
        "| room type | scenes | floor box m² (metadata) | room m² (real / procedural) | reachable positions "
        "(real / procedural) | objects (metadata / real / procedural) | blocking (real / procedural) | "
        "target-class objects (real / procedural) | room-type targets present (metadata / real scene / "
        "seen in real / procedural) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for rt in ROOM_TYPES:
        r, p = by.get(rt, []), pby.get(rt, [])
        if not r:
            continue
        lines.append(
            f"| {rt} | {len(r)} | {mean(r, 'floor_box_area'):.1f} | {mean(r, 'room_area'):.1f} / {mean(p, 'room_area'):.1f} | "
            f"{mean(r, 'positions'):.0f} / {mean(p, 'positions'):.0f} | {mean(r, 'objects_recorded'):.0f} / "
            f"{mean(r, 'objects'):.0f} / {mean(p, 'objects'):.0f} | {mean(r, 'blocking'):.0f} / {mean(p, 'blocking'):.0f} | "
            f"{mean(r, 'target_objects'):.1f} / {mean(p, 'target_objects'):.1f} | {mean(r, 'targets_meta'):.1f} / "
            f"{mean(r, 'targets_scene'):.1f} / {mean(r, 'targets_seen'):.1f} / {mean(p, 'targets_scene'):.1f} "
            f"(of {len(ROOM_TARGETS[rt])}) |"
        )
    lines += [
        "",
        "Scenes holding each room-type target (metadata / real scene / seen from a state in the real "
        "scene / procedural):",
        "",
    ]
    for rt in ROOM_TYPES:
        r, p = by.get(rt, []), pby.get(rt, [])
        if not r:
            continue
        cells = []
        for c in ROOM_TARGETS[rt]:
            n = [sum(c in m[k] for m in r) for k in ("targets_meta", "targets_scene", "targets_seen")]
            cells.append(f"{c} {n[0]}/{n[1]}/{n[2]}/{sum(c in m['targets_scene'] for m in p)}")
        lines.append(f"- {rt} ({len(r)} scenes): " + ", ".join(cells))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n")[0])
    p.add_argument("--real", required=True, help="a dataset built with `tsnav world --preset ithor-real`")
    p.add_argument("--scenes", default=None, help="comma-separated scene names (default: all 120)")
    p.add_argument("--out", default=None, help="also write the tables to this Markdown file")
    a = p.parse_args(argv)
    names = a.scenes.split(",") if a.scenes else ithor_scenes()
    for n in names:
        scene_info(n)
    missing = [n for n in names if not (Path(a.real) / n / "scene.json").exists()]
    if missing:
        raise SystemExit(f"{a.real}: {len(missing)} scenes not built (e.g. {missing[0]})")
    real = [real_measures(Path(a.real) / n) for n in tqdm(names, desc="real", unit="scene")]
    proc = [procedural_measures(n) for n in tqdm(names, desc="procedural", unit="scene")]
    text = table(real, proc)
    print(text)
    if a.out:
        atomic_write_text(a.out, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


__all__ = ["procedural_measures", "real_measures", "table"]
