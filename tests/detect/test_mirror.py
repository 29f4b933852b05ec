"""Mirrored rooms (training-data augmentation, TrainConfig.mirror): the mirror image is a room of the same kind
(its moves obey the action geometry every loaded room obeys), path lengths and success are the room's, and the
features and detection tables of the flipped frames line up with the mirrored poses and boxes."""

from __future__ import annotations

import shutil
from dataclasses import replace

import h5py
import numpy as np
import pytest
import torch

from tsnav.agent import agent_config
from tsnav.agent.memory import relative_pose
from tsnav.cli import main
from tsnav.constants import DONE, ROTATE_LEFT, ROTATE_RIGHT
from tsnav.data.detections import load_detections
from tsnav.data.reader import MIRROR_SUFFIX, edge_actions, list_scenes, load_scene
from tsnav.detect.evaluate import evaluate_detections
from tsnav.pretrain.features import cache_features, load_encoder, read_features
from tsnav.pretrain.model import vit_tiny
from tsnav.pretrain.pixels import cache_pixel_features
from tsnav.pretrain.synthetic import write_synthetic_dataset
from tsnav.pretrain.data import normalize_rgb
from tsnav.pretrain.train import save_encoder
from tsnav.rl.assemble import load_bank
from tsnav.rl.config import TrainConfig
from tsnav.rl.train import train_run
from tsnav.sim.paths import distance_fields, scene_distance_fields

from conftest import PIXEL_FEATURES


pytestmark = pytest.mark.usefixtures("one_torch_thread")

ARRAYS = ("keys", "x", "z", "rotation", "horizon", "next_state", "visible", "distance", "pixels", "boxes")


def test_the_mirror_image_is_a_room_with_the_same_paths(tiny_real):
    scene = load_scene(list_scenes(tiny_real)[0])
    m = scene.mirrored()
    assert m.mirror and m.name == scene.name + MIRROR_SUFFIX and m.num_states == scene.num_states
    # every move of the mirrored graph is the action its two poses say it is (the reader's own rule)
    S = np.arange(m.num_states)
    for a in range(DONE):
        t = m.next_state[:, a]
        moved = t != S
        assert moved.any()
        got = edge_actions(
            m.x[moved],
            m.z[moved],
            m.rotation[moved],
            m.horizon[moved],
            m.x[t[moved]],
            m.z[t[moved]],
            m.rotation[t[moved]],
            m.horizon[t[moved]],
        )
        assert (got == a).all(), a
    # the turns trade places; x and the heading change sign
    np.testing.assert_array_equal(m.next_state[:, ROTATE_LEFT], scene.next_state[:, ROTATE_RIGHT])
    np.testing.assert_array_equal(m.x, -scene.x)
    np.testing.assert_array_equal((m.rotation.astype(int) + scene.rotation) % 360, 0)
    # mirrored twice: the room back, field by field
    back = m.mirrored()
    assert back.name == scene.name and not back.mirror and back.meta == scene.meta
    for k in ARRAYS:
        np.testing.assert_array_equal(getattr(back, k), getattr(scene, k), err_msg=k)
    for p, q in zip(back.floor, scene.floor):
        np.testing.assert_array_equal(p, q)
    # path lengths: those of the room (the cache is the room's and stays valid: not rewritten by the mirror)
    for protocol in ("paper", "lineage"):
        want = scene_distance_fields(scene, protocol=protocol)
        cache = next(scene.path.glob("shortest_paths_lineage.npz" if protocol == "lineage" else "shortest_paths_1*"))
        before = cache.stat().st_mtime_ns
        np.testing.assert_array_equal(scene_distance_fields(m, protocol=protocol), want)
        np.testing.assert_array_equal(distance_fields(m.next_state, m.success_table(protocol)), want)
        assert cache.stat().st_mtime_ns == before
    # boxes: the same size, at the mirrored place
    w = scene.image_size - 1
    seen = scene.boxes[..., 0] >= 0
    assert seen.any()
    np.testing.assert_array_equal(m.boxes[..., 0][seen], w - scene.boxes[..., 2][seen])
    np.testing.assert_array_equal(m.boxes[..., 2][seen], w - scene.boxes[..., 0][seen])
    np.testing.assert_array_equal(m.boxes[~seen], scene.boxes[~seen])
    # the memory's view of another pose: as far ahead, on the other side, turned the other way
    rng = np.random.default_rng(0)
    i, j = rng.integers(0, scene.num_states, 50), rng.integers(0, scene.num_states, 50)

    def pose(s, k):
        return torch.tensor(np.stack([s.x[k], s.z[k], s.rotation[k], s.horizon[k]], 1), dtype=torch.float32)

    r, rm = relative_pose(pose(scene, j)[:, None], pose(scene, i)), relative_pose(pose(m, j)[:, None], pose(m, i))
    torch.testing.assert_close(rm[..., [0, 3, 4]], r[..., [0, 3, 4]], atol=1e-5, rtol=0)
    torch.testing.assert_close(rm[..., [1, 2]], -r[..., [1, 2]], atol=1e-5, rtol=0)


