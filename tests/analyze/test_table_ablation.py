"""tsnav analyze table-ablation: each kind of mended table changes only the cells it names, as a cell-by-cell rule says."""

from dataclasses import replace

import numpy as np
import pytest
from script_helpers import load_analysis

from tsnav.data.detections import Detections


@pytest.fixture(scope="module")
def mod():
    return load_analysis("table_ablation")


def _table(rng, S, score_lo=0.0):
    scores = rng.uniform(score_lo, 1.0, (S, 22)).astype(np.float32)
    keep = scores >= 0.05
    labels = np.where(keep, np.arange(22)[None, :], -1).astype(np.int16)
    boxes = np.where(keep[..., None], rng.uniform(0, 100, (S, 22, 4)), -1.0).astype(np.float32)
    return Detections(
        keys=np.array([f"s{i}" for i in range(S)]),
        scores=scores,
        labels=labels,
        boxes=boxes,
        features=rng.normal(size=(S, 22, 4)).astype(np.float16),
    )


def expected(L, O, present, kind):
    """The rule of each kind, one cell at a time."""
    sc, lb, bx = L.scores.copy(), L.labels.copy(), L.boxes.copy()
    for i in range(sc.shape[0]):
        for c in range(22):
            p = present[i, c]
            if kind in ("nofp", "both") and not p:
                sc[i, c], lb[i, c], bx[i, c] = 0.0, -1, -1.0
            if kind in ("recall", "both") and p:
                sc[i, c], lb[i, c], bx[i, c] = O.scores[i, c], O.labels[i, c], O.boxes[i, c]
            if kind in ("score", "raise") and p and (kind == "score" or O.scores[i, c] > L.scores[i, c]):
                sc[i, c], lb[i, c] = O.scores[i, c], O.labels[i, c]
                if L.labels[i, c] < 0:
                    bx[i, c] = O.boxes[i, c]
            if kind == "box" and p and L.labels[i, c] >= 0:
                bx[i, c] = O.boxes[i, c]
    return sc, lb, bx


def test_each_kind_follows_its_rule(mod):
    rng = np.random.default_rng(0)
    L, O = _table(rng, 6), _table(rng, 6)
    O.scores[:, ::2] = 0.0  # the oracle scores nothing where nothing is in view
    O.labels[:, ::2], O.boxes[:, ::2] = -1, -1.0
    present = O.scores > 0
    for kind in mod.KINDS:
        got = mod.mend(L, O, present, kind)
        sc, lb, bx = expected(L, O, present, kind)
        assert np.array_equal(got.scores, sc) and np.array_equal(got.labels, lb), kind
        assert np.array_equal(got.boxes, bx) and np.array_equal(got.features, L.features), kind
        assert got.config["table_ablation"]["kind"] == kind
    both = mod.mend(L, O, present, "both", oracle_features=True)
    assert np.array_equal(both.features, O.features)


def test_refuses_tables_of_other_states(mod):
    rng = np.random.default_rng(1)
    L, O = _table(rng, 3), _table(rng, 4)
    with pytest.raises(ValueError, match="same states"):
        mod.mend(L, O, np.zeros((3, 22), bool), "nofp")
    with pytest.raises(ValueError, match="kind"):
        mod.mend(L, L, np.zeros((3, 22), bool), "all")


def test_state_recall_on_real_rooms_against_cell_loops(mod, tiny_real_learned4):
    """``state_recall`` on the tiny real rooms with the shipped detector's tables, against the same counts made one
    cell at a time; the oracle against itself recalls every near cell."""
    from tsnav.data.detections import load_detections
    from tsnav.data.reader import list_scenes, load_scene
    from tsnav.detect.oracle import ground_truth, oracle_detections
    from tsnav.detect.quality import scene_targets

    dirs = list_scenes(tiny_real_learned4)
    scenes = [load_scene(d) for d in dirs]
    tables = [load_detections(d, "learned4") for d in dirs]
    oracles = [oracle_detections(s) for s in scenes]
    got = mod.state_recall(scenes, tables, oracles)
    near = near_hit = far = far_below = absent = absent_fp = 0
    for s, d, o in zip(scenes, tables, oracles):
        present, targets = ground_truth(s).present, scene_targets(s)
        for i in range(s.num_states):
            for c in range(22):
                if not targets[c]:
                    continue
                if present[i, c] and o.scores[i, c] >= 0.7:
                    near += 1
                    near_hit += d.scores[i, c] >= 0.7
                elif present[i, c]:
                    far += 1
                    far_below += d.scores[i, c] < o.scores[i, c]
                else:
                    absent += 1
                    absent_fp += d.scores[i, c] > 0.7
    assert near > 0 and far > 0 and absent > 0
    assert got["near_cells"] == near and got["far_cells"] == far
    assert got["near_recall"] == pytest.approx(near_hit / near)
    assert got["far_below_oracle"] == pytest.approx(far_below / far)
    assert got["absent_above"] == pytest.approx(absent_fp / absent)
    itself = mod.state_recall(scenes, oracles, oracles)
    assert itself["near_recall"] == 1.0 and itself["far_below_oracle"] == 0.0 and itself["absent_above"] == 0.0


