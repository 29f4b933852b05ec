"""``tsnav thor export-lineage`` and ``tsnav thor check`` (issue 13, part 2): every file the lineage's trainer and
evaluator read, with the shapes and dtypes they expect, and a check that catches each known defect."""

from __future__ import annotations

import json
import pickle
import shutil
from collections import deque
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from sim_helpers import write_scene_folder
from tsnav.cli import main
from tsnav.constants import ACTIONS, DONE, NUM_ACTIONS, TARGET_CATEGORIES
from tsnav.data import lineage as L
from tsnav.data import lineage_splits as LS
from tsnav.sim.lineage import optimal_actions, optimal_actions_reference, write_splits
from tsnav.data.reader import load_scene
from tsnav.data.thor_export import check_lineage_dataset, check_lineage_layout
from tsnav.detect.oracle import oracle_detections
from tsnav.data.detections import write_detections

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _trimmed(scene, positions: int = 4):
    """``scene`` cut down to ``positions`` grid positions connected by MoveAhead around one that sees a target
    (a small real scene: the ResNet18 export runs on its 224 px frames in a few seconds)."""
    succ = scene.category_visible_within(1.5)
    start = int(np.flatnonzero(succ.any(axis=1))[0])
    pos = {(float(x), float(z)) for x, z in zip(scene.x, scene.z)}
    order, seen, q = (
        [],
        {(float(scene.x[start]), float(scene.z[start]))},
        deque([(float(scene.x[start]), float(scene.z[start]))]),
    )
    while q and len(order) < positions:
        p = q.popleft()
        order.append(p)
        for dx, dz in ((0.25, 0), (-0.25, 0), (0, 0.25), (0, -0.25)):
            n = (round(p[0] + dx, 2), round(p[1] + dz, 2))
            if n in pos and n not in seen:
                seen.add(n)
                q.append(n)
    keep = np.flatnonzero([(float(x), float(z)) in set(order) for x, z in zip(scene.x, scene.z)])
    new = np.full(scene.num_states, -1)
    new[keep] = np.arange(len(keep))
    ns = scene.next_state[keep]
    ns = np.where(new[ns] >= 0, new[ns], np.arange(len(keep))[:, None]).astype(np.int32)
    return replace(
        scene,
        keys=scene.keys[keep],
        x=scene.x[keep],
        z=scene.z[keep],
        rotation=scene.rotation[keep],
        horizon=scene.horizon[keep],
        next_state=ns,
        visible=scene.visible[keep],
        distance=scene.distance[keep],
        pixels=scene.pixels[keep],
        boxes=scene.boxes[keep],
    )


@pytest.fixture(scope="module")
def small_root(tiny_world, tmp_path_factory):
    """A dataset of one trimmed test kitchen (FloorPlan22) with its real frames and oracle detections."""
    root = tmp_path_factory.mktemp("lineage_small")
    src = load_scene(tiny_world / "FloorPlan22")
    t = _trimmed(src)
    d = write_scene_folder(t, root / "FloorPlan22")
    with h5py.File(src.path / "images.hdf5", "r") as fi, h5py.File(d / "images.hdf5", "w") as fo:
        for k in t.keys.tolist():
            fo.create_dataset(k, data=fi[k][()])
    write_detections(d, "oracle", oracle_detections(load_scene(d)))
    return root


@pytest.fixture(scope="module")
def exported(small_root):
    assert (
        main(
            [
                "thor",
                "export-lineage",
                str(small_root),
                "--encoder",
                "untrained:resnet18",
                "--detections",
                "oracle",
                "--per-room-type",
                "20",
            ]
        )
        == 0
    )
    return small_root