def test_encoder_features_of_flipped_frames(tmp_path):
    root = write_synthetic_dataset(tmp_path / "data", size=16)
    torch.manual_seed(3)
    model = vit_tiny(patch_size=8, img_size=16)
    save_encoder(model, tmp_path / "enc.safetensors", "demae")
    enc = load_encoder(str(tmp_path / "enc.safetensors"))
    cache_features(enc, root, "t", split="val", progress=False)
    files = cache_features(enc, root, "t", split="val", progress=False, mirror=True)
    scene = load_scene(list_scenes(root, "val")[0])
    assert [f.name for f in files] == ["features_t-mirror.hdf5"]
    feats, keys, attrs = read_features(scene.path, "t-mirror")
    plain = read_features(scene.path, "t")[0]
    assert attrs["mirror"] == 1 and keys.tolist() == scene.keys.tolist()
    assert np.abs(feats.astype(np.float32) - plain.astype(np.float32)).max() > 0.1  # not the unflipped frames
    i = 5  # the slow way: flip one frame by hand and encode it
    with h5py.File(scene.path / "images.hdf5") as f:
        rgb = torch.from_numpy(f[keys[i]][()][:, ::-1].copy()).permute(2, 0, 1)[None]
    with torch.no_grad():
        want = model.eval().feature_map(normalize_rgb(rgb))[0].numpy()
    np.testing.assert_allclose(feats[i].astype(np.float32), want, atol=2e-2, rtol=1e-2)
    # a cache of unflipped frames under the mirror's name is refused, not reused
    shutil.copy(scene.path / "features_t.hdf5", scene.path / "features_u-mirror.hdf5")
    with pytest.raises(ValueError, match="unflipped"):
        cache_features(enc, root, "u", split="val", progress=False, mirror=True)


@pytest.fixture(scope="module")
def real(tiny_real, tmp_path_factory):
    root = tmp_path_factory.mktemp("mirror_real") / "world"
    shutil.copytree(tiny_real, root, ignore=shutil.ignore_patterns("detections_*", "features_*"))
    return root


