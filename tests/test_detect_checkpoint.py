"""Detector checkpoints (issue 16 section 5): the newest two are kept, and a broken newest one never ends a
run: it is named in one line and training resumes from the one before, as if nothing had happened."""

from __future__ import annotations

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


def test_truncated_newest_checkpoint_resumes_from_the_previous_one(tiny_world, frames, tmp_path, monkeypatch, capsys):
    cfg = DetectorTrainConfig(steps=6, batch_size=8, warmup=2, checkpoint_every=2, threads=1)
    train_detector(tiny_world, tmp_path / "a", cfg, SMALL, frames=frames, progress=False)
    assert read_meta(tmp_path / "a")["step"] == 6 and read_meta(tmp_path / "a" / "previous")["step"] == 4

    calls = {"n": 0}
    make_batch = T.make_batch

    def interrupted(*args, **kwargs):  # Ctrl-C during step 5: the trainer saves step 5 and stops
        calls["n"] += 1
        if calls["n"] == 6:
            raise KeyboardInterrupt
        return make_batch(*args, **kwargs)

    monkeypatch.setattr(T, "make_batch", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train_detector(tiny_world, tmp_path / "b", cfg, SMALL, frames=frames, progress=False)
    monkeypatch.setattr(T, "make_batch", make_batch)
    b = tmp_path / "b"
    assert read_meta(b)["step"] == 5 and read_meta(b / "previous")["step"] == 4
    broken = b / "model.safetensors"
    broken.write_bytes(broken.read_bytes()[:50])
    with pytest.raises(ValueError, match="broken checkpoint file"):  # reading it alone: a one-line error
        load_model(b)
    capsys.readouterr()
    r = train_detector(tiny_world, b, DetectorTrainConfig(steps=6, threads=1), frames=frames, progress=False)
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("tsnav:")]
    assert len(err) == 1 and str(broken) in err[0] and "resuming from" in err[0] and "previous" in err[0], err
    assert (r.start_step, r.step) == (4, 6)
    assert (b / "model.safetensors.broken").exists()
    ma, _ = load_model(tmp_path / "a")
    mb, _ = load_model(b)
    for (k, x), y in zip(ma.state_dict().items(), mb.state_dict().values()):
        torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6, msg=k)