def test_export_writes_every_file_with_the_lineages_shapes(exported):
    d = exported / "FloorPlan22"
    s = load_scene(d)
    with h5py.File(d / L.RESNET_FILE, "r") as f:
        assert sorted(f.keys()) == s.keys.tolist()
        x = f[s.keys[0]]
        assert x.dtype == np.float32 and x.shape == (1, 512, 7, 7)
    with h5py.File(d / "detr_features_22cls.hdf5", "r") as f:
        assert sorted(f.keys()) == s.keys.tolist()
        r = f[s.keys[0]][()]
        assert r.dtype == np.float32 and r.shape == (22, 264)
        assert set(np.unique(r[:, 257]).astype(int)) <= set(range(1, 24)) and (r[:, 260:] >= 0).all()
    opt = json.loads((d / L.OPTIMAL_ACTION_FILE).read_text())
    assert set(opt) == set(s.keys.tolist())
    assert all(t in TARGET_CATEGORIES and 0 <= a < NUM_ACTIONS for v in opt.values() for t, a in v.items())
    assert check_lineage_layout(d, complete=True) == []
    report = check_lineage_dataset(exported, complete=True)
    assert report == {"FloorPlan22": [], "test_val_split": []}
    info = json.loads((exported / "test_val_split" / LS.INFO_FILE).read_text())
    assert info["success_distance"] == 1.5 and "visibility map" in info["success_rule"]
    assert info["files"] == {
        "kitchen_test_22.pkl": len(LS.read_split(exported / "test_val_split" / "kitchen_test_22.pkl"))
    }


def test_resnet_features_are_resnet18_on_the_224_frame(exported):
    """The stored map equals ResNet18's layer4 output on the frame resized to 224 and normalised (reference path)."""
    from tsnav.pretrain.data import normalize_rgb, resize_rgb
    from tsnav.pretrain.features import load_encoder

    d = exported / "FloorPlan22"
    enc = load_encoder("untrained:resnet18", img_size=224)
    with h5py.File(d / "images.hdf5", "r") as fi, h5py.File(d / L.RESNET_FILE, "r") as fr:
        k = sorted(fi.keys())[3]
        img = torch.from_numpy(fi[k][()]).permute(2, 0, 1)[None]
        assert img.shape[-1] == 64  # the tiny world's frames, resized to 224 for the encoder
        with torch.no_grad():
            ref = enc.module.feature_map(normalize_rgb(resize_rgb(img, 224))).numpy()
        assert fr.attrs["fingerprint"] == enc.fingerprint
        assert np.allclose(fr[k][()], ref, atol=1e-4)


def test_optimal_actions_match_the_reference_and_lead_to_success(tiny_scenes):
    s = tiny_scenes[0]
    fast = optimal_actions(s, 1.5)
    assert fast == optimal_actions_reference(s, 1.5)
    succ = s.category_visible_within(1.5)
    # following the actions reaches a success state, in as many steps as the BFS says
    from tsnav.sim.paths import scene_distance_fields

    dist = scene_distance_fields(s, 1.5)
    for key in s.keys[::37]:
        for t, a in fast[str(key)].items():
            c, st, steps = TARGET_CATEGORIES.index(t), s.index(str(key)), 0
            while fast[str(s.keys[st])][t] != DONE:
                st = int(s.next_state[st, fast[str(s.keys[st])][t]])
                steps += 1
            assert succ[st, c] and steps == dist[s.index(str(key)), c]
    assert ACTIONS[3] == "LookUp"  # ids in the lineage's order


def test_split_records_and_round_trip(exported, tiny_world, tmp_path):
    recs = LS.read_split(exported / "test_val_split" / "kitchen_test_22.pkl")
    assert 0 < len(recs) <= 20
    r = recs[0]
    assert set(r) == {"scene", "state", "goal_object_type", "task_data", "glove_embedding"}
    assert r["glove_embedding"].shape == (60, 1) and r["glove_embedding"].dtype == np.float32
    assert (
        r["glove_embedding"][TARGET_CATEGORIES.index(r["goal_object_type"]), 0] == 1 and r["glove_embedding"].sum() == 1
    )
    vis = json.loads((exported / "FloorPlan22" / L.VISIBLE_MAP_FILE).read_text())
    assert all(t in vis and t.startswith(x["goal_object_type"] + "|") for x in recs for t in x["task_data"])
    # round trip: the reader reads back what export-lineage wrote (same scene, start, target, L*)
    out = tmp_path / "eps.json"
    assert (
        main(
            [
                "thor",
                "episodes",
                str(exported / "test_val_split" / "kitchen_test_22.pkl"),
                "--data",
                str(exported),
                "--out",
                str(out),
                "--success-distance",
                "1.5",
            ]
        )
        == 0
    )
    from tsnav.sim.batch import SceneBank
    from tsnav.sim.episodes import episodes_to_arrays, read_episodes

    eps, meta = read_episodes(out)
    assert [(e.scene, e.start, e.target) for e in eps] == [
        (x["scene"], x["state"], x["goal_object_type"]) for x in recs
    ]
    bank = SceneBank.from_root(exported, None, success_distance=1.5)
    episodes_to_arrays(bank, eps, check=True)  # stored L* = the bank's
    assert meta["success_distance"] == 1.5 and meta["dropped"] == {}


