"""Class sets (constants.ClassSet): a RoboTHOR scene's 12 target classes through the scene reader, the bank's
success masks and distance fields, the batched env's Done, the detection tables (oracle), the episode tools and
the agent's target memory; a table, an episode list or an agent of another class set is refused in one line; the
iTHOR 22-class setting reads as before (files without a class set are ithor22)."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from tsnav.constants import (
    CATEGORY_INDEX,
    CLASS_SETS,
    ITHOR22,
    NUM_CATEGORIES,
    ROBOTHOR12,
    ROOM_TARGETS,
    check_same_class_set,
    class_set,
    class_set_of,
    room_target_mask,
)
from tsnav.data.detections import Detections, load_detections, load_scene_detections, write_detections
from tsnav.data.reader import SceneFormatError, load_scene
from tsnav.data.toy import toy_scene
from tsnav.detect.oracle import ground_truth, ground_truth_reference, oracle_detections
from tsnav.sim.batch import BatchEnv, SceneBank
from tsnav.sim.episodes import Episode, EpisodeConfig, episodes_to_arrays, make_episodes, valid_starts

from sim_helpers import write_scene_folder

OBJECTS = {"Apple|1": (2.0, 1.5), "HousePlant|1": (0.0, 0.75), "Chair|1": (1.0, 0.0), "Bowl|1": (0.0, 0.0)}
BLOCKED = [(1.0, 0.5), (1.0, 0.75), (1.0, 1.0)]


def robothor_scene(name="FloorPlan_Train1_1"):
    return toy_scene(2.0, 1.5, OBJECTS, blocked=BLOCKED, name=name, class_set="robothor12")


def ithor_scene(name="FloorPlan1"):
    return toy_scene(2.0, 1.5, OBJECTS, blocked=BLOCKED, name=name)


def test_class_sets_are_named_and_ithor22_is_the_old_constants():
    assert ITHOR22.categories == tuple(CATEGORY_INDEX) and ITHOR22.size == NUM_CATEGORIES == 22
    assert ITHOR22.index == CATEGORY_INDEX and ITHOR22.room_targets == ROOM_TARGETS
    assert ROBOTHOR12.size == 12 and ROBOTHOR12.categories == (
        "AlarmClock",
        "Apple",
        "BaseballBat",
        "BasketBall",
        "Bowl",
        "GarbageCan",
        "HousePlant",
        "Laptop",
        "Mug",
        "SprayBottle",
        "Television",
        "Vase",
    )
    assert set(CLASS_SETS) == {"ithor22", "robothor12"} and class_set(None) is ITHOR22
    assert class_set_of({}) is ITHOR22 and class_set_of({"class_set": "robothor12"}) is ROBOTHOR12
    with pytest.raises(ValueError, match="unknown class set 'coco'"):
        class_set("coco")
    # room lists: iTHOR's kitchen allows 15 of 22; an apartment (no list) allows all 12
    assert room_target_mask("kitchen").sum() == 15 and room_target_mask("kitchen", "robothor12").all()
    assert room_target_mask("apartment", ROBOTHOR12).shape == (12,)
    with pytest.raises(ValueError) as e:
        check_same_class_set("ithor22", ROBOTHOR12, "the agent of RUN", "these scenes")
    assert str(e.value).count("\n") == 0 and "ithor22" in str(e.value) and "robothor12" in str(e.value)


def test_scene_columns_follow_its_class_set(tmp_path):
    r, i = robothor_scene(), ithor_scene()
    # Apple and HousePlant are RoboTHOR targets, Chair an iTHOR one; Bowl is both (column 4 vs 2)
    assert r.object_category.tolist() == [1, 6, -1, 4]
    assert i.object_category.tolist() == [-1, -1, 4, 2]
    assert r.success_table("paper").shape == (r.num_states, 12)
    assert i.success_table("paper").shape == (i.num_states, 22)
    # the same geometry: the Bowl column is the same mask in both
    np.testing.assert_array_equal(r.success_table("lineage")[:, 4], i.success_table("lineage")[:, 2])
    np.testing.assert_array_equal(r.success_mask("Apple"), r.category_visible_within(1.0)[:, 1])
    assert r.mirrored().class_set is ROBOTHOR12
    # the class set is read back from scene.json, and a folder without one is ithor22
    back = load_scene(write_scene_folder(r, tmp_path / r.name))
    assert back.class_set is ROBOTHOR12 and back.object_category.tolist() == r.object_category.tolist()
    assert load_scene(write_scene_folder(i, tmp_path / i.name)).class_set is ITHOR22
    meta = json.loads((tmp_path / r.name / "scene.json").read_text())
    meta["class_set"] = "robothor13"
    (tmp_path / r.name / "scene.json").write_text(json.dumps(meta))
    with pytest.raises(SceneFormatError, match="unknown class set 'robothor13'"):
        load_scene(tmp_path / r.name)


def test_bank_masks_env_done_and_mixed_banks():
    r = robothor_scene()
    bank = SceneBank([r])
    assert bank.class_set is ROBOTHOR12 and bank.num_categories == 12
    assert bank.success.shape == bank.dist.shape == bank.in_frame.shape == (r.num_states, 12)
    assert bank.present[0].nonzero()[0].tolist() == [1, 4, 6]
    np.testing.assert_array_equal(bank.success, r.success_table("paper"))
    # Done succeeds by the Apple column (1), which in iTHOR's numbering would be Book
    s = int(np.flatnonzero(bank.success[:, 1] & ~bank.success[:, 4])[0])
    env = BatchEnv(bank, 2, autoreset=False)
    env.reset(episodes=(np.zeros(2, np.int64), np.array([1, 4]), np.array([s, s])))
    _, _, term, _, info = env.step(np.array([5, 5]))
    assert term.all() and info["success"].tolist() == [True, False]
    with pytest.raises(ValueError, match=r"category ids in \[0, 12\)"):
        BatchEnv(bank, 1, autoreset=False).reset(episodes=(np.zeros(1, np.int64), np.array([12]), np.array([s])))
    with pytest.raises(ValueError, match="class sets"):
        SceneBank([r, ithor_scene()])
    with pytest.raises(ValueError, match=r"confidence must have shape \(\d+, 12\)"):
        bank.set_confidence(np.zeros((bank.num_states, 22), np.float32))


def test_oracle_table_shape_round_trip_and_mismatch_refused(tmp_path):
    r, i = robothor_scene(), ithor_scene()
    gt = ground_truth(r)
    assert gt.present.shape == (r.num_states, 12)
    ref = ground_truth_reference(r)
    np.testing.assert_array_equal(gt.present, ref.present)
    np.testing.assert_array_equal(gt.boxes, ref.boxes)
    det = oracle_detections(r)
    assert det.class_set == "robothor12" and det.scores.shape == (r.num_states, 12)
    assert det.features.shape == (r.num_states, 12, 64) and det.rows().shape == (r.num_states, 12, 6)
    assert (det.labels[:, 1] >= 0).any() and not (det.labels[:, 2] >= 0).any()  # Apple seen; no BaseballBat
    folder = write_scene_folder(r, tmp_path / r.name)
    write_detections(folder, "oracle", det)
    with h5py.File(folder / "detections_oracle.hdf5") as f:
        assert f.attrs["class_set"] == "robothor12"
    back = load_detections(folder, "oracle")
    assert back.class_set == "robothor12" and back.scores.shape == (r.num_states, 12)
    bank = SceneBank([load_scene(folder)])
    table = bank.install_detections("oracle")
    assert bank.detections.shape == (r.num_states, 12, 6) and table.features.shape[:2] == (r.num_states, 12)
    # an iTHOR table (22 columns) in a RoboTHOR scene is refused in one line, and the reverse
    ith = oracle_detections(i)
    assert ith.class_set == "ithor22" and ith.scores.shape == (i.num_states, 22)
    write_detections(folder, "ithor", ith)
    with h5py.File(folder / "detections_ithor.hdf5") as f:
        assert "class_set" not in f.attrs  # iTHOR tables are written as before
    with pytest.raises(ValueError) as e:
        load_scene_detections([load_scene(folder)], "ithor")
    assert "class set ithor22" in str(e.value) and "robothor12" in str(e.value) and "\n" not in str(e.value)
    # a table must have its class set's width
    with pytest.raises(ValueError, match=r"scores must have shape \(\d+, 12\)"):
        Detections(
            keys=ith.keys,
            scores=ith.scores,
            labels=ith.labels,
            boxes=ith.boxes,
            features=ith.features,
            class_set="robothor12",
        )
    with pytest.raises(ValueError, match="class sets differ"):
        Detections.concatenate([det, ith])
    # the lineage's 22 x 264 table is iTHOR's: a RoboTHOR table is not written into it
    from tsnav.data.lineage import table_to_22x264

    assert table_to_22x264(ith).shape == (i.num_states, 22, 264)
    with pytest.raises(ValueError, match="iTHOR's 22 classes; this detection table is of class set robothor12"):
        table_to_22x264(det)


def test_episode_tools_use_the_class_set_names():
    bank = SceneBank([robothor_scene()], protocol="lineage")
    eps = make_episodes(bank, per_room_type=20, seed=0)
    assert eps and {e.target for e in eps} <= {"Apple", "Bowl", "HousePlant"}
    assert {e.target for e in eps} == {"Apple", "Bowl", "HousePlant"}
    _, target, start = episodes_to_arrays(bank, eps)
    assert [ROBOTHOR12.categories[t] for t in target] == [e.target for e in eps]
    np.testing.assert_array_equal(bank.dist[start, target], [e.optimal_length for e in eps])
    vs = valid_starts(bank, EpisodeConfig())
    assert set(vs.pair_target.tolist()) == {1, 4, 6}
    bad = Episode(scene=bank.names[0], target="Chair", start=eps[0].start, optimal_length=0)
    with pytest.raises(ValueError, match="'Chair' is not a class of the scenes' class set robothor12"):
        episodes_to_arrays(bank, [bad])


@pytest.fixture(scope="module")
def two_worlds(tmp_path_factory):
    """The same toy room as a RoboTHOR scene and as an iTHOR one (same folder name), each with 32-px frames, a
    pixel-feature cache and the oracle's table."""
    from tsnav.pipeline.steps import ensure_oracle_detections
    from tsnav.pretrain.pixels import cache_pixel_features

    out = {}
    for kind, make in (("robothor", robothor_scene), ("ithor", ithor_scene)):
        root = tmp_path_factory.mktemp(kind)
        write_scene_folder(make("FloorPlan_Train1_1"), root / "FloorPlan_Train1_1", images=32)
        cache_pixel_features(root, "px", grid=4)
        ensure_oracle_detections(root, "oracle")
        out[kind] = root
    return out