def test_shift_and_borrowed_features(mod):
    """``shifted`` raises every logit by b (a score of 0.5 becomes sigmoid(b)); ``with_features`` swaps the
    features only, and refuses a table of other states."""
    rng = np.random.default_rng(2)
    L, A = _table(rng, 5, score_lo=0.01), _table(rng, 5)
    for b in (0.0, 1.0, -2.0):
        got = mod.shifted(L, b).scores.astype(np.float64)
        z = np.log(L.scores.astype(np.float64)) - np.log1p(-L.scores.astype(np.float64))
        np.testing.assert_allclose(got, 1 / (1 + np.exp(-(z + b))), rtol=1e-6)
    half = replace(L, scores=np.full_like(L.scores, 0.5))
    np.testing.assert_allclose(mod.shifted(half, 1.0).scores, 1 / (1 + np.exp(-1.0)), rtol=1e-6)
    h = mod.with_features(L, A)
    assert np.array_equal(h.features, A.features) and np.array_equal(h.scores, L.scores)
    assert np.array_equal(h.boxes, L.boxes) and np.array_equal(h.labels, L.labels)
    with pytest.raises(ValueError, match="same states"):
        mod.with_features(L, _table(rng, 4))


def test_flip_average_cell_by_cell(mod):
    """``flip_averaged``: per cell, sigmoid of the mean of the two logits (the geometric mean of the odds); labels
    where either table has one; boxes and features the first table's; refuses a table not made from flipped frames
    and one of other states."""
    import math

    rng = np.random.default_rng(4)
    L, M = _table(rng, 6, score_lo=0.01), _table(rng, 6, score_lo=0.01)
    M = replace(
        M,
        labels=np.where(rng.uniform(size=M.labels.shape) < 0.5, M.labels, -1).astype(np.int16),
        config={"mirror": True},
    )
    got = mod.flip_averaged(L, M)
    for i in range(6):
        for c in range(22):
            a, b = float(L.scores[i, c]), float(M.scores[i, c])
            odds = math.sqrt(a / (1 - a) * b / (1 - b))
            assert got.scores[i, c] == pytest.approx(odds / (1 + odds), rel=1e-5)
            assert got.labels[i, c] == (L.labels[i, c] if L.labels[i, c] >= 0 else M.labels[i, c])
    assert np.array_equal(got.boxes, L.boxes) and np.array_equal(got.features, L.features)
    same = mod.flip_averaged(L, replace(L, config={"mirror": True}))
    np.testing.assert_allclose(same.scores, L.scores, rtol=1e-5)
    with pytest.raises(ValueError, match="flipped frames"):
        mod.flip_averaged(L, replace(M, config={}))
    with pytest.raises(ValueError, match="same states"):
        mod.flip_averaged(L, replace(_table(rng, 5), config={"mirror": True}))


