"""What lies under a detector's false boxes (issue 46, analysis): where a table scores a target class above
C_target in a state where no instance of that class is in view (the pixel rule of the world), the state is rendered
again with instance ids and the box's pixels say what the detector fired on:

* ``target in the box`` / ``target elsewhere``: an instance of the class shows, fewer pixels than the pixel rule asks;
* ``another target class``: most of the box is an object of another class of the class set (a Mug for an Apple);
* ``another object``: most of the box is an object outside the class set (furniture, a plan's furniture blob);
  for both, ``confusions`` counts the pairs (``"Sink on CounterTop"``: a Sink box on a CounterTop);
* ``floor`` / ``wall`` / ``ceiling``: most of the box is the room's surface, split by whether any object shows in
  the box at all (``, an object in the box``) or none (``, bare``);
* ``nothing``: the box lies on no geometry.

    tsnav analyze false-boxes --data WORLD --from TABLE [--split val] [--scenes A,B] [--c-target 0.7] \\
        [--sample 300] [--seed 0] [--json OUT] [--picture PNG] [--examples 12]

Only the classes a scene can ask for count (:func:`tsnav.detect.quality.scene_targets`), as in the switch report.
At most ``--sample`` false (state, class) pairs of each scene are rendered (drawn with ``--seed``); the shares are
weighted back to each scene's count. ``--picture`` draws ``--examples`` of the rendered false boxes (drawn at
random from the scenes' samples, spread over the scenes) on their frames, each captioned with its scene, class and
kind. The world must render as it was built: before classifying, the states where a target shows are rendered and
their pixel counts checked against the scene's own (a world built by another renderer or from another camera is
refused in one line). Ground truth is read here for analysis only.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_json
from ..constants import camera_height_of
from ..data.detections import load_detections
from ..data.reader import list_scenes, load_scene
from ..detect.oracle import ground_truth
from ..detect.quality import scene_targets
from ..world.show import scene_poses

SURFACES = {"Floor": "floor", "Wall": "wall", "Ceiling": "ceiling"}
KINDS = (
    "target in the box",
    "target elsewhere",
    "another target class",
    "another object",
    "floor, an object in the box",
    "floor, bare",
    "wall, an object in the box",
    "wall, bare",
    "ceiling, an object in the box",
    "ceiling, bare",
    "nothing",
)


def instance_types(instances: list[str]) -> list[str]:
    """The type of each instance id of a ``scene.json`` (``"Mug|+1.0|..."`` -> ``"Mug"``; ``""`` for id 0)."""
    return [str(n).split("|")[0] for n in instances]


def box_pixels(ids: np.ndarray, box) -> np.ndarray:
    """The instance ids inside box ``[x0, y0, x1, y1]`` (inclusive pixels, clipped to the frame)."""
    S = ids.shape[0]
    x0, y0, x1, y1 = (int(np.clip(round(float(v)), 0, S - 1)) for v in box)
    return ids[min(y0, y1) : max(y0, y1) + 1, min(x0, x1) : max(x0, x1) + 1]


def majority_type(sub: np.ndarray, types: list[str]) -> str:
    """The type of the instance that shows the most pixels of ``sub`` (ties to the smaller id)."""
    vals, counts = np.unique(sub, return_counts=True)
    return types[int(vals[np.argmax(counts)])]


def classify_box(ids: np.ndarray, box, cls: str, types: list[str], classes: set[str]) -> str:
    """The kind (:data:`KINDS`) of one false box ``[x0, y0, x1, y1]`` (inclusive pixels) of class ``cls`` on the
    instance-id frame ``ids``; ``types``: each instance id's type; ``classes``: the class set's names."""
    sub = box_pixels(ids, box)
    own = np.array([t == cls for t in types])
    if own[sub].any():
        return "target in the box"
    if own[ids].any():
        return "target elsewhere"
    top = majority_type(sub, types)
    if top in SURFACES:
        objects = [v for v in np.unique(sub) if types[int(v)] not in SURFACES and int(v) != 0]
        return f"{SURFACES[top]}, {'an object in the box' if objects else 'bare'}"
    if top == "":
        return "nothing"
    return "another target class" if top in classes else "another object"


def false_pairs(scene, table, c_target: float, gt=None) -> tuple[list[tuple[int, int]], int]:
    """The false (state, class) pairs of a scene's table (score above ``c_target``, no instance in view, a class
    the scene can ask for) and the number of true ones (``gt``: the scene's ground truth, computed when None)."""
    gt = ground_truth(scene) if gt is None else gt
    false, true = [], 0
    for c in np.flatnonzero(scene_targets(scene)):
        hi = table.scores[:, c] > c_target
        false += [(int(r), int(c)) for r in np.flatnonzero(hi & ~gt.present[:, c])]
        true += int((hi & gt.present[:, c]).sum())
    return false, true


def check_render(renderer, scene, gt, inst: list[str], height: float, n: int = 16) -> None:
    """Refuse a world that does not render as it was built: the stored pixel counts (``gt``, the scene's ground
    truth) of the target shown in ``n`` states must come back from the renderer (within 2 pixels)."""
    rows = np.flatnonzero(gt.present.any(1))[:n]
    if rows.size == 0:
        return
    _, _, ids = renderer.render(scene_poses(scene, rows), height=height)
    index = {name: k for k, name in enumerate(inst)}
    for r, frame in zip(rows, ids):
        c = int(np.flatnonzero(gt.present[r])[0])
        k = index.get(scene.object_ids[int(gt.instance[r, c])])
        got = int((frame == k).sum()) if k is not None else -1
        if abs(got - int(gt.pixels[r, c])) > 2:
            raise ValueError(
                f"{scene.name}: state {scene.keys[r]} renders {got} pixels of {scene.object_ids[int(gt.instance[r, c])]}"
                f" where the world stores {int(gt.pixels[r, c])}: the world was built by another renderer or camera"
            )


def scene_anatomy(
    renderer,
    folder: Path,
    source: str,
    c_target: float,
    sample: int,
    rng,
    examples: list | None = None,
    keep: int = 0,
    show_rng=None,
) -> dict:
    """One scene's false boxes, classified (a sample of at most ``sample`` rendered, the rest weighted back); ``keep``
    of them, drawn from the sample with ``show_rng``, are appended to ``examples`` as (scene, class, kind, frame,
    box)."""
    scene = load_scene(folder)
    js = scene.meta
    table = load_detections(folder, source)
    if table.class_set != scene.class_set.name:
        raise ValueError(
            f"{folder}: {source}'s table is for class set {table.class_set}, the scene {scene.class_set.name}"
        )
    height = camera_height_of(js)
    inst = [str(n) for n in js["instances"]]
    types = instance_types(inst)
    names = list(scene.class_set.categories)
    renderer.set_scene(np.array(js["parts"], dtype=np.float32), js.get("light"))
    gt = ground_truth(scene)
    check_render(renderer, scene, gt, inst, height)
    false, true = false_pairs(scene, table, c_target, gt)
    picked = (
        false if len(false) <= sample else [false[i] for i in sorted(rng.choice(len(false), sample, replace=False))]
    )
    kinds: Counter = Counter()
    by_class: Counter = Counter()
    confusions: Counter = Counter()
    poses = scene_poses(scene)
    classes = set(names)
    shown = set(show_rng.choice(len(picked), min(keep, len(picked)), replace=False).tolist()) if picked else set()
    for start in range(0, len(picked), 64):
        chunk = picked[start : start + 64]
        rgb, _, ids = renderer.render(poses[[r for r, _ in chunk]], height=height)
        for i, ((r, c), frame, image) in enumerate(zip(chunk, ids, rgb), start):
            kind = classify_box(frame, table.boxes[r, c], names[c], types, classes)
            if examples is not None and i in shown:
                examples.append((scene.name, names[c], kind, image, table.boxes[r, c].copy()))
            kinds[kind] += 1
            by_class[names[c]] += 1
            if kind in ("another target class", "another object"):
                confusions[f"{names[c]} on {majority_type(box_pixels(frame, table.boxes[r, c]), types)}"] += 1
    return {
        "pairs": int(scene.num_states * int(scene_targets(scene).sum())),
        "false": len(false),
        "true": true,
        "sampled": len(picked),
        "kinds": dict(kinds),
        "classes": dict(by_class),
        "confusions": dict(confusions),
    }


def draw_examples(examples: list, path: Path, cols: int = 4, scale: int = 2) -> None:
    """A grid of false boxes on their frames (``examples``: (scene, class, kind, frame, box)), each captioned."""
    from PIL import Image, ImageDraw

    from ..eval.video import _font

    S = examples[0][3].shape[0] * scale
    cols = min(cols, len(examples))
    cap = 30
    rows = (len(examples) + cols - 1) // cols
    sheet = Image.new("RGB", (cols * S, rows * (S + cap)), "white")
    font = _font(11)
    for i, (scene, cls, kind, frame, box) in enumerate(examples):
        x, y = (i % cols) * S, (i // cols) * (S + cap)
        tile = Image.fromarray(frame).resize((S, S), Image.NEAREST)
        d = ImageDraw.Draw(tile)
        x0, y0, x1, y1 = (float(v) * scale for v in box)
        d.rectangle([x0, y0, x1 + scale - 1, y1 + scale - 1], outline=(255, 0, 0), width=2)
        sheet.paste(tile, (x, y))
        d = ImageDraw.Draw(sheet)
        d.text((x + 3, y + S + 2), f"{scene.replace('FloorPlan_', '')}: {cls}", fill="black", font=font)
        d.text((x + 3, y + S + 15), kind, fill=(90, 90, 90), font=font)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial.png")
    sheet.save(tmp)
    tmp.replace(path)


def summarise(per_scene: dict) -> dict:
    """The scenes' counts added up, each scene's sample weighted back to its false pairs: the share of each kind,
    class and confusion among all false boxes, and the false share of the pairs and of the boxes above C_target."""
    pairs = sum(s["pairs"] for s in per_scene.values())
    false = sum(s["false"] for s in per_scene.values())
    true = sum(s["true"] for s in per_scene.values())
    weighted = {k: Counter() for k in ("kinds", "classes", "confusions")}
    for s in per_scene.values():
        w = s["false"] / s["sampled"] if s["sampled"] else 0.0
        for k in weighted:
            for name, n in s[k].items():
                weighted[k][name] += n * w
    share = lambda c: {k: round(100.0 * v / false, 2) for k, v in c.most_common()} if false else {}  # noqa: E731
    return {
        "pairs": pairs,
        "false": false,
        "true": true,
        "false_per_pair_pct": round(100.0 * false / pairs, 3) if pairs else None,
        "false_per_box_pct": round(100.0 * false / (false + true), 2) if false + true else None,
        "kinds_pct": share(weighted["kinds"]),
        "classes_pct": share(weighted["classes"]),
        "confusions_pct": dict(list(share(weighted["confusions"]).items())[:20]),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze false-boxes", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--data", required=True, type=Path, help="a built world (its scene.json parts are rendered)")
    ap.add_argument("--from", dest="source", required=True, help="the detection table's name")
    ap.add_argument("--split", default=None, help="only the scenes of this split")
    ap.add_argument("--scenes", default=None, help="comma-separated scene names (default: every scene of the split)")
    ap.add_argument("--c-target", type=float, default=0.7, help="the score a box must pass (default 0.7)")
    ap.add_argument("--sample", type=int, default=300, help="false boxes rendered per scene at most (default 300)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the sample")
    ap.add_argument("--json", type=Path, default=None, help="write the per-scene and summed figures here")
    ap.add_argument("--picture", type=Path, default=None, help="draw examples of the false boxes into this PNG")
    ap.add_argument("--examples", type=int, default=12, help="false boxes in the picture (default 12)")
    a = ap.parse_args(argv)

    def fail(msg: str) -> int:
        print(f"false-boxes: {msg}", file=sys.stderr)
        return 2

    if not 0 < a.c_target < 1:
        return fail(f"--c-target must be in (0, 1), got {a.c_target}")
    if a.sample < 1:
        return fail(f"--sample must be at least 1, got {a.sample}")
    if a.picture is not None and not 1 <= a.examples <= 64:
        return fail(f"--examples must be 1 to 64, got {a.examples}")
    if not a.data.is_dir():
        return fail(f"--data {a.data}: no such folder")
    folders = list_scenes(a.data, a.split)
    if a.scenes:
        want = [s.strip() for s in a.scenes.split(",") if s.strip()]
        have = {p.name: p for p in folders}
        missing = [s for s in want if s not in have]
        if missing:
            return fail(f"--scenes: {', '.join(missing[:3])} not a complete scene of {a.data}")
        folders = [have[s] for s in want]
    if not folders:
        return fail(f"{a.data}: no complete scene" + (f" of split {a.split}" if a.split else ""))
    from ..render.gl import Renderer, RendererUnavailable

    try:
        renderer = Renderer(load_scene(folders[0]).image_size, 16)
    except RendererUnavailable as e:
        return fail(str(e))
    rng = np.random.default_rng(a.seed)
    per_scene = {}
    examples: list = []
    keep = -(-a.examples // len(folders)) if a.picture is not None else 0  # per scene, rounded up
    show_rng = np.random.default_rng([a.seed, 1])  # apart from the sample's draws: a picture changes no figure
    try:
        for p in folders:
            per_scene[p.name] = scene_anatomy(
                renderer, p, a.source, a.c_target, a.sample, rng, examples, keep, show_rng
            )
            s = per_scene[p.name]
            print(f"{p.name}: {s['false']} false of {s['false'] + s['true']} boxes above {a.c_target}", flush=True)
    except (OSError, ValueError, KeyError) as e:
        return fail(str(e).strip("'\""))
    finally:
        renderer.release()
    total = summarise(per_scene)
    print(
        f"{len(per_scene)} scenes, {a.source} above {a.c_target}: {total['false']} false boxes "
        f"({total['false_per_box_pct']} % of the boxes, {total['false_per_pair_pct']} % of (state, target) pairs)"
    )
    for kind, pct in total["kinds_pct"].items():
        print(f"  {kind:<30} {pct:6.2f} %")
    if a.picture is not None and examples:
        pick = np.linspace(0, len(examples) - 1, min(a.examples, len(examples))).round().astype(int)
        draw_examples([examples[i] for i in pick], a.picture)
        print(f"wrote {a.picture}")
    if a.json:
        doc = {
            "source": a.source,
            "data": str(a.data),
            "split": a.split,
            "c_target": a.c_target,
            "sample": a.sample,
            "seed": a.seed,
            "kinds": list(KINDS),
            "total": total,
            "scenes": per_scene,
        }
        atomic_write_json(a.json, doc)
        print(f"wrote {a.json}")
    return 0
