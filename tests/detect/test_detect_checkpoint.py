"""Detector checkpoints (issue 16 section 5): the newest two are kept, and a broken newest one never ends a
run: it is named in one line and training resumes from the one before, as if nothing had happened."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

import tsnav.detect.train as T
from tsnav.detect.data import load_frames
from tsnav.detect.model import DetectorConfig
from tsnav.detect.train import DetectorTrainConfig, load_model, read_meta, train_detector

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SMALL = DetectorConfig(widths=(8, 16, 32), dim=32)


@pytest.fixture(scope="module")
def frames(tiny_world):
    return load_frames(tiny_world, "train", max_states_per_scene=8, seed=0)


def _train_interrupted_at_step_5(tiny_world, out, cfg, frames, monkeypatch):
    """Train into ``out`` with a Ctrl-C during step 5: the trainer saves step 5 and stops."""
    calls = {"n": 0}
    make_batch = T.make_batch

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 6:
            raise KeyboardInterrupt
        return make_batch(*args, **kwargs)

    monkeypatch.setattr(T, "make_batch", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train_detector(tiny_world, out, cfg, SMALL, frames=frames, progress=False)
    monkeypatch.setattr(T, "make_batch", make_batch)


def test_truncated_newest_checkpoint_resumes_from_the_previous_one(tiny_world, frames, tmp_path, monkeypatch, capsys):
    cfg = DetectorTrainConfig(steps=6, batch_size=8, warmup=2, checkpoint_every=2, threads=1)
    train_detector(tiny_world, tmp_path / "a", cfg, SMALL, frames=frames, progress=False)
    kept = tmp_path / "a" / "checkpoints"
    assert sorted(p.name for p in kept.iterdir()) == ["ckpt_000000004", "ckpt_000000006"]
    assert sorted(p.name for p in (kept / "ckpt_000000006").iterdir()) == [
        "model.safetensors",
        "optimizer.safetensors",
        "state.json",
    ]
    assert read_meta(tmp_path / "a")["step"] == 6 and read_meta(kept / "ckpt_000000004")["step"] == 4

    _train_interrupted_at_step_5(tiny_world, tmp_path / "b", cfg, frames, monkeypatch)
    b = tmp_path / "b"
    assert read_meta(b)["step"] == 5 and read_meta(b / "checkpoints" / "ckpt_000000004")["step"] == 4
    broken = b / "checkpoints" / "ckpt_000000005" / "model.safetensors"
    broken.write_bytes(broken.read_bytes()[:50])
    with pytest.raises(ValueError, match="broken checkpoint file"):  # reading it alone: a one-line error
        load_model(b)
    capsys.readouterr()
    r = train_detector(tiny_world, b, DetectorTrainConfig(steps=6, threads=1), frames=frames, progress=False)
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("tsnav:")]
    assert len(err) == 1 and str(broken) in err[0] and "resuming from" in err[0] and "ckpt_000000004" in err[0], err
    assert (r.start_step, r.step) == (4, 6)
    assert (b / "checkpoints" / "ckpt_000000005.broken" / "model.safetensors").exists()  # kept, not listed
    ma, _ = load_model(tmp_path / "a")
    mb, _ = load_model(b)
    for (k, x), y in zip(ma.state_dict().items(), mb.state_dict().values()):
        torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6, msg=k)


def _to_legacy_folder(d):
    """Rewrite a detector folder by hand into the layout before checkpoints/: the newest checkpoint's files at
    the top (JSON named detector.json), the one before in previous/."""
    old, new = sorted((d / "checkpoints").iterdir())
    for src, dst in ((new, d), (old, d / "previous")):
        dst.mkdir(exist_ok=True)
        (src / "model.safetensors").rename(dst / "model.safetensors")
        (src / "optimizer.safetensors").rename(dst / "optimizer.safetensors")
        (src / "state.json").rename(dst / "detector.json")
    shutil.rmtree(d / "checkpoints")


def test_legacy_detector_folder_is_read_resumed_and_calibrated(tiny_world, frames, tmp_path, monkeypatch, capsys):
    """A detector folder written before the one layout (detector.json at the top, previous/) still loads with
    the same fingerprint, resumes exactly (also from previous/ when its newest file is broken), and new
    checkpoints go to checkpoints/ckpt_<step>."""
    cfg = DetectorTrainConfig(steps=6, batch_size=8, warmup=2, checkpoint_every=2, threads=1)
    train_detector(tiny_world, tmp_path / "a", cfg, SMALL, frames=frames, progress=False)
    ma, _ = load_model(tmp_path / "a")
    for name, broken in (("b", False), ("c", True)):
        d = tmp_path / name
        _train_interrupted_at_step_5(tiny_world, d, cfg, frames, monkeypatch)
        fp = read_meta(d)["fingerprint"]
        _to_legacy_folder(d)
        assert json.loads((d / "detector.json").read_text())["step"] == 5 and read_meta(d)["step"] == 5
        assert read_meta(d / "previous")["step"] == 4
        model, meta = load_model(d)
        assert meta["fingerprint"] == fp == T.weights_fingerprint(model, meta["temperature"])
        if broken:
            f = d / "model.safetensors"
            f.write_bytes(f.read_bytes()[:50])
        capsys.readouterr()
        r = train_detector(tiny_world, d, DetectorTrainConfig(steps=6, threads=1), frames=frames, progress=False)
        err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("tsnav:")]
        assert len(err) == int(broken) and (not broken or "previous" in err[0]), err
        assert (r.start_step, r.step) == ((4 if broken else 5), 6)
        assert [p.name for p in (d / "checkpoints").iterdir()] == ["ckpt_000000006"]
        mb, _ = load_model(d)
        for (k, x), y in zip(ma.state_dict().items(), mb.state_dict().values()):
            torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6, msg=k)