@pytest.mark.usefixtures("one_torch_thread")
def test_agent_records_its_class_set_and_is_refused_on_another(two_worlds, tmp_path, capsys):
    from tsnav.cli import main
    from tsnav.rl.checkpoint import load_model

    world, ithor = two_worlds["robothor"], two_worlds["ithor"]
    run = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "--data",
                str(world),
                "--features",
                "px",
                "--detections",
                "oracle",
                "--algo",
                "batched",
                "--out",
                str(run),
                "--updates",
                "2",
                "--num-envs",
                "2",
                "--preset",
                "cpu",
                "--rollout-steps",
                "4",
                "--checkpoint-every",
                "2",
                "--quiet",
            ]
        )
        == 0
    )
    model, _ = load_model(run)
    assert model.class_set == "robothor12" and model.describe()["class_set"] == "robothor12"
    assert model.memory.query.weight.shape[0] == 12  # one target embedding per RoboTHOR class
    eps_r, eps_i = tmp_path / "r.json", tmp_path / "i.json"
    assert (
        main(["episodes", "--data", str(world), "--split", "train", "--per-room-type", "5", "--out", str(eps_r)]) == 0
    )
    assert json.loads(eps_r.read_text())["class_set"] == "robothor12"
    assert (
        main(["episodes", "--data", str(ithor), "--split", "train", "--per-room-type", "5", "--out", str(eps_i)]) == 0
    )
    assert "class_set" not in json.loads(eps_i.read_text())  # iTHOR lists are written as before
    capsys.readouterr()
    assert (
        main(["eval", "--data", str(world), "--episodes", str(eps_r), "--run", str(run), "--out", str(tmp_path / "ev")])
        == 0
    )
    m = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert m["metrics"]["ALL"]["episodes"] == len(json.loads(eps_r.read_text())["episodes"])
    # the RoboTHOR agent on iTHOR scenes, and a RoboTHOR list on iTHOR scenes: one line each
    assert (
        main(["eval", "--data", str(ithor), "--episodes", str(eps_i), "--run", str(run), "--out", str(tmp_path / "x1")])
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "the agent of" in err and "class set robothor12" in err and "ithor22" in err and len(err.splitlines()) == 1
    assert main(["eval", "--data", str(ithor), "--episodes", str(eps_r), "--out", str(tmp_path / "x2")]) == 2
    err = capsys.readouterr().err.strip()
    assert "class set robothor12" in err and len(err.splitlines()) == 1


def test_ithor_agent_description_is_unchanged():
    import torch

    from tsnav.agent.model import ActorCritic, agent_config

    torch.manual_seed(0)
    a = ActorCritic(agent_config("cpu"), (3, 4, 4), 64)
    assert "class_set" not in a.describe() and a.memory.query.weight.shape[0] == 22
    b = ActorCritic.from_description(a.describe())
    assert b.class_set == "ithor22"
    r = ActorCritic.from_description({**a.describe(), "class_set": "robothor12"})
    assert r.memory.query.weight.shape[0] == 12 and r.describe()["class_set"] == "robothor12"


@pytest.mark.usefixtures("one_torch_thread")
def test_learned_detector_takes_the_train_scenes_class_set(two_worlds, tmp_path, capsys):
    from tsnav.cli import main
    from tsnav.detect.learned import LearnedDetector
    from tsnav.detect.model import DetectorConfig
    from tsnav.detect.train import DetectorTrainConfig, train_detector

    world, ithor = two_worlds["robothor"], two_worlds["ithor"]
    ckpt = tmp_path / "det"
    assert (
        main(
            [
                "detect",
                "--data",
                str(world),
                "--detector",
                "learned",
                "--checkpoint",
                str(ckpt),
                "--name",
                "learned",
                "--train-steps",
                "2",
                "--no-eval",
                "--quiet",
            ]
        )
        == 0
    )
    det = LearnedDetector.load(ckpt)
    assert det.class_set == "robothor12" and det.model.cfg.num_classes == 12
    table = load_detections(world / "FloorPlan_Train1_1", "learned")
    assert table.class_set == "robothor12" and table.scores.shape[1] == 12 and table.features.shape[1] == 12
    SceneBank.from_root(world).install_detections("learned")
    capsys.readouterr()
    # the RoboTHOR detector on iTHOR scenes: one line, nothing written
    assert (
        main(
            [
                "detect",
                "--data",
                str(ithor),
                "--detector",
                "learned",
                "--checkpoint",
                str(ckpt),
                "--name",
                "learned",
                "--no-eval",
                "--quiet",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "class set robothor12" in err and "ithor22" in err and len(err.splitlines()) == 1
    assert not (ithor / "FloorPlan_Train1_1" / "detections_learned.hdf5").exists()
    # a 22-class detector is not trained on RoboTHOR frames
    with pytest.raises(ValueError, match="12 target classes but the detector scores 22"):
        train_detector(
            world,
            tmp_path / "det22",
            DetectorTrainConfig(steps=1),
            model_cfg=DetectorConfig(image_size=32),
            progress=False,
        )
    with pytest.raises(ValueError, match="num_classes 22 but class set robothor12 has 12"):
        DetectorConfig(num_classes=22, class_set="robothor12")
    assert (
        "class_set" not in DetectorConfig().to_dict()
        and DetectorConfig.from_dict({"num_classes": 22}).num_classes == 22
    )


def test_gymnasium_spaces_follow_the_class_set(two_worlds):
    import gymnasium as gym

    env = gym.make(
        "tsnav.sim:tsnav/ObjectNav-v1",
        data=str(two_worlds["robothor"]),
        split="train",
        reward="tsrm",
        detections="oracle",
    )
    assert env.observation_space["target"].n == 12 and env.observation_space["detections"].shape == (72,)
    obs, info = env.reset(seed=0, options={"episode": ("FloorPlan_Train1_1", "Apple", "0.00|0.00|45|0")})
    assert obs["target"] == 1 and info["target_name"] == "Apple" and obs["detections"].shape == (72,)
    assert env.observation_space.contains(obs)
    with pytest.raises(ValueError, match="class set robothor12"):
        env.reset(options={"episode": ("FloorPlan_Train1_1", "Chair", "0.00|0.00|45|0")})
    env.close()
