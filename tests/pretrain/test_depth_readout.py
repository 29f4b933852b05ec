"""``tsnav analyze depth-readout`` (issue 47): a depth decoder on a frozen feature map and its file (the command and
the stop head's ``est-depth`` input: tests/analyze/test_stop_head.py)."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from tsnav.pretrain import depth_readout as dr
from tsnav.analyze import stop_head as sh

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_average_depth_by_hand():
    frame = np.zeros((64, 64), dtype=np.float32)
    frame[:2, :2] = [[1.0, 2.0], [3.0, np.nan]]  # one cell of 2x2 pixels; NaN reads as the far clip
    frame[2:4, :2] = 100.0  # clipped
    out = dr.average_depth(frame)
    assert out.shape == (dr.GRID, dr.GRID)
    assert out[0, 0] == pytest.approx((1 + 2 + 3 + dr.MAX_DEPTH) / 4)
    assert out[1, 0] == pytest.approx(dr.MAX_DEPTH)
    assert out[5, 5] == 0.0
    with pytest.raises(ValueError, match="multiple of"):
        dr.average_depth(np.zeros((48, 48)))


def test_readout_maps_each_token_to_its_patch():
    torch.manual_seed(0)
    model = dr.DepthReadout(8, 4, 4)
    feat = torch.randn(3, 8, 4, 4)
    with torch.no_grad():
        out = model(feat)
    assert out.shape == (3, dr.GRID, dr.GRID)
    assert float(out.min()) >= 0.0 and float(out.max()) <= dr.MAX_DEPTH
    # the (i, j) patch of the map is token i * 4 + j's prediction
    with torch.no_grad():
        x = model.embed(model.norm_in(feat.flatten(2).transpose(1, 2))) + model.pos
        for blk in model.blocks:
            x = blk(x)
        p = torch.sigmoid(model.pred(model.norm(x))) * dr.MAX_DEPTH
    k = dr.GRID // 4
    assert torch.allclose(out[1, 2 * k : 3 * k, 1 * k : 2 * k].reshape(-1), p[1, 2 * 4 + 1])
    with pytest.raises(ValueError, match="trained on"):
        model(torch.randn(1, 8, 2, 2))


def test_training_beats_the_mean_map_and_the_file_round_trips(tmp_path):
    # depth a function of the features: each token's first channel sets its patch's depth
    rng = np.random.default_rng(0)
    feat = rng.normal(size=(600, 8, 4, 4)).astype(np.float16)
    level = 1.0 + 0.8 * np.tanh(feat[:, 0].astype(np.float32))  # (N, 4, 4) in metres
    depth = np.repeat(np.repeat(level, dr.GRID // 4, axis=1), dr.GRID // 4, axis=2).astype(np.float16)
    model = dr.train_readout(feat, depth, epochs=8, batch=32)
    s = dr.score(model, feat, depth)
    mean_map_mae = float(np.abs(depth.astype(np.float32) - depth.astype(np.float32).mean(axis=0)).mean())
    assert s["mae_m"] < 0.5 * mean_map_mae
    path = tmp_path / "r.safetensors"
    dr.save_readout(path, model, {"features": "x"})
    again, meta = dr.load_readout(path)
    x = torch.from_numpy(feat[:5]).float()
    assert torch.equal(model(x), again(x)) and meta["features"] == "x"
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a file of tensors")
    with pytest.raises(ValueError, match="broken"):
        dr.load_readout(bad)
    with pytest.raises(ValueError, match="no such depth readout"):
        dr.load_readout(tmp_path / "missing.safetensors")
    with pytest.raises(ValueError, match="no frames"):
        dr.train_readout(feat[:0], depth[:0])
    few = dr.train_readout(feat[:10], depth[:10], epochs=1)  # fewer frames than a batch: one step on all of them
    assert not torch.equal(few.pred.weight, dr.DepthReadout(8, 4, 4).pred.weight)


def test_box_depth_of_maps_matches_its_reference():
    rng = np.random.default_rng(1)
    maps = rng.uniform(0.2, 6.0, (50, sh.DEPTH_GRID, sh.DEPTH_GRID)).astype(np.float32)
    corners = np.sort(rng.random((50, 2, 2)), axis=1)
    boxes = corners.transpose(0, 2, 1).reshape(50, 4)[:, [0, 2, 1, 3]]
    scores = np.where(rng.random(50) < 0.2, 0.0, rng.random(50))
    assert np.allclose(sh.box_depth(maps, boxes, scores), sh.box_depth_reference(maps, boxes, scores), atol=1e-5)


def test_scene_depth_maps_match_the_frame_by_frame_reference(tmp_path):
    """The whole scene at once (read_stack, one average over the stack) against one frame at a time, clipped and
    unclipped, flipped for a mirrored room; a missing frame or file is one line naming it."""
    import h5py

    rng = np.random.default_rng(0)
    frames = rng.uniform(0.1, 8.0, (6, 64, 64)).astype(np.float16)
    frames[2, :3, :5] = np.inf
    path = tmp_path / "depth.hdf5"
    keys = [f"k{i}" for i in range(6)]
    with h5py.File(path, "w") as f:
        for k, d in zip(keys, frames):
            f[k] = d
    for max_depth in (dr.MAX_DEPTH, None):
        for flip in (False, True):
            got = dr.scene_depth_maps(path, keys[::-1], max_depth=max_depth, flip=flip)
            ref = []
            for d in frames[::-1]:
                d = np.asarray(d, dtype=np.float32)
                d = d[:, ::-1] if flip else d
                if max_depth is not None:
                    d = np.clip(np.nan_to_num(d, nan=max_depth, posinf=max_depth), 0.0, max_depth)
                ref.append(d.reshape(dr.GRID, 2, dr.GRID, 2).mean(axis=(1, 3)))
            assert np.array_equal(got, np.stack(ref).astype(np.float16))
    with pytest.raises(ValueError, match="no dataset 'nope'") as e:
        dr.scene_depth_maps(path, ["k0", "nope"])
    assert len(str(e.value).splitlines()) == 1
    with pytest.raises(ValueError, match="no such depth file"):
        dr.scene_depth_maps(tmp_path / "none.hdf5", keys)
