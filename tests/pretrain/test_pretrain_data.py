"""Pretraining images: train split only, order, labels, batched flip / crop applied to RGB and depth alike."""

import numpy as np
import pytest
import torch

from tsnav.constants import CATEGORY_INDEX
from tsnav.data.reader import load_scene
from tsnav.pretrain.data import (
    DEPTH_MEAN,
    DEPTH_STD,
    AugmentConfig,
    RGBDImages,
    apply_augment,
    clean_depth,
    denormalize_rgb,
    draw_augment,
    normalize_rgb,
    prepare_batch,
)
from tsnav.pretrain.synthetic import write_synthetic_dataset


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("synth"), size=16)


def test_train_split_only_sorted_keys_and_streaming_equals_preload(root):
    import h5py

    imgs = RGBDImages(root, "train", img_size=16)
    assert [p.name for p in imgs.scenes] == ["Synth1", "Synth2"]
    assert len(imgs) == 64 and imgs.offsets.tolist() == [0, 32, 64]
    scene, key = imgs.key(33)
    assert scene.name == "Synth2" and key == sorted(load_scene(scene).keys.tolist())[1]
    b = imgs.get([33, 0])
    with h5py.File(scene / "images.hdf5") as fi, h5py.File(scene / "depth.hdf5") as fd:
        assert torch.equal(b["rgb"][0], torch.from_numpy(fi[key][()]).permute(2, 0, 1))
        np.testing.assert_allclose(b["depth"][0, 0].numpy(), fd[key][()], atol=5e-3)  # float16 in memory
    s = RGBDImages(root, "train", img_size=16, preload=False).get([33, 0])
    assert torch.equal(s["rgb"], b["rgb"])
    with pytest.raises(ValueError, match="no complete test scene"):
        RGBDImages(root, "test", img_size=16)


def test_resize_and_labels(root):
    imgs = RGBDImages(root, "val", img_size=8, labels=True)
    b = imgs.get(np.arange(len(imgs)))
    assert b["rgb"].shape == (32, 3, 8, 8) and b["depth"].shape == (32, 1, 8, 8)
    scene = load_scene(imgs.scenes[0])
    want = np.zeros((scene.num_states, 22))
    for j, c in enumerate(scene.object_category):
        want[:, c] = np.maximum(want[:, c], scene.pixels[:, j] >= 1)
    np.testing.assert_array_equal(b["labels"].numpy(), want)


def test_flip_moves_rgb_and_depth_together():
    rgb = torch.arange(2 * 3 * 4 * 4, dtype=torch.float32).reshape(2, 3, 4, 4)
    depth = torch.arange(2 * 16, dtype=torch.float32).reshape(2, 1, 4, 4)
    r, d = apply_augment(rgb, depth, {"flip": torch.tensor([True, False])})
    assert torch.equal(r[0], rgb[0].flip(-1)) and torch.equal(r[1], rgb[1])
    assert torch.equal(d[0], depth[0].flip(-1)) and torch.equal(d[1], depth[1])


def test_crop_is_identical_for_rgb_and_depth_and_full_box_is_identity():
    g = torch.Generator().manual_seed(0)
    # depth = a copy of the red channel: after the same crop, nearest(depth) must be a red-channel pixel
    x = torch.rand(4, 3, 16, 16)
    d = x[:, :1].clone()
    p = draw_augment(g, 4, AugmentConfig(crop=True, flip_prob=0.5))
    assert p["box"].shape == (4, 4)
    w, h = p["box"][:, 2], p["box"][:, 3]
    assert torch.all((w * h >= 0.2 - 1e-6) | (w == 1) | (h == 1)) and torch.all(w <= 1) and torch.all(h <= 1)
    r, dd = apply_augment(x, d, p)
    assert r.shape == x.shape and dd.shape == d.shape
    for i in range(4):
        assert torch.isin(dd[i], d[i]).all()
    full = {"flip": torch.tensor([False, True]), "box": torch.tensor([[0.5, 0.5, 1.0, 1.0]] * 2)}
    r, dd = apply_augment(x[:2], d[:2], full)
    torch.testing.assert_close(r[0], x[0], atol=1e-5, rtol=0)
    torch.testing.assert_close(r[1], x[1].flip(-1), atol=1e-5, rtol=0)
    torch.testing.assert_close(dd[1], d[1].flip(-1), atol=1e-5, rtol=0)


def test_normalisation_and_depth_scaling():
    rgb = torch.randint(0, 256, (2, 3, 4, 4), dtype=torch.uint8)
    torch.testing.assert_close(denormalize_rgb(normalize_rgb(rgb)), rgb.float() / 255, atol=1e-6, rtol=0)
    depth = torch.tensor([[[[2.5, float("nan")], [float("inf"), -1.0]]]])
    assert clean_depth(depth.clone()).flatten().tolist() == [2.5, 10.0, 10.0, 0.0]
    _, d = prepare_batch({"rgb": rgb[:1, :, :2, :2], "depth": torch.full((1, 1, 2, 2), 2.5)}, None)
    assert torch.allclose(d, torch.tensor((2.5 - DEPTH_MEAN) / DEPTH_STD))
    assert CATEGORY_INDEX["Toaster"] == 21


def test_tiny_world_train_frames(tiny_world):
    from tsnav.data.reader import list_scenes

    imgs = RGBDImages(tiny_world, "train", img_size=32, labels=True)
    train_scenes = list_scenes(tiny_world, "train")
    assert imgs.scenes == train_scenes
    assert len(imgs) == sum(load_scene(p).num_states for p in train_scenes)
    b = imgs.get(np.arange(0, len(imgs), max(1, len(imgs) // 16)))
    assert b["rgb"].shape[1:] == (3, 32, 32) and torch.isfinite(b["depth"]).all()
    assert 0 < b["depth"].mean() < 10 and b["rgb"].float().std() > 5
    assert b["labels"].sum() > 0
