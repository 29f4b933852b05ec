"""tsnav analyze false-boxes: each box's kind against a pixel-by-pixel reference on rendered frames, and end to end
on a built world, a table with planted false boxes comes back classified as planted."""

import json
import shutil

import numpy as np
import pytest
from script_helpers import load_analysis

from tsnav.data.detections import Detections, write_detections
from tsnav.data.reader import list_scenes, load_scene
from tsnav.detect.oracle import ground_truth
from tsnav.detect.quality import scene_targets
from tsnav.world.show import scene_poses


@pytest.fixture(scope="module")
def mod():
    return load_analysis("false_boxes")


def reference_kind(ids, box, cls, types, classes):
    """The kind of a box by looking at every pixel in turn (the definition in the module docstring)."""
    S = len(ids)
    x0, y0, x1, y1 = (min(max(int(round(float(v))), 0), S - 1) for v in box)
    inside = [int(ids[y][x]) for y in range(y0, y1 + 1) for x in range(x0, x1 + 1)]
    everywhere = [int(v) for row in ids for v in row]
    if any(types[v] == cls for v in inside):
        return "target in the box"
    if any(types[v] == cls for v in everywhere):
        return "target elsewhere"
    counts = {}
    for v in inside:
        counts[v] = counts.get(v, 0) + 1
    top = min(counts, key=lambda v: (-counts[v], v))  # the most pixels; ties to the smaller id, as np.unique
    surfaces = {"Floor": "floor", "Wall": "wall", "Ceiling": "ceiling"}
    if types[top] in surfaces:
        others = any(types[v] not in surfaces and v != 0 for v in counts)
        return f"{surfaces[types[top]]}, {'an object in the box' if others else 'bare'}"
    if types[top] == "":
        return "nothing"
    return "another target class" if types[top] in classes else "another object"


@pytest.fixture(scope="module")
def world(tiny_world, tmp_path_factory):
    root = tmp_path_factory.mktemp("fb")
    for p in list_scenes(tiny_world):
        shutil.copytree(p, root / p.name, ignore=shutil.ignore_patterns("detections_*", "features_*"))
    return root


def test_kinds_match_the_pixel_reference(mod, world):
    from tsnav.render.gl import Renderer

    folder = list_scenes(world)[0]
    scene = load_scene(folder)
    js = json.loads((folder / "scene.json").read_text())
    types = mod.instance_types(js["instances"])
    classes = set(scene.class_set.categories)
    r = Renderer(scene.image_size, 16)
    try:
        r.set_scene(np.array(js["parts"], np.float32), js.get("light"))
        _, _, ids = r.render(scene_poses(scene)[:: max(1, scene.num_states // 24)][:24])
    finally:
        r.release()
    rng = np.random.default_rng(0)
    S = scene.image_size
    seen = set()
    for frame in ids:
        for _ in range(12):
            x0, y0 = rng.integers(0, S, 2)
            box = [x0, y0, min(S - 1, x0 + rng.integers(0, S // 2)), min(S - 1, y0 + rng.integers(0, S // 2))]
            cls = scene.class_set.categories[int(rng.integers(scene.class_set.size))]
            want = reference_kind(frame.tolist(), box, cls, types, classes)
            assert mod.classify_box(frame, box, cls, types, classes) == want
            seen.add(want)
    assert len(seen) >= 4  # the draw reaches several kinds, not one


def test_planted_false_boxes_come_back_as_planted(mod, world, tmp_path, capsys):
    """In one scene, a state where a class the scene asks for is not in view gets a box of that class over another
    class's instance, and that class's own box in the same state scores too (a true box). Nothing else scores."""
    folder = next(p for p in list_scenes(world) if (ground_truth(load_scene(p)).present.sum(1) > 0).any())
    scene = load_scene(folder)
    gt = ground_truth(scene)
    targets = np.flatnonzero(scene_targets(scene))
    # a state showing some target class c2 (large enough to hold the box) and missing another target class c
    plant = None
    for r in np.flatnonzero(gt.pixels.max(1) >= 30):
        shown = [c for c in targets if gt.present[r, c]]
        missing = [c for c in targets if not gt.present[r, c] and gt.pixels[r, c] == 0]
        if shown and missing:
            plant = (int(r), int(missing[0]), int(max(shown, key=lambda c: gt.pixels[r, c])))
            break
    assert plant is not None
    C = scene.class_set.size
    S = scene.num_states
    scores = np.zeros((S, C), np.float32)
    boxes = np.full((S, C, 4), -1.0, np.float32)
    labels = np.full((S, C), -1, np.int16)
    r, c, c2 = plant
    scores[r, c], boxes[r, c], labels[r, c] = 0.95, gt.boxes[r, c2], c
    # a true box too: the shown class at its own box
    scores[r, c2], boxes[r, c2], labels[r, c2] = 0.95, gt.boxes[r, c2], c2
    table = Detections(
        keys=scene.keys,
        scores=scores,
        labels=labels,
        boxes=boxes,
        features=np.zeros((S, C, 4), np.float16),
        detector="test",
        fingerprint="planted",
        image_size=scene.image_size,
        class_set=scene.class_set.name,
    )
    write_detections(folder, "planted", table)
    out = tmp_path / "fb.json"
    png = tmp_path / "fb.png"
    argv = [
        "--data",
        str(world),
        "--from",
        "planted",
        "--scenes",
        folder.name,
        "--json",
        str(out),
        "--picture",
        str(png),
    ]
    assert mod.main(argv) == 0
    doc = json.loads(out.read_text())
    s = doc["scenes"][folder.name]
    assert (s["false"], s["true"], s["sampled"]) == (1, 1, 1)
    assert s["kinds"] == {"another target class": 1}
    names = scene.class_set.categories
    assert s["confusions"] == {f"{names[c]} on {names[c2]}": 1}
    assert doc["total"]["kinds_pct"] == {"another target class": 100.0}
    assert "1 false boxes (50.0 % of the boxes" in capsys.readouterr().out
    from PIL import Image

    with Image.open(png) as im:  # one example: one tile of the frame at twice its size, its caption below
        assert im.size == (2 * scene.image_size, 2 * scene.image_size + 30)


def test_bad_input_is_one_line(mod, world, tmp_path, capsys):
    for argv, msg in (
        (["--data", str(tmp_path / "none"), "--from", "x"], "no such folder"),
        (["--data", str(world), "--from", "x", "--c-target", "1.5"], "--c-target must be in (0, 1)"),
        (["--data", str(world), "--from", "x", "--scenes", "Nope"], "Nope not a complete scene"),
        (["--data", str(world), "--from", "x", "--picture", str(tmp_path / "p.png"), "--examples", "0"], "1 to 64"),
        (["--data", str(world), "--from", "nosuchtable"], "nosuchtable"),
    ):
        assert mod.main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert msg in err and len(err.splitlines()) == 1, err