def test_detect_mirror_tables_line_up_with_the_mirrored_room(real, capsys):
    assert main(["detect", "--data", str(real), "--detector", "oracle", "--no-eval", "--quiet"]) == 0
    assert main(["detect", "--data", str(real), "--detector", "oracle", "--mirror", "--no-eval", "--quiet"]) == 0
    assert "detections_oracle-mirror.hdf5: 3 scenes written" in capsys.readouterr().out
    scene = load_scene(list_scenes(real)[0])
    plain, mir = load_detections(scene.path, "oracle"), load_detections(scene.path, "oracle-mirror")
    np.testing.assert_array_equal(mir.scores, plain.scores)
    kept = plain.labels >= 0
    np.testing.assert_array_equal(mir.boxes[..., 0][kept], scene.image_size - 1 - plain.boxes[..., 2][kept])
    assert mir.config["mirror"] is True and "mirror" not in plain.config

    # the learned detector on the flipped frames finds the mirrored boxes, as well as it finds the room's
    for extra in ([], ["--mirror"]):
        assert (
            main(
                [
                    "detect",
                    "--data",
                    str(real),
                    "--detector",
                    "shipped",
                    "--shipped",
                    "learned6",
                    "--name",
                    "l6",
                    "--no-eval",
                    "--quiet",
                    "--workers",
                    "2",
                    *extra,
                ]
            )
            == 0
        )
    scenes = [load_scene(p) for p in list_scenes(real)]
    mirrored = [s.mirrored() for s in scenes]
    own = evaluate_detections(scenes, [load_detections(s.path, "l6") for s in scenes])
    mir = evaluate_detections(mirrored, [load_detections(s.path, "l6-mirror") for s in scenes])
    wrong = evaluate_detections(scenes, [load_detections(s.path, "l6-mirror") for s in scenes])
    assert own.mean_box_ap > 0.5
    assert abs(mir.mean_box_ap - own.mean_box_ap) < 0.1, (mir.mean_box_ap, own.mean_box_ap)
    assert wrong.mean_box_ap < own.mean_box_ap - 0.15, (wrong.mean_box_ap, own.mean_box_ap)
    assert abs(mir.mean_presence_ap - own.mean_presence_ap) < 0.1


def test_training_on_mirrored_rooms(pixel_world, tmp_path, capsys):
    cfg = TrainConfig(
        data=str(pixel_world),
        features=PIXEL_FEATURES,
        algo="batched",
        num_envs=8,
        rollout_steps=6,
        updates=3,
        checkpoint_every=3,
        log_every=1,
        lr=1e-3,
        device="cpu",
        detections="oracle",
        mirror=True,
    )
    # without the flipped frames' tables or features: one line naming the missing file and the command that makes it
    out = tmp_path / "run"
    with pytest.raises(FileNotFoundError, match="detect --mirror --name oracle"):
        load_bank(cfg)
    assert main(["detect", "--data", str(pixel_world), "--detector", "oracle", "--mirror", "--no-eval", "--quiet"]) == 0
    with pytest.raises(FileNotFoundError, match=f"features --mirror --name {PIXEL_FEATURES}"):
        train_run(cfg, agent_config("cpu"), out, progress_bar=False)
    cache_pixel_features(pixel_world, PIXEL_FEATURES, grid=4, mirror=True)

    bank, _ = load_bank(cfg)
    plain, _ = load_bank(replace(cfg, mirror=False))
    n = plain.num_scenes
    assert bank.num_scenes == 2 * n and bank.num_states == 2 * plain.num_states
    assert bank.names[n:] == [s + MIRROR_SUFFIX for s in plain.names]
    np.testing.assert_array_equal(bank.dist[plain.num_states :], plain.dist)
    # pooled pixels of a flipped frame: the room's grid flipped left to right
    scene = load_scene(list_scenes(pixel_world, "train")[0])
    px, mx = read_features(scene.path, PIXEL_FEATURES)[0], read_features(scene.path, PIXEL_FEATURES + "-mirror")[0]
    np.testing.assert_allclose(mx.astype(np.float32), px[..., ::-1].astype(np.float32), atol=2e-3)

    progress = train_run(cfg, agent_config("cpu"), out, progress_bar=False)
    assert progress["update"] == 3
    with pytest.raises(ValueError, match="mirror"):
        train_run(replace(cfg, mirror=False, updates=4), agent_config("cpu"), out, progress_bar=False)
    assert main(["train", "--out", str(out), "--updates", "4", "--quiet"]) == 0  # resumes with its own setting
    assert "after 4 updates" in capsys.readouterr().out
