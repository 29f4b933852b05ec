"""Feature cache: shapes, key order, agreement with a direct encoder call, resume, encoder specs."""

import h5py
import numpy as np
import pytest
import torch

from tsnav.data.reader import list_scenes, load_scene
from tsnav.pretrain.data import normalize_rgb
from tsnav.pretrain.features import cache_features, default_name, load_encoder, read_features
from tsnav.pretrain.model import vit_tiny
from tsnav.pretrain.synthetic import write_synthetic_dataset
from tsnav.pretrain.train import PretrainConfig, save_encoder, train


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture()
def root(tmp_path):
    return write_synthetic_dataset(tmp_path / "data", size=16)


def test_vit_cache_shapes_order_and_values(root, tmp_path):
    torch.manual_seed(3)
    m = vit_tiny(patch_size=8, img_size=16)
    save_encoder(m, tmp_path / "enc.safetensors", "demae")
    enc = load_encoder(str(tmp_path / "enc.safetensors"))
    assert enc.arch == "vit" and enc.img_size == 16
    files = cache_features(enc, root, "t", batch_size=5, progress=False)
    assert len(files) == 3  # every split
    scene = load_scene(list_scenes(root)[2])
    feats, keys, attrs = read_features(scene.path, "t")
    assert feats.shape == (scene.num_states, 192, 2, 2) and feats.dtype == np.float16
    assert keys.tolist() == scene.keys.tolist() and attrs["method"] == "demae"
    i = 7
    with h5py.File(scene.path / "images.hdf5") as f:
        rgb = torch.from_numpy(f[keys[i]][()]).permute(2, 0, 1)[None]
    with torch.no_grad():
        want = m.eval().feature_map(normalize_rgb(rgb))[0].numpy()
    np.testing.assert_allclose(feats[i].astype(np.float32), want, atol=2e-2, rtol=1e-2)

    # a rerun skips finished scenes; a different encoder under the same name is refused
    mtimes = [f.stat().st_mtime_ns for f in files]
    cache_features(enc, root, "t", progress=False)
    assert mtimes == [f.stat().st_mtime_ns for f in files]
    other = load_encoder("untrained:vit_tiny", patch_size=8, img_size=16)
    with pytest.raises(ValueError, match="another encoder"):
        cache_features(other, root, "t", progress=False)
    cache_features(other, root, "t", overwrite=True, progress=False)
    assert read_features(scene.path, "t")[2]["method"] == "untrained"


def test_resnet_cache_and_specs(root, tmp_path):
    enc = load_encoder("untrained:resnet18", img_size=32)
    cache_features(enc, root, default_name("untrained:resnet18"), split="val", progress=False)
    scene = list_scenes(root, "val")[0]
    feats, keys, attrs = read_features(scene, "untrained_resnet18")
    assert feats.shape == (32, 512, 1, 1) and attrs["arch"] == "resnet18"
    assert not (list_scenes(root, "train")[0] / "features_untrained_resnet18.hdf5").exists()
    with pytest.raises(FileNotFoundError, match="no such encoder"):
        load_encoder(str(tmp_path / "nothing"))
    with pytest.raises(ValueError, match="unknown encoder"):
        load_encoder("untrained:vit_huge")


def test_tiny_world_features_from_a_pretraining_run(tiny_world, tmp_path):
    cfg = PretrainConfig(
        method="demae", model="vit_micro", patch_size=16, img_size=32, batch_size=8, steps=2, viz_images=2, max_scenes=1
    )
    train(cfg, tiny_world, tmp_path / "run", progress=False)
    assert (tmp_path / "run" / "recon.png").exists()
    enc = load_encoder(str(tmp_path / "run"))
    files = cache_features(
        enc, tiny_world, default_name(str(tmp_path / "run")), batch_size=128, split="val", progress=False
    )
    for f in files:
        scene = load_scene(f.parent)
        feats, keys, _ = read_features(f.parent, "run")
        assert feats.shape == (scene.num_states, 64, 2, 2) and keys.tolist() == scene.keys.tolist()
        assert np.isfinite(feats).all()