def test_write_splits_covers_test_and_val_with_both_horizons(tiny_world, tmp_path):
    root = tmp_path / "data"
    root.mkdir()
    for n in ("FloorPlan21", "FloorPlan22"):  # val and test kitchens
        shutil.copytree(tiny_world / n, root / n)
    files = write_splits(root, success_distance=1.0, per_room_type=60)
    assert set(files) == {"kitchen_test_22.pkl", "kitchen_val_22.pkl"}
    recs = LS.read_split(root / "test_val_split" / "kitchen_val_22.pkl")
    assert {x["scene"] for x in recs} == {"FloorPlan21"} and len(recs) == files["kitchen_val_22.pkl"]
    assert {x["state"].split("|")[3] for x in recs} == {"0", "30"}
    info = json.loads((root / "test_val_split" / LS.INFO_FILE).read_text())
    assert info["success_distance"] == 1.0 and "1.0 m" in info["success_rule"]


# --------------------------------------------------------------------------- the check catches each defect
def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_check_catches_each_defect_of_the_issue(exported, tmp_path):
    good = exported / "FloorPlan22"
    keys = sorted(json.loads((good / "optimal_action.json").read_text()))

    def broken(name, edit):
        d = _copy(good, tmp_path / name / "FloorPlan22")
        edit(d)
        return check_lineage_layout(d, complete=True, image_size=None)

    # 1. no resnet18_featuremap.hdf5
    p = broken("noresnet", lambda d: (d / L.RESNET_FILE).unlink())
    assert any(x.startswith("resnet18_featuremap.hdf5: missing file") for x in p)

    # 2. features stored (512, 7, 7) instead of (1, 512, 7, 7)
    def squeeze(d):
        with h5py.File(d / L.RESNET_FILE, "a") as f:
            x = f[keys[0]][()]
            del f[keys[0]]
            f.create_dataset(keys[0], data=x[0])

    p = broken("resnet3d", squeeze)
    assert any("(512, 7, 7), expected float32 (1, 512, 7, 7)" in x for x in p), p

    # 2b. float16 features
    def half(d):
        with h5py.File(d / L.RESNET_FILE, "a") as f:
            x = f[keys[1]][()]
            del f[keys[1]]
            f.create_dataset(keys[1], data=x.astype(np.float16))

    assert any("float16" in x for x in broken("resnet16", half))

    # 3. no DETR table
    p = broken("nodetr", lambda d: (d / "detr_features_22cls.hdf5").unlink())
    assert any(x.startswith("detr_features_22cls.hdf5: missing file") for x in p)

    # 4. rows without a detection as tsnav wrote them before: label 0 and box -1 rescaled to 300 px (-4.6875)
    def old_rows(d):
        with h5py.File(d / "detr_features_22cls.hdf5", "a") as f:
            r = f[keys[2]][()]
            empty = r[:, 257] == 23
            r[empty, 257] = 0
            r[empty, 260:264] = -4.6875
            f[keys[2]][...] = r

    p = broken("label0", old_rows)
    assert any("labelled 0" in x and "last class" in x for x in p), p

    def neg_boxes(d):
        with h5py.File(d / "detr_features_22cls.hdf5", "a") as f:
            r = f[keys[2]][()]
            r[r[:, 257] == 23, 260:264] = -4.6875
            f[keys[2]][...] = r

    assert any("outside the 300 px frame" in x for x in broken("negbox", neg_boxes))

    # 5. no optimal_action.json, or a wrong one
    p = broken("noopt", lambda d: (d / "optimal_action.json").unlink())
    assert any(x.startswith("optimal_action.json: missing file") for x in p)

    def bad_opt(d):
        o = json.loads((d / "optimal_action.json").read_text())
        o[keys[0]] = {"Bowl": 7}
        del o[keys[1]]
        (d / "optimal_action.json").write_text(json.dumps(o))

    p = broken("badopt", bad_opt)
    assert any("not an action id" in x for x in p) and any("no entry for 1 of" in x for x in p)

    # 6. images not at the lineage's 300 x 300
    p = check_lineage_layout(good, complete=True, image_size=300)
    assert any("is 64 x 64, expected 300 x 300" in x for x in p)

    # 7. an object listed with no state in the visibility map
    def empty_obj(d):
        v = json.loads((d / L.VISIBLE_MAP_FILE).read_text())
        v["Pot|+00.10|+00.90|+00.20"] = []
        (d / L.VISIBLE_MAP_FILE).write_text(json.dumps(v))

    assert any("listed with no state" in x for x in broken("emptyobj", empty_obj))

    # the good folder passes
    assert check_lineage_layout(good, complete=True) == []


