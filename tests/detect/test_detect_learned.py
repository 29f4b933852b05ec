"""The learned grid detector: model, dense targets vs reference, batches, training (loss drops, exact
resume), calibration, tables."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil

import numpy as np
import pytest
import torch

from tsnav.constants import NUM_CATEGORIES
from tsnav.detect.data import FrameSet, load_frames, make_batch, read_images
from tsnav.detect.model import (
    DetectorConfig,
    GridDetector,
    LossWeights,
    default_config,
    dense_targets,
    dense_targets_reference,
    detection_loss,
    generalized_iou,
    pixel_to_unit,
    unit_to_pixel,
)
from tsnav.detect.train import (
    HARD_NEGATIVES,
    DetectorTrainConfig,
    apply_gains,
    batch_plan,
    calibrate,
    classes_with_pixels,
    default_train_steps,
    fit_temperature,
    hard_negative_rows,
    hard_negative_rows_reference,
    load_model,
    lr_at,
    predict,
    read_meta,
    repeat_factors,
    repeat_factors_reference,
    sample_weighted,
    train_detector,
)
from tsnav.checkpoint import BrokenCheckpoint

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def tiny_frames(tiny_world):
    return load_frames(tiny_world, "train", max_states_per_scene=24, seed=0)


def test_model_outputs():
    torch.manual_seed(0)
    m = GridDetector(DetectorConfig()).eval()
    x = m.normalize(torch.randint(0, 256, (3, 64, 64, 3), dtype=torch.uint8))
    logits, boxes, feats = m(x)
    assert logits.shape == (3, NUM_CATEGORIES) and boxes.shape == (3, NUM_CATEGORIES, 4)
    assert feats.shape == (3, NUM_CATEGORIES, 64)
    assert (boxes >= 0).all() and (boxes <= 1).all()
    assert (boxes[..., 2] >= boxes[..., 0]).all() and (boxes[..., 3] >= boxes[..., 1]).all()
    # The start bias makes every class unlikely (about the base rate of a class in view).
    assert torch.sigmoid(logits).max() < 0.2
    # Per class: the box and feature of the best cell.
    cl, cb, cf = m.dense(x)
    best = cl.argmax(-1)
    torch.testing.assert_close(boxes[1, 5], cb[1, 5, best[1, 5]].clamp(0, 1))
    torch.testing.assert_close(feats[2, 7], cf[2, best[2, 7]])
    torch.testing.assert_close(logits, torch.logsumexp(cl, -1) + m.class_bias)


def test_space_to_depth_stem():
    """stem 2: a 128px frame enters as 12 channels at 64px (pixel unshuffle, every pixel kept); the grid is
    that of a 64px frame; the first layer sees exactly the unshuffled pixels."""
    torch.manual_seed(0)
    cfg = DetectorConfig(image_size=128, stem=2)
    assert cfg.grid == 8 and DetectorConfig.from_dict(cfg.to_dict()) == cfg
    m = GridDetector(cfg).eval()
    assert m.backbone[0][0].in_channels == 12
    x = m.normalize(torch.randint(0, 256, (2, 128, 128, 3), dtype=torch.uint8))
    logits, boxes, feats = m(x)
    assert logits.shape == (2, NUM_CATEGORIES) and boxes.shape == (2, NUM_CATEGORIES, 4)
    cl, _, _ = m.dense(x)
    assert cl.shape == (2, NUM_CATEGORIES, 64)
    seen = []
    hook = m.backbone[0][0].register_forward_hook(lambda mod, inp, out: seen.append(inp[0]))
    m(x)
    hook.remove()
    # channel c * 4 + i * 2 + j of the unshuffled input is pixel (2y + i, 2x + j) of colour c
    torch.testing.assert_close(seen[0][:, 1 * 4 + 1 * 2 + 0], x[:, 1, 1::2, 0::2])
    with pytest.raises(ValueError, match="multiple of 16"):
        GridDetector(DetectorConfig(image_size=72, stem=2))
    assert DetectorConfig.from_dict({k: v for k, v in DetectorConfig().to_dict().items() if k != "stem"}).stem == 1


def test_fine_grid():
    """fine: a grid twice as fine (stride 4 after the stem); its cell feature is the smoothed sum of the
    upsampled coarse neck output and the stride-4 stage's lateral projection; the dense targets and loss work
    on it; old configs (no ``fine`` field) read as coarse."""
    torch.manual_seed(0)
    cfg = DetectorConfig(image_size=128, stem=2, widths=(8, 16, 32), dim=16, fine=True)
    assert cfg.grid == 16 and DetectorConfig.from_dict(cfg.to_dict()) == cfg
    m = GridDetector(cfg).eval()
    x = m.normalize(torch.randint(0, 256, (2, 128, 128, 3), dtype=torch.uint8))
    cl, cb, cf = m.dense(x)
    assert cl.shape == (2, NUM_CATEGORIES, 256) and cb.shape == (2, NUM_CATEGORIES, 256, 4)
    assert cf.shape == (2, 256, 16)
    u = torch.nn.functional.pixel_unshuffle(x, 2)
    stage2 = m.backbone[:3](u)
    coarse = m.neck(m.backbone[3:](stage2))
    assert stage2.shape[-1] == 16 and coarse.shape[-1] == 8
    up = coarse.repeat_interleave(2, dim=2).repeat_interleave(2, dim=3)  # nearest upsampling by hand
    expect = m.smooth(up + m.lateral(stage2)).flatten(2).transpose(1, 2)
    torch.testing.assert_close(cf, expect)
    # A 6x6-pixel object at the top left claims the fine cell that holds its centre.
    boxes = torch.tensor([[[2 / 128, 2 / 128, 8 / 128, 8 / 128]]])
    pos, _, _ = dense_targets(boxes, torch.tensor([[3]]), torch.tensor([[2]]), cfg.grid)
    assert pos[0, 3].nonzero().flatten().tolist() == [0]
    # Random objects on the fine grid, with area ties inside a class and untargeted padding: as the reference.
    g = torch.Generator().manual_seed(1)
    lo, hi = torch.rand(4, 9, 2, generator=g) * 0.7, torch.rand(4, 9, 2, generator=g) * 0.3
    rnd = torch.cat([lo, lo + hi], -1)
    rnd[:, 1] = rnd[:, 0]
    cat = torch.randint(-1, 4, (4, 9), generator=g)
    cat[:, 1] = cat[:, 0]
    st = torch.randint(0, 3, (4, 9), generator=g)
    for f, r in zip(dense_targets(rnd, cat, st, 16), dense_targets_reference(rnd.numpy(), cat.numpy(), st.numpy(), 16)):
        np.testing.assert_array_equal(f.numpy(), r)
    m.train()
    loss, terms = detection_loss(
        m, x[:1], torch.zeros(1, NUM_CATEGORIES, dtype=torch.bool), boxes, torch.tensor([[3]]), torch.tensor([[2]])
    )
    loss.backward()
    assert math.isfinite(terms["loss"]) and m.lateral.weight.grad.abs().sum() > 0
    # The default of a new 128px checkpoint is this fine, wider detector; below 128px the small one stays.
    best = default_config(128)
    assert best.fine and best.stem == 2 and best.widths == (32, 64, 128) and best.grid == 16
    assert default_config(64) == DetectorConfig() and default_config(96).stem == 1
    assert default_train_steps(128) == 9000 and default_train_steps(64) == DetectorTrainConfig.steps
    legacy = {k: v for k, v in DetectorConfig(image_size=128, stem=2).to_dict().items() if k != "fine"}
    assert DetectorConfig.from_dict(legacy).fine is False and DetectorConfig.from_dict(legacy).grid == 8


def test_box_conversions_and_giou():
    px = np.array([[0, 0, 63, 63], [10, 20, 10, 20], [3, 4, 7, 9]], np.float32)
    unit = pixel_to_unit(px, 64)
    np.testing.assert_allclose(unit[0], [0, 0, 1, 1])
    np.testing.assert_allclose(unit[1], [10 / 64, 20 / 64, 11 / 64, 21 / 64])
    np.testing.assert_allclose(unit_to_pixel(unit, 64), px, atol=1e-5)
    a = torch.tensor([[0.0, 0.0, 0.5, 0.5], [0.0, 0.0, 0.5, 0.5]])
    b = torch.tensor([[0.0, 0.0, 0.5, 0.5], [0.5, 0.5, 1.0, 1.0]])
    # Identical: 1. Touching corners: IoU 0, hull 1, union 0.5 -> 0 - (1 - 0.5) / 1 = -0.5.
    np.testing.assert_allclose(generalized_iou(a, b).numpy(), [1.0, -0.5], atol=1e-6)


def test_flip_moves_boxes_with_the_pixels():
    img = np.zeros((1, 64, 64, 3), np.uint8)
    img[0, 10:20, 5:12] = 255  # rows 10..19, columns 5..11
    present = np.zeros((1, NUM_CATEGORIES), bool)
    present[0, 3] = True
    boxes = np.zeros((1, NUM_CATEGORIES, 4), np.float32)
    boxes[0, 3] = pixel_to_unit(np.array([5, 10, 11, 19]), 64)
    obj = np.zeros((1, 2, 4), np.float32)
    obj[0, 0] = boxes[0, 3]
    fs = FrameSet(
        img, present, boxes, obj, np.array([[3, 4]], np.int16), np.array([[2, 0]], np.int8), ["x"], np.array([0, 1])
    )
    b = make_batch(fs, np.array([0, 0]), np.array([False, True]))
    assert (fs.images[0] == img[0]).all() and (fs.obj_boxes[0] == obj[0]).all()  # sources never modified
    ys, xs = np.nonzero(b.images[1, :, :, 0].numpy())
    np.testing.assert_allclose(
        unit_to_pixel(b.boxes[1, 3].numpy(), 64), [xs.min(), ys.min(), xs.max(), ys.max()], atol=1e-4
    )
    torch.testing.assert_close(b.obj_boxes[1, 0], b.boxes[1, 3])
    np.testing.assert_array_equal(b.boxes[0].numpy(), boxes[0])
    assert (b.boxes[1, 0] == 0).all() and (b.obj_boxes[1, 1] == 0).all()  # absent stays zero


def test_dense_targets_by_hand_and_against_reference(tiny_frames):
    # One 8x8 grid; object 0 (class 2, visible) covers cells x 0..1, y 0..0; object 1 (class 2, visible) is
    # a sliver inside cell (5, 5) away from its centre; object 2 (class 4, too few pixels) covers cell (7, 7).
    boxes = torch.tensor([[[0.0, 0.0, 0.25, 0.125], [0.63, 0.63, 0.65, 0.66], [0.875, 0.875, 1.0, 1.0]]])
    cat = torch.tensor([[2, 2, 4]])
    state = torch.tensor([[2, 2, 1]])
    pos, ign, tgt = dense_targets(boxes, cat, state, 8)
    assert pos[0, 2].nonzero().flatten().tolist() == [0, 1, 5 * 8 + 5]
    assert pos.sum() == 3 and ign[0, 4].nonzero().flatten().tolist() == [63] and ign.sum() == 1
    torch.testing.assert_close(tgt[0, 2, 1], boxes[0, 0])
    torch.testing.assert_close(tgt[0, 2, 45], boxes[0, 1])
    # Real frames (with flips): equal to the loop reference.
    b = make_batch(tiny_frames, np.arange(12), np.arange(12) % 2 == 1)
    fast = dense_targets(b.obj_boxes, b.obj_category, b.obj_state, 8)
    ref = dense_targets_reference(b.obj_boxes.numpy(), b.obj_category.numpy(), b.obj_state.numpy(), 8)
    for f, r in zip(fast, ref):
        np.testing.assert_array_equal(f.numpy(), r)
    assert fast[0].any()


def test_frames_and_targets(tiny_world, tiny_frames, tiny_scenes):
    fs = tiny_frames
    assert fs.images.dtype == np.uint8 and fs.images.shape[1:] == (64, 64, 3)
    assert len(fs) == fs.offsets[-1] == 24 * len(fs.scenes)
    assert set(fs.scenes) <= {s.name for s in tiny_scenes if s.meta["split"] == "train"}
    assert fs.present.any()
    b = fs.boxes[fs.present]
    assert (b[:, 2] > b[:, 0]).all() and (b[:, 3] > b[:, 1]).all() and (b >= 0).all() and (b <= 1).all()
    # Present exactly when a visible object of the class is in the frame.
    onehot = fs.obj_category[..., None] == np.arange(NUM_CATEGORIES)
    np.testing.assert_array_equal(fs.present, ((fs.obj_state == 2)[..., None] & onehot).any(1))
    assert ((fs.obj_state > 0) <= (fs.obj_category >= 0)).all()
    # Each scene's slice holds the frames of its drawn states, read one scene at a time (the reference)
    by_name = {x.name: x for x in tiny_scenes}
    for i, name in enumerate(fs.scenes):
        sc = by_name[name]
        rows = np.sort(np.random.default_rng([0, i]).choice(sc.num_states, 24, replace=False))
        np.testing.assert_array_equal(fs.images[fs.offsets[i] : fs.offsets[i + 1]], read_images(sc.path, sc.keys[rows]))
    s = next(x for x in tiny_scenes if x.name == fs.scenes[0])
    full = read_images(s.path, s.keys[:3])
    assert full.shape == (3, 64, 64, 3)
    with pytest.raises(Exception, match="lacks state"):
        read_images(s.path, ["9.99|9.99|0|0"])


def test_batch_plan_and_colour_gains():
    cfg = DetectorTrainConfig(batch_size=32, color_jitter=0.2, brightness=0.1)
    a, b = batch_plan(7, 100, cfg), batch_plan(7, 100, cfg)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)  # a function of (seed, step) only
    assert not np.array_equal(batch_plan(8, 100, cfg)[0], a[0])
    idx, flip, gains = a
    assert idx.shape == (32,) and flip.dtype == bool and gains.shape == (32, 3)
    assert (gains >= 0.8 * 0.9 - 1e-6).all() and (gains <= 1.2 * 1.1 + 1e-6).all()
    img = torch.tensor([[[[100, 200, 250]]]], dtype=torch.uint8)
    out = apply_gains(img, np.array([[1.0, 0.5, 1.2]], np.float32))
    np.testing.assert_allclose(out.numpy().reshape(-1), [100, 100, 255])  # 250 * 1.2 clipped


def test_repeat_factors_by_hand_and_against_reference():
    # 10 frames; class 0 in 5 (f 0.5), class 1 in 1 (f 0.1), class 2 never.
    present = np.zeros((10, 3), bool)
    present[:5, 0] = True
    present[4, 1] = True
    w = repeat_factors(present, 0.4)
    # class 0: max(1, sqrt(0.4 / 0.5)) = 1; class 1: sqrt(0.4 / 0.1) = 2; frame 4 shows both -> 2.
    np.testing.assert_allclose(w, [1, 1, 1, 1, 2, 1, 1, 1, 1, 1])
    np.testing.assert_allclose(repeat_factors(present, 0.0), np.ones(10))
    rng = np.random.default_rng(3)
    for t in (0.01, 0.1, 0.3):
        p = rng.random((200, 22)) < rng.uniform(0.005, 0.4, 22)
        np.testing.assert_allclose(repeat_factors(p, t), repeat_factors_reference(p, t))
    with pytest.raises(ValueError, match=">= 0"):
        repeat_factors(present, -0.1)
    with pytest.raises(ValueError, match="frames, classes"):
        repeat_factors(present[0], 0.1)


def test_weighted_batches_follow_the_weights():
    w = np.array([1.0, 0.0, 3.0, 4.0])
    u = np.array([0.0, 0.124, 0.125, 0.49, 0.5, 0.999])
    # cumulative 1, 1, 4, 8 of 8: [0, 1/8) -> row 0, [1/8, 1/2) -> row 2, [1/2, 1) -> row 3; row 1 never.
    np.testing.assert_array_equal(sample_weighted(u, w), [0, 0, 2, 2, 3, 3])
    ref = [next(i for i, c in enumerate(np.cumsum(w)) if x * w.sum() < c) for x in u]
    np.testing.assert_array_equal(sample_weighted(u, w), ref)
    cfg = DetectorTrainConfig(batch_size=4000)
    idx = batch_plan(5, 4, cfg, w)[0]
    np.testing.assert_allclose(np.bincount(idx, minlength=4) / 4000, w / w.sum(), atol=0.03)
    np.testing.assert_array_equal(idx, batch_plan(5, 4, cfg, w)[0])  # still a function of (seed, step)
    for bad in (np.zeros(3), np.array([1.0, -1.0]), np.array([])):
        with pytest.raises(ValueError, match="sampling weights"):
            sample_weighted(u, bad)


def test_lr_schedule():
    cfg = DetectorTrainConfig(steps=100, warmup=10, lr=1.0, min_lr_ratio=0.1)
    assert lr_at(0, cfg) == pytest.approx(0.1) and lr_at(9, cfg) == pytest.approx(1.0)
    assert lr_at(10, cfg) == pytest.approx(1.0) and lr_at(100, cfg) == pytest.approx(0.1)
    assert lr_at(55, cfg) == pytest.approx(0.1 + 0.9 * 0.5)


def test_training_loss_drops_and_resume_is_exact(tiny_world, tiny_frames, tmp_path):
    cfg = DetectorTrainConfig(steps=40, batch_size=16, lr=3e-3, warmup=5, log_every=5, checkpoint_every=100, threads=1)
    small = DetectorConfig(widths=(8, 16, 32), dim=32)

    def full_loss(model) -> float:
        with torch.no_grad():
            b = make_batch(tiny_frames, np.arange(len(tiny_frames)), np.zeros(len(tiny_frames)))
            return detection_loss(
                model.eval(), model.normalize(b.images), b.present, b.obj_boxes, b.obj_category, b.obj_state
            )[1]["loss"]

    torch.manual_seed(cfg.seed)
    before = full_loss(GridDetector(small))  # the initialisation train_detector starts from
    res = train_detector(tiny_world, tmp_path / "a", cfg, small, frames=tiny_frames, progress=False)
    assert (res.start_step, res.step) == (0, 40)
    after = full_loss(load_model(tmp_path / "a")[0])
    assert after < 0.75 * before, (before, after)
    hist = read_meta(tmp_path / "a")["history"]
    assert [h["step"] for h in hist] == list(range(5, 41, 5))

    # 6 steps at once == 3 steps, then resumed to 6 (weights, BatchNorm statistics and AdamW state).
    cfg6 = DetectorTrainConfig(steps=6, batch_size=8, warmup=2, checkpoint_every=100, threads=1)
    train_detector(tiny_world, tmp_path / "once", cfg6, small, frames=tiny_frames, progress=False)
    cfg3 = DetectorTrainConfig(steps=3, batch_size=8, warmup=2, checkpoint_every=100, threads=1)
    train_detector(tiny_world, tmp_path / "twice", cfg3, small, frames=tiny_frames, progress=False)
    r = train_detector(
        tiny_world, tmp_path / "twice", DetectorTrainConfig(steps=6, threads=1), frames=tiny_frames, progress=False
    )
    assert (r.start_step, r.step) == (3, 6)
    ma, _ = load_model(tmp_path / "once")
    mb, meta = load_model(tmp_path / "twice")
    assert meta["train"]["batch_size"] == 8  # the stored settings are kept on resume
    for (k, a), b in zip(ma.state_dict().items(), mb.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=k)
    # Already finished: returns at once.
    again = train_detector(
        tiny_world, tmp_path / "twice", DetectorTrainConfig(steps=6), frames=tiny_frames, progress=False
    )
    assert again.start_step == again.step == 6
    # Class-balanced sampling given for an existing checkpoint: applies from its step on and is recorded.
    tuned = train_detector(
        tiny_world,
        tmp_path / "twice",
        DetectorTrainConfig(steps=8, repeat_threshold=0.3),
        frames=tiny_frames,
        progress=False,
    )
    assert (tuned.start_step, tuned.step) == (6, 8)
    meta = read_meta(tmp_path / "twice")
    assert meta["train"]["repeat_threshold"] == 0.3
    assert meta["sampling_changes"] == [{"step": 6, "repeat_threshold": 0.3}]
    with pytest.raises(ValueError, match="repeat_threshold"):
        train_detector(
            tiny_world,
            tmp_path / "bad",
            DetectorTrainConfig(steps=2, repeat_threshold=-1.0),
            small,
            frames=tiny_frames,
            progress=False,
        )


def test_fit_temperature_recovers_a_known_temperature():
    rng = np.random.default_rng(0)
    z = rng.normal(0, 4, 20000)
    y = rng.random(len(z)) < 1 / (1 + np.exp(-z / 2.5))
    t = fit_temperature(z, y)
    assert t == pytest.approx(2.5, rel=0.08)
    # The fitted optimum is the minimum of a fine grid of the same objective (slow reference).
    grid = np.exp(np.linspace(math.log(0.5), math.log(10), 400))
    nll = [np.mean(np.logaddexp(0, z / g) - y * z / g) for g in grid]
    assert t == pytest.approx(grid[int(np.argmin(nll))], rel=0.01)


def test_learned_table(tiny_world, tiny_frames, tiny_scenes, tmp_path):
    from tsnav.detect.learned import LearnedDetector

    cfg = DetectorTrainConfig(steps=4, batch_size=8, warmup=1, threads=1)
    small = DetectorConfig(widths=(8, 16, 32), dim=32)
    train_detector(tiny_world, tmp_path / "c", cfg, small, frames=tiny_frames, progress=False)
    t = calibrate(tiny_world, tmp_path / "c", frames=tiny_frames)
    assert t > 0 and read_meta(tmp_path / "c")["temperature"] == t
    det = LearnedDetector.load(tmp_path / "c")
    assert det.temperature == t
    s = tiny_scenes[3]
    table = det.detect_scene(s, batch_size=64, chunk=100)
    np.testing.assert_array_equal(table.keys, s.keys)
    assert table.scores.shape == (s.num_states, NUM_CATEGORIES)
    assert table.features.shape == (s.num_states, NUM_CATEGORIES, 32)
    kept = table.scores >= det.min_score
    np.testing.assert_array_equal(table.labels >= 0, kept)
    assert (table.boxes[~kept] == -1).all()
    assert (table.boxes[kept] >= 0).all() and (table.boxes[kept] <= 63).all()
    # Scores are sigmoid(logit / T) of the model's logits.
    img = read_images(s.path, s.keys[:5])
    logits, _, _ = predict(det.model, img)
    np.testing.assert_allclose(table.scores[:5], 1 / (1 + np.exp(-logits / t)), rtol=1e-5, atol=1e-6)
    assert table.fingerprint == read_meta(tmp_path / "c")["fingerprint"]


def test_hard_negative_rows_by_hand_and_against_reference(tiny_frames):
    scores = np.array([[0.9, 0.1, 0.2], [0.6, 0.4, 0.0], [0.3, 0.2, 0.1], [0.1, 0.8, 0.1]])
    seen = np.array([[True, False, False], [False, False, False], [False, False, False], [False, True, False]])
    # frame 0: its 0.9 is a class in view; frame 1: class 0 scores 0.6 with nothing of it in view -> hard;
    # frame 2: nothing above 0.5; frame 3: the 0.8 is seen.
    np.testing.assert_array_equal(hard_negative_rows(scores, seen, 0.5), [False, True, False, False])
    np.testing.assert_array_equal(hard_negative_rows(scores, seen, 0.25), [False, True, True, False])
    rng = np.random.default_rng(0)
    sc, se = rng.random((300, 22)), rng.random((300, 22)) < 0.2
    for t in (0.3, 0.7, 0.95):
        np.testing.assert_array_equal(hard_negative_rows(sc, se, t), hard_negative_rows_reference(sc, se, t))
    with pytest.raises(ValueError, match="shape"):
        hard_negative_rows(sc, se[:, :3], 0.5)
    # A class counts as in view when any of its objects has a pixel, even below the presence threshold; padding
    # columns (category -1) and objects with no pixel do not count.
    n, z = 3, np.zeros
    fs = FrameSet(
        images=z((n, 8, 8, 3), np.uint8),
        present=z((n, NUM_CATEGORIES), bool),
        boxes=z((n, NUM_CATEGORIES, 4), np.float32),
        obj_boxes=z((n, 3, 4), np.float32),
        obj_category=np.array([[2, 5, -1]] * n, np.int16),
        obj_state=np.array([[1, 0, 2], [0, 2, 0], [0, 0, 0]], np.int8),
        scenes=["a"],
        offsets=np.array([0, n]),
    )
    fs.present[1, 5] = True
    fs.present[2, 7] = True  # present with no object column: still seen
    want = z((n, NUM_CATEGORIES), bool)
    want[0, 2] = want[1, 5] = want[2, 7] = True
    np.testing.assert_array_equal(classes_with_pixels(fs), want)
    seen = classes_with_pixels(tiny_frames)
    ref = tiny_frames.present.copy()
    for i, k in zip(*np.nonzero(tiny_frames.obj_state > 0)):
        if tiny_frames.obj_category[i, k] >= 0:
            ref[i, tiny_frames.obj_category[i, k]] = True
    np.testing.assert_array_equal(seen, ref)


def test_hard_negative_sampling_is_mined_once_recorded_and_resumes_exactly(tiny_world, tiny_frames, tmp_path):
    small = DetectorConfig(widths=(8, 16, 32), dim=32)
    base = dict(batch_size=8, warmup=2, checkpoint_every=2, threads=1)
    for name in ("once", "twice"):
        train_detector(
            tiny_world, tmp_path / name, DetectorTrainConfig(steps=3, **base), small, frames=tiny_frames, progress=False
        )
    model3 = load_model(tmp_path / "twice")[0]
    scores = 1 / (1 + np.exp(-predict(model3, tiny_frames.images)[0].astype(np.float64)))
    seen = classes_with_pixels(tiny_frames)
    # A threshold at the median of each frame's highest score of a class not in view makes about half the frames hard.
    thr = float(np.median(np.where(seen, 0.0, scores).max(axis=1)))
    expect = hard_negative_rows(scores, seen, thr)
    assert 0 < expect.sum() < len(expect)
    hard_cfg = dict(hard_negative_weight=5.0, hard_negative_threshold=thr)
    train_detector(
        tiny_world, tmp_path / "once", DetectorTrainConfig(steps=7, **hard_cfg), frames=tiny_frames, progress=False
    )
    rec = json.loads((tmp_path / "once" / HARD_NEGATIVES).read_text())
    assert rec["step"] == 3 and rec["threshold"] == thr and rec["scenes"] == list(tiny_frames.scenes)
    assert rec["rows"] == np.flatnonzero(expect).tolist() and rec["count"] == int(expect.sum())
    meta = read_meta(tmp_path / "once")
    assert meta["sampling_changes"] == [{"step": 3, "hard_negative_weight": 5.0, "hard_negative_threshold": thr}]
    assert meta["train"]["hard_negative_weight"] == 5.0 and meta["hard_negatives"] == int(expect.sum())
    # The same fine-tune interrupted after step 6 (its last checkpoint lost) resumes from step 6 with the rows
    # mined at step 3, not mined again, and ends on the same weights.
    train_detector(
        tiny_world, tmp_path / "twice", DetectorTrainConfig(steps=7, **hard_cfg), frames=tiny_frames, progress=False
    )
    shutil.rmtree(tmp_path / "twice" / "checkpoints" / "ckpt_000000007")
    assert read_meta(tmp_path / "twice")["step"] == 6
    r = train_detector(tiny_world, tmp_path / "twice", DetectorTrainConfig(steps=7), frames=tiny_frames, progress=False)
    assert (r.start_step, r.step) == (6, 7)
    assert json.loads((tmp_path / "twice" / HARD_NEGATIVES).read_text()) == rec
    assert len(read_meta(tmp_path / "twice")["sampling_changes"]) == 1
    for (k, a), b in zip(
        load_model(tmp_path / "once")[0].state_dict().items(), load_model(tmp_path / "twice")[0].state_dict().values()
    ):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=k)
    # The factor is used: the same fine-tune with weight 1 (the same draws, every frame weighing 1) ends elsewhere,
    # and its batches hold fewer hard frames than weight 5's.
    train_detector(
        tiny_world, tmp_path / "w1", DetectorTrainConfig(steps=3, **base), small, frames=tiny_frames, progress=False
    )
    train_detector(
        tiny_world,
        tmp_path / "w1",
        DetectorTrainConfig(steps=7, hard_negative_weight=1.0, hard_negative_threshold=thr),
        frames=tiny_frames,
        progress=False,
    )
    assert not torch.equal(load_model(tmp_path / "w1")[0].class_bias, load_model(tmp_path / "once")[0].class_bias)
    cfg = DetectorTrainConfig(batch_size=2000)
    share = [expect[batch_plan(3, len(expect), cfg, np.where(expect, w, 1.0))[0]].mean() for w in (1.0, 5.0)]
    h = expect.mean()
    assert share[0] == pytest.approx(h, abs=0.05) and share[1] == pytest.approx(5 * h / (5 * h + 1 - h), abs=0.05)
    # A resumed run needs the rows its sampling began with: a missing or damaged record is named, not mined again.
    saved = (tmp_path / "twice" / HARD_NEGATIVES).read_text()
    for damage in (None, "{", json.dumps({**rec, "step": 4}), json.dumps({**rec, "rows": [10**6]})):
        if damage is None:
            (tmp_path / "twice" / HARD_NEGATIVES).unlink()
        else:
            (tmp_path / "twice" / HARD_NEGATIVES).write_text(damage)
        with pytest.raises(BrokenCheckpoint, match=HARD_NEGATIVES):
            train_detector(
                tiny_world, tmp_path / "twice", DetectorTrainConfig(steps=8), frames=tiny_frames, progress=False
            )
    (tmp_path / "twice" / HARD_NEGATIVES).write_text(saved)
    # A new setting begins anew at its step: its rows are mined with the model of that step.
    train_detector(
        tiny_world,
        tmp_path / "twice",
        DetectorTrainConfig(steps=8, hard_negative_weight=2.0, hard_negative_threshold=thr),
        frames=tiny_frames,
        progress=False,
    )
    assert json.loads((tmp_path / "twice" / HARD_NEGATIVES).read_text())["step"] == 7
    assert read_meta(tmp_path / "twice")["sampling_changes"][-1]["step"] == 7
    for bad in (
        dict(hard_negative_weight=-1.0),
        dict(hard_negative_weight=float("inf")),
        dict(hard_negative_threshold=1.0),
    ):
        with pytest.raises(ValueError, match="hard_negative"):
            train_detector(
                tiny_world,
                tmp_path / "bad",
                DetectorTrainConfig(steps=2, **bad),
                small,
                frames=tiny_frames,
                progress=False,
            )


def test_presence_pos_weight_weighs_the_present_classes(tiny_world, tiny_frames, tmp_path):
    """The presence term with ``presence_pos_weight`` k is the cross-entropy with the present classes' terms
    multiplied by k, written out; a fine-tune that gives it (or ``focal_alpha``) is recorded from its step on."""
    torch.manual_seed(0)
    m = GridDetector(DetectorConfig(widths=(8, 16, 32), dim=32)).eval()
    x = m.normalize(torch.from_numpy(tiny_frames.images[:4]))
    present = torch.from_numpy(tiny_frames.present[:4])
    empty = torch.full((4, 1, 4), -1.0), torch.full((4, 1), -1, dtype=torch.long), torch.zeros(4, 1, dtype=torch.long)
    z = m(x)[0].detach().double()
    y = present.double()
    for k in (1.0, 3.0):
        _, terms = detection_loss(m, x, present, *empty, LossWeights(presence_pos_weight=k))
        by_hand = -(k * y * torch.log(torch.sigmoid(z)) + (1 - y) * torch.log(1 - torch.sigmoid(z))).mean()
        assert terms["bce"] == pytest.approx(float(by_hand), rel=1e-5), k
    base = dict(batch_size=8, warmup=2, checkpoint_every=2, threads=1)
    small = DetectorConfig(widths=(8, 16, 32), dim=32)
    train_detector(
        tiny_world, tmp_path / "d", DetectorTrainConfig(steps=2, **base), small, frames=tiny_frames, progress=False
    )
    train_detector(tiny_world, tmp_path / "d", DetectorTrainConfig(steps=4, **base), frames=tiny_frames, progress=False)
    assert "loss_changes" not in read_meta(tmp_path / "d")  # the defaults change nothing
    w = LossWeights(presence_pos_weight=4.0, focal_alpha=0.5)
    train_detector(
        tiny_world, tmp_path / "d", DetectorTrainConfig(steps=6, loss=w, **base), frames=tiny_frames, progress=False
    )
    meta = read_meta(tmp_path / "d")
    assert meta["loss_changes"] == [{"step": 4, **dataclasses.asdict(w)}]
    assert meta["train"]["loss"]["presence_pos_weight"] == 4.0 and meta["train"]["loss"]["focal_alpha"] == 0.5