def test_near_recall_by_class_and_band_against_cell_loops(mod, tiny_real_learned4):
    """``near_recall_by`` counts the same near cells as ``state_recall``, split per class and per pixel band, as a
    cell-by-cell loop does."""
    from tsnav.data.detections import load_detections
    from tsnav.data.reader import list_scenes, load_scene
    from tsnav.detect.oracle import ground_truth, oracle_detections
    from tsnav.detect.quality import scene_targets

    dirs = list_scenes(tiny_real_learned4)
    scenes = [load_scene(d) for d in dirs]
    tables = [load_detections(d, "learned4") for d in dirs]
    oracles = [oracle_detections(s) for s in scenes]
    got = mod.near_recall_by(scenes, tables, oracles)
    cn, ch = np.zeros(22, int), np.zeros(22, int)
    bn, bh = np.zeros(len(mod.PIXEL_BANDS), int), np.zeros(len(mod.PIXEL_BANDS), int)
    for s, d, o in zip(scenes, tables, oracles):
        g, targets = ground_truth(s), scene_targets(s)
        for i in range(s.num_states):
            for c in range(22):
                if targets[c] and g.present[i, c] and o.scores[i, c] >= 0.7:
                    b = max(k for k, lo in enumerate(mod.PIXEL_BANDS) if g.pixels[i, c] >= lo)
                    hit = d.scores[i, c] >= 0.7
                    cn[c] += 1
                    ch[c] += hit
                    bn[b] += 1
                    bh[b] += hit
    assert cn.sum() > 0 and 0 < ch.sum() <= cn.sum()
    assert np.array_equal(got["class_near"], cn) and np.array_equal(got["class_hit"], ch)
    assert np.array_equal(got["band_near"], bn) and np.array_equal(got["band_hit"], bh)
    r = mod.state_recall(scenes, tables, oracles)
    assert r["near_cells"] == cn.sum() and r["near_recall"] == pytest.approx(ch.sum() / cn.sum())


def test_recall_curve_command(mod, tiny_real_learned4, tmp_path, capsys):
    """``--recall T --curve`` prints one line per shift (recall cannot fall as the logits rise) and ``--by-class``
    its breakdown; a bad ``--curve`` is one clear error."""
    import re

    from tsnav.data.detections import write_detections
    from tsnav.data.reader import list_scenes, load_scene
    from tsnav.detect.oracle import oracle_detections

    import shutil

    world = tmp_path / "world"
    shutil.copytree(tiny_real_learned4, world)  # the session fixture stays as it was
    for d in list_scenes(world):
        write_detections(d, "oracle", oracle_detections(load_scene(d)))
    assert mod.main(["--data", str(world), "--recall", "learned4", "--curve=-1,0,1", "--by-class"]) == 0
    out = capsys.readouterr().out
    rec = [float(x) for x in re.findall(r"scoring >= 0.7 ([0-9.]+) %", out)]
    assert len(rec) == 3 and rec[0] <= rec[1] <= rec[2] and rec[0] < rec[2]
    assert "learned4 -1:" in out and "learned4 +1:" in out and "per class" in out and "per band" in out
    assert mod.main(["--data", str(world), "--recall", "learned4", "--curve", "a"]) == 2
    assert "--curve 'a'" in capsys.readouterr().err

    # --misses: every drawn cell is a near cell the table scores under 0.7
    from PIL import Image

    from tsnav.constants import TARGET_CATEGORIES
    from tsnav.data.detections import load_detections
    from tsnav.detect.oracle import ground_truth

    dirs = list_scenes(world)
    scenes = [load_scene(d) for d in dirs]
    tables = [load_detections(d, "learned4") for d in dirs]
    oracles = [load_detections(d, "oracle") for d in dirs]
    counts = {c: len(mod.near_misses(scenes, tables, oracles, c)) for c in range(22)}
    c = max(counts, key=counts.get)
    assert counts[c] > 0
    for s, i, score, px, dist, box in mod.near_misses(scenes, tables, oracles, c):
        g = ground_truth(s)
        assert g.present[i, c] and load_detections(s.path, "oracle").scores[i, c] >= 0.7 and score < 0.7
        assert px == g.pixels[i, c] and np.array_equal(box, g.boxes[i, c])
    png = tmp_path / "misses.png"
    assert (
        mod.main(
            ["--data", str(world), "--recall", "learned4", "--misses", str(png), "--misses-class", TARGET_CATEGORIES[c]]
        )
        == 0
    )
    n = min(counts[c], 24)
    assert f"{n} missed near" in capsys.readouterr().out
    w, h = Image.open(png).size
    assert w == 6 * (2 * scenes[0].image_size + 4) and h == -(-n // 6) * (2 * scenes[0].image_size + 16)
    assert (
        mod.main(["--data", str(world), "--recall", "learned4", "--misses", str(png), "--misses-class", "Unicorn"]) == 2
    )
    assert "not a target class" in capsys.readouterr().err
    assert mod.main(["--data", str(world), "--by-class"]) == 2
    assert "give it" in capsys.readouterr().err