def test_check_catches_missing_and_bad_episode_lists(exported, tmp_path):
    root = tmp_path / "data"
    shutil.copytree(exported / "FloorPlan22", root / "FloorPlan22")
    # 8. no episode lists at all
    assert check_lineage_dataset(root, complete=True)["test_val_split"][0].startswith(
        "test_val_split: no episode lists"
    )
    assert check_lineage_dataset(root, complete=False)["test_val_split"] == []
    split = root / "test_val_split"
    recs = LS.read_split(exported / "test_val_split" / "kitchen_test_22.pkl")
    bad = [dict(r) for r in recs[:4]]
    bad[0]["state"] = "9.00|9.00|0|0"
    bad[1]["task_data"] = ["Pot|+09.99|+00.90|+09.99"]
    bad[2]["glove_embedding"] = np.zeros((22, 1), np.float32)
    bad[3]["scene"] = "FloorPlan30"
    LS.write_split(split / "kitchen_test_22.pkl", bad)
    p = check_lineage_dataset(root, complete=True)["test_val_split"]
    assert len(p) == 4 and "not a state" in p[0] and "task_data" in p[1] and "(60, 1)" in p[2] and "FloorPlan30" in p[3]


def test_check_command_on_a_dataset_folder(exported, capsys):
    assert main(["thor", "check", str(exported), "--complete"]) == 0
    out = capsys.readouterr().out
    assert "FloorPlan22: ok" in out and "test_val_split: ok" in out
    assert main(["thor", "check", str(exported), "--complete", "--image-size", "300"]) == 1
    assert "expected 300 x 300" in capsys.readouterr().out


def test_export_lineage_refuses_bad_input(small_root, tmp_path, capsys):
    assert main(["thor", "export-lineage", str(small_root), "--detections", "nope", "--no-splits"]) == 2
    assert "no detections_nope.hdf5" in capsys.readouterr().err
    assert main(["thor", "export-lineage", str(small_root), "--encoder", "untrained:vit_tiny", "--no-splits"]) == 2
    assert "needs a ResNet18" in capsys.readouterr().err
    assert main(["thor", "export-lineage", str(small_root)]) == 2


def test_pickles_written_hold_only_plain_data(exported):
    """What export-lineage writes loads with the restricted unpickler (plain dicts, lists, strings, numpy)."""
    data = (exported / "test_val_split" / "kitchen_test_22.pkl").read_bytes()
    a, b = LS.safe_load(data), pickle.loads(data)
    assert len(a) == len(b) and all(np.array_equal(x["glove_embedding"], y["glove_embedding"]) for x, y in zip(a, b))
