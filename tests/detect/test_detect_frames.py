"""A detector that sees finer frames than the agent: ``tsnav detect --frames DIR`` (train and detect on a build of the
same scenes at another side, write the world's tables with the boxes scaled to its frames), ``--retarget`` (an
existing checkpoint going on at another frame side) and :func:`tsnav.data.detections.rescale_detections`."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch

from tsnav.cli import main
from tsnav.data.detections import Detections, load_detections, rescale_detections
from tsnav.data.reader import list_scenes, load_scene
from tsnav.detect.model import DetectorConfig, GridDetector
from tsnav.detect.train import retarget_model

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def rescale_reference(det: Detections, size: int) -> np.ndarray:
    """Slow reference for :func:`rescale_detections`'s boxes: box by box, inclusive corners through the continuous
    box ``[x0, y0, x1 + 1, y1 + 1]``."""
    f = size / det.image_size
    out = det.boxes.astype(np.float64).copy()
    for s in range(det.num_states):
        for c in range(det.scores.shape[1]):
            if det.labels[s, c] < 0:
                continue
            x0, y0, x1, y1 = (float(v) for v in det.boxes[s, c])
            nx0, ny0 = x0 * f, y0 * f
            nx1, ny1 = max((x1 + 1) * f - 1, nx0), max((y1 + 1) * f - 1, ny0)
            out[s, c] = [min(max(v, 0.0), size - 1) for v in (nx0, ny0, nx1, ny1)]
    return out.astype(np.float32)


def random_table(rng, states: int = 40, size: int = 256) -> Detections:
    C = 22
    labels = np.where(rng.random((states, C)) < 0.6, np.arange(C)[None, :], -1).astype(np.int16)
    a = rng.uniform(0, size - 1, (states, C, 2))
    b = rng.uniform(0, size - 1, (states, C, 2))
    boxes = np.concatenate([np.minimum(a, b), np.maximum(a, b)], axis=-1)
    boxes = np.where((labels >= 0)[..., None], np.round(boxes), -1.0)
    return Detections(
        keys=np.array([f"{i:03d}|0|0|0" for i in range(states)]),
        scores=rng.random((states, C)),
        labels=labels,
        boxes=boxes,
        features=rng.standard_normal((states, C, 8)),
        detector="learned",
        config={"a": 1},
        image_size=size,
    )


def test_rescale_detections_matches_the_reference_and_round_trips():
    rng = np.random.default_rng(0)
    det = random_table(rng)
    for size in (128, 64, 300):
        small = rescale_detections(det, size)
        np.testing.assert_allclose(small.boxes, rescale_reference(det, size), atol=1e-4)
        kept = det.labels >= 0
        assert small.image_size == size and small.config == {"a": 1, "frames_size": 256}
        assert (small.boxes[kept] >= 0).all() and (small.boxes[kept] <= size - 1).all()
        assert (small.boxes[..., 2] >= small.boxes[..., 0]).all() and (small.boxes[..., 3] >= small.boxes[..., 1]).all()
        np.testing.assert_array_equal(small.boxes[~kept], det.boxes[~kept])  # no detection: the -1 box stays
        np.testing.assert_array_equal(small.scores, det.scores)
        np.testing.assert_array_equal(small.features, det.features)
    # Halving then doubling gives the boxes back exactly; the frames' side is the first table's
    t = random_table(np.random.default_rng(2), size=128)
    back = rescale_detections(rescale_detections(t, 256), 128)
    np.testing.assert_allclose(back.boxes, t.boxes, atol=1e-4)
    assert back.config["frames_size"] == 128
    with pytest.raises(ValueError, match="cannot rescale"):
        rescale_detections(det, 0)


def test_retarget_model_keeps_the_weights_and_the_presence_logit_of_a_grid_that_fires_alike():
    torch.manual_seed(0)
    old = GridDetector(DetectorConfig(image_size=64)).eval()
    meta = {"model": old.cfg.to_dict()}
    new = retarget_model(old, meta, 128, step=7).eval()
    assert new.cfg.image_size == 128 and new.cfg.grid == 2 * old.cfg.grid
    assert meta["model"]["image_size"] == 128 and meta["size_changes"] == [{"step": 7, "from": 64, "to": 128}]
    so, sn = old.state_dict(), new.state_dict()
    assert set(so) == set(sn)
    for k in so:
        if k != "class_bias":
            torch.testing.assert_close(sn[k], so[k])
    torch.testing.assert_close(sn["class_bias"], so["class_bias"] - math.log(4.0))
    # A frame whose every cell fires alike keeps its presence logit: logsumexp over 4x the cells, bias lowered log 4
    cells = torch.zeros(1, 22, old.cfg.grid**2)
    lo = torch.logsumexp(cells, -1) + so["class_bias"]
    ln = torch.logsumexp(torch.zeros(1, 22, new.cfg.grid**2), -1) + sn["class_bias"]
    torch.testing.assert_close(lo, ln)
    with pytest.raises(ValueError, match="multiple"):
        retarget_model(old, {}, 100, step=0)


@pytest.fixture(scope="module")
def worlds(tiny_world, tmp_path_factory):
    """(the tiny world at 64 px, the same scenes at 128 px, the first scene again at another seed)."""
    from tsnav.world.build import BuildConfig, build_dataset

    root = tmp_path_factory.mktemp("frames")
    low = root / "w64"
    shutil.copytree(tiny_world, low, ignore=shutil.ignore_patterns("detections_*", "features_*"))
    high = root / "w128"
    build_dataset(high, "tiny", cfg=BuildConfig.from_preset("tiny", image_size=128), progress=False)
    other = root / "seed1"
    first = list_scenes(low)[0].name
    build_dataset(other, "tiny", scenes=[first], cfg=BuildConfig.from_preset("tiny", seed=1), progress=False)
    return low, high, other


def test_frames_trains_on_the_finer_frames_and_writes_the_worlds_tables_in_its_pixels(worlds, tmp_path, capsys):
    low, high, _ = worlds
    ck = tmp_path / "ck"
    args = ["detect", "--data", str(low), "--frames", str(high), "--detector", "learned", "--checkpoint", str(ck)]
    args += ["--quiet", "--max-states-per-scene", "16", "--batch-size", "4", "--train-steps", "2", "--name", "hi"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "trained the detector 0 -> 2 steps" in out and "5 scenes written" in out and "box AP@0.5" in out
    meta = json.loads(next((ck / "checkpoints").glob("ckpt_*/state.json")).read_text())
    assert meta["model"]["image_size"] == 128
    for p in list_scenes(low):
        det, native = load_detections(p, "hi"), load_detections(high / p.name, "hi")
        assert det.image_size == 64 and native.image_size == 128 and det.fingerprint == native.fingerprint
        assert det.config["frames_size"] == 128
        np.testing.assert_array_equal(det.keys, load_scene(p).keys)
        np.testing.assert_array_equal(det.scores, native.scores)
        np.testing.assert_allclose(det.boxes, rescale_reference(native, 64), atol=1e-4)
    assert json.loads((low / "detectors" / "hi_eval_val.json").read_text())["name"] == "hi"
    assert main(args + ["--no-eval"]) == 0
    assert "0 scenes written, 5 already done" in capsys.readouterr().out
    # Interrupted after DIR's tables: they are rescaled, not made again
    native = {p.name: (high / p.name / "detections_hi.hdf5").stat().st_mtime_ns for p in list_scenes(low)}
    for p in list_scenes(low)[:2]:
        (p / "detections_hi.hdf5").unlink()
    assert main(args + ["--no-eval"]) == 0
    assert "2 scenes written, 3 already done (0 states)" in capsys.readouterr().out
    for p in list_scenes(low):
        assert (high / p.name / "detections_hi.hdf5").stat().st_mtime_ns == native[p.name]
        np.testing.assert_allclose(
            load_detections(p, "hi").boxes, rescale_reference(load_detections(high / p.name, "hi"), 64), atol=1e-4
        )


def test_retarget_goes_on_at_the_new_side_and_is_needed_for_it(worlds, tmp_path, capsys):
    low, high, _ = worlds
    ck = tmp_path / "ck"
    base = ["detect", "--detector", "learned", "--checkpoint", str(ck), "--quiet", "--no-eval", "--no-calibrate"]
    base += ["--max-states-per-scene", "16", "--batch-size", "4"]
    assert main(base + ["--data", str(low), "--train-steps", "2", "--name", "a"]) == 0
    capsys.readouterr()
    assert main(base + ["--data", str(high), "--train-steps", "3", "--name", "b"]) == 2
    assert "--retarget" in capsys.readouterr().err
    assert main(base + ["--data", str(high), "--train-steps", "3", "--name", "b", "--retarget"]) == 0
    meta = json.loads(sorted((ck / "checkpoints").glob("ckpt_*/state.json"))[-1].read_text())
    assert meta["step"] == 3 and meta["model"]["image_size"] == 128
    assert meta["size_changes"] == [{"step": 2, "from": 64, "to": 128}]
    assert load_detections(list_scenes(high)[0], "b").image_size == 128
    assert (
        main(
            base
            + [
                "--data",
                str(low),
                "--train-steps",
                "2",
                "--name",
                "c",
                "--retarget",
                "--checkpoint",
                str(tmp_path / "new"),
            ]
        )
        == 2
    )
    assert "holds none" in capsys.readouterr().err


@pytest.mark.parametrize(
    "extra, frames, message",
    [
        (["--detector", "oracle"], "high", "needs --detector learned or shipped"),
        (["--detector", "learned", "--mirror"], "high", "does not go with --mirror"),
        (["--detector", "learned"], "missing", "no such dataset folder"),
        (["--detector", "learned"], "self", "is --data itself"),
        (["--detector", "learned"], "other", "other states"),
    ],
)
def test_frames_refuses_what_cannot_go_with_it(worlds, tmp_path, capsys, extra, frames, message):
    low, high, other = worlds
    where = {"high": high, "missing": tmp_path / "nope", "self": low, "other": other}[frames]
    args = ["detect", "--data", str(low), "--frames", str(where), "--quiet", "--no-eval", "--name", "x"] + extra
    assert main(args + ["--checkpoint", str(tmp_path / "ck")]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_a_shipped_detector_of_finer_frames_reads_them_through_frames(worlds, tmp_path, monkeypatch, capsys):
    """A shipped detector that reads 128-px frames writes a 64-px world's tables through --frames (boxes scaled, as
    a learned one's); without --frames it is refused in one line that names the way."""
    from tsnav.detect import shipped

    low, high, _ = worlds
    ck = tmp_path / "ck"
    args = ["detect", "--data", str(low), "--frames", str(high), "--detector", "learned", "--checkpoint", str(ck)]
    args += ["--quiet", "--no-eval", "--max-states-per-scene", "16", "--batch-size", "4", "--train-steps", "2"]
    assert main(args + ["--name", "trained"]) == 0
    monkeypatch.setitem(shipped.SHIPPED, "tinyhi", ck)
    base = ["detect", "--data", str(low), "--detector", "shipped", "--shipped", "tinyhi", "--quiet", "--no-eval"]
    capsys.readouterr()
    assert main(base + ["--name", "sh"]) == 2
    err = capsys.readouterr().err
    assert "reads 128x128 frames" in err and "--frames DIR" in err and len(err.strip().splitlines()) == 1
    assert main(base + ["--name", "sh", "--frames", str(high)]) == 0
    for p in list_scenes(low):
        det, native = load_detections(p, "sh"), load_detections(high / p.name, "sh")
        assert det.image_size == 64 and native.image_size == 128
        np.testing.assert_array_equal(det.scores, load_detections(p, "trained").scores)  # the same weights
        np.testing.assert_allclose(det.boxes, rescale_reference(native, 64), atol=1e-4)
