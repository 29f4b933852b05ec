"""A RoboTHOR agent through `tsnav release` (issue 46): `release eval` builds the card's val scenes only, writes the
shipped detector's tables and the encoder's features there, converts the challenge's val episodes packaged with
tsnav under each protocol and prints the table under its own header; `release make`'s scoring on the challenge's
train episodes (a fixed sample, never the val scenes). Tiny scale: two robothor-real scenes at 32 px, a tiny
untrained robothor12 detector registered as a shipped one for this module, an agent trained two updates."""

import gzip
import json

import numpy as np
import pytest

from tsnav.cli import main
from tsnav.data.reader import list_scenes, load_scene
from tsnav.pipeline import release

pytestmark = [pytest.mark.usefixtures("one_torch_thread"), pytest.mark.slow]

TRAIN, VAL = "FloorPlan_Train1_1", "FloorPlan_Val1_5"  # VAL: the smallest val scene (3,024 states at any size)
DET = "tinyrobo"  # the module's stand-in for the lead's robothor1
SIZE = 32


def _save_tiny_detector(folder, seed: int, size: int = SIZE, min_score: float = 0.05):
    """An untrained robothor12 grid detector reading ``size``-px frames, its weights drawn with ``seed``, keeping
    boxes scored above ``min_score``, saved as a checkpoint into ``folder`` (returned)."""
    import torch

    from tsnav.detect.model import DetectorConfig, GridDetector
    from tsnav.detect.train import FORMAT, save_checkpoint

    torch.manual_seed(seed)
    model = GridDetector(DetectorConfig(image_size=size, widths=(4, 8, 8), dim=8, class_set="robothor12"))
    meta = {"format": FORMAT, "step": 0, "calibrated_step": 0, "temperature": 1.0, "model": model.cfg.to_dict()}
    save_checkpoint(folder, model, None, {**meta, "min_score": min_score})
    return folder


@pytest.fixture(scope="module")
def tiny_detector(tmp_path_factory):
    """An untrained (seeded) robothor12 grid detector reading 32-px frames, registered in tsnav.detect.shipped as
    :data:`DET` while the module runs."""
    from tsnav.detect import shipped

    folder = _save_tiny_detector(tmp_path_factory.mktemp("tinyrobo"), seed=0)
    mp = pytest.MonkeyPatch()
    mp.setitem(shipped.SHIPPED, DET, folder)
    yield folder
    mp.undo()


@pytest.fixture(scope="module")
def robo(tiny_detector, tmp_path_factory):
    """A robothor-real train scene at 32 px with the tiny detector's tables and a 2-step DE-MAE's features, an agent
    trained two updates on it, packed with a RoboTHOR card (eval_split val, the val scene VAL, challenge
    episodes)."""
    from tsnav.detect.shipped import shipped_detector, shipped_meta
    from tsnav.pipeline.detector_steps import write_learned_tables
    from tsnav.pipeline.steps import EncoderSpec, ensure_encoder, ensure_features
    from tsnav.render.gl import RendererUnavailable
    from tsnav.world.build import BuildConfig, build_dataset

    root = tmp_path_factory.mktemp("robothor_release")
    data = root / "world"
    try:
        build_dataset(
            data,
            "robothor-real",
            [TRAIN],
            BuildConfig.from_preset("robothor-real", image_size=SIZE),
            workers=1,
            progress=False,
        )
    except RendererUnavailable:
        pytest.skip("no EGL renderer")
    pre = dict(method="demae", model="vit_micro", patch_size=16, img_size=32, steps=2, batch_size=4, device="cpu")
    es = EncoderSpec("demae", str(root / "pre"), "vit_micro", 16, 32, pre)
    ensure_encoder(es, data)
    feats = ensure_features(es, data, ["train"], batch_size=64, workers=1)
    write_learned_tables(data, DET, shipped_detector(SIZE, DET), progress=False)
    run = root / "run"
    argv = ["train", "--out", str(run), "--data", str(data), "--features", feats, "--reward", "tsrm"]
    argv += ["--algo", "batched", "--num-envs", "4", "--preset", "cpu", "--detections", DET, "--updates", "2"]
    argv += ["--protocol", "lineage", "--checkpoint-every", "1", "--milestone-every", "1", "--quiet"]
    assert main(argv) == 0
    card = {
        "name": "tiny-robothor",
        "summary": "a RoboTHOR test agent",
        "world_preset": "robothor-real",
        "world_version": 1,
        "image_size": SIZE,
        "eval_split": "val",
        "val_rooms": [VAL],
        "episodes": "challenge",
        "detector_shipped": DET,
        "detector_fingerprint": shipped_meta(DET)["fingerprint"],
        "detections": DET,
        "protocol": "lineage",
        "budget": "2 updates",
        "figures": {},
    }
    (root / "card.json").write_text(json.dumps(card))
    out = root / "tiny-robothor"
    argv = ["release", "pack", "--run", str(run), "--checkpoint", str(sorted((run / "checkpoints").iterdir())[-1])]
    argv += ["--encoder-run", str(root / "pre"), "--card", str(root / "card.json"), "--out", str(out)]
    assert main(argv) == 0
    return {"root": root, "data": data, "run": run, "out": out, "feats": feats}


def test_release_eval_of_a_robothor_agent(robo, capsys):
    from tsnav.sim.batch import SceneBank
    from tsnav.sim.challenge import CHALLENGE_SOURCE, challenge_episodes, packaged_challenge, read_challenge_episodes
    from tsnav.sim.episodes import read_episodes

    world, ev = robo["root"] / "val_world", robo["root"] / "eval"
    args = ["release", "eval", "--agent", str(robo["out"]), "--data", str(world), "--out", str(ev)]
    args += ["--workers", "1", "--threads", "1"]
    # RoboTHOR has no test split: refused in one line before anything is built
    assert main(args + ["--split", "test", "--build-world"]) == 2
    err = capsys.readouterr().err
    assert "the robothor-real world has no test rooms: evaluate this agent with --split val" in err
    assert not world.exists()
    # the default split is the card's eval_split: the val scene is built (and nothing else), at the card's size
    assert main(args + ["--build-world"]) == 0
    text = capsys.readouterr().out
    assert [p.name for p in list_scenes(world)] == [VAL] and load_scene(world / VAL).image_size == SIZE
    card = release.read_card(robo["out"])
    assert (world / VAL / f"features_{card['features']}.hdf5").exists()
    assert (world / VAL / f"detections_{DET}.hdf5").exists()
    assert f"tiny-robothor on the 1 RoboTHOR val scenes, challenge episodes, greedy, detector {DET}" in text
    assert "real test rooms" not in text and "world: built 1 of 1 val scenes" in text
    res = json.loads((ev / "results.json").read_text())
    assert res["split"] == "val" and [(r["protocol"], r["policy"]) for r in res["rows"]] == [
        (p, pol) for p in ("paper", "lineage") for pol in ("agent", "scripted explorer", "random")
    ]
    # the episodes: the packaged challenge's val episodes of the scene, converted under each protocol, exactly as
    # tsnav.sim.challenge converts them (read from the package: nothing from ../shared)
    records = read_challenge_episodes(packaged_challenge(), "val")
    assert len(records) == 1800
    for protocol in ("paper", "lineage"):
        eps, meta = read_episodes(ev / f"episodes_val_{protocol}.json")
        assert meta["protocol"] == protocol and meta["class_set"] == "robothor12" and meta["split"] == "val"
        assert meta["source"] == CHALLENGE_SOURCE.format(split="val") and "packaged with tsnav" in meta["challenge"]
        assert meta["conversion"]["read"] == 1800 and meta["conversion"]["dropped"]["scene not in DATA"] == sum(
            r["scene"] != VAL for r in records
        )
        want, _ = challenge_episodes(records, SceneBank([load_scene(world / VAL)], protocol=protocol))
        assert [e.to_json() for e in eps] == [e.to_json() for e in want] and eps
        row = next(r for r in res["rows"] if r["protocol"] == protocol and r["policy"] == "agent")
        assert row["episodes"] == len(eps)
    assert res["inputs"] == release.release_inputs(robo["out"], card, world, ev, ["paper", "lineage"], True, "val")
    assert list(res["inputs"]["data"]["rooms"]) == [VAL]
    # a second run prints the saved table (the same lines) and says so
    assert main(args) == 0
    second = capsys.readouterr().out
    assert "nothing changed since the evaluation of" in second
    head = "RoboTHOR val scenes, challenge episodes"
    assert second.split(head)[1].split("\n", 1)[1].replace("read ", "wrote ") == text.split(head)[1].split("\n", 1)[1]
    # the card's figures, its Markdown and its headline say where they come from
    assert main(args + ["--update-card"]) == 0
    capsys.readouterr()
    card = release.read_card(robo["out"])
    md = (robo["out"] / "card.md").read_text()
    assert card["figures"]["val"]["rows"] == res["rows"] and "test" not in card["figures"]
    assert "## RoboTHOR val scenes, the challenge's episodes (" in md
    assert "`tsnav release eval --agent tiny-robothor`" in md and "builds the test rooms" not in md
    assert release.headline(card).startswith("val, challenge episodes SR / SPL (")


def _agent_evaluated_with(robo, tmp_path, det: str):
    """A copy of the packed agent in ``tmp_path`` whose card swaps in the shipped detector ``det`` ([detections]
    evaluated; trained on DET's tables); (its folder, its card)."""
    import shutil

    from tsnav.detect import shipped

    agent = tmp_path / "tiny-robothor"
    shutil.copytree(robo["out"], agent)
    card = release.read_card(agent)
    card.update(
        detector_shipped=det,
        detections=det,
        trained_detector_shipped=DET,
        trained_detections=DET,
        detector_fingerprint=shipped.shipped_meta(det)["fingerprint"],
    )
    (agent / "card.json").write_text(json.dumps(card))
    return agent, card


def test_release_eval_with_the_detector_its_card_swaps_in(robo, tmp_path, monkeypatch, capsys):
    """A card whose detector is another than the one of training ([detections] evaluated, as tsrm-demae-robothor
    v2 reads robothor3 with a policy trained on robothor2's tables): release eval writes that detector's tables only,
    the agent and the explorer read them, and the card's Markdown names both detectors."""
    import shutil

    from tsnav.detect import shipped

    det2 = _save_tiny_detector(tmp_path / "det2", seed=1)  # another detector than DET's (seed 0)
    monkeypatch.setitem(shipped.SHIPPED, "tinyrobo2", det2)
    agent, card = _agent_evaluated_with(robo, tmp_path, "tinyrobo2")
    world, ev = tmp_path / "val_world", tmp_path / "eval"
    args = ["release", "eval", "--agent", str(agent), "--data", str(world), "--out", str(ev), "--build-world"]
    assert main(args + ["--workers", "1", "--threads", "1", "--protocol", "lineage", "--update-card"]) == 0
    assert (world / VAL / "detections_tinyrobo2.hdf5").exists()
    assert not (world / VAL / f"detections_{DET}.hdf5").exists()
    for policy in ("agent", "explorer"):
        assert json.loads((ev / "lineage" / policy / "metrics.json").read_text())["detections"] == "tinyrobo2"
    assert json.loads((agent / "config.json").read_text())["train"]["detections"] == DET  # trained on DET's
    md = (agent / "card.md").read_text()
    assert f"| trained with | the shipped detector {DET}'s tables (evaluated with tinyrobo2's) |" in md
    # tables of that name made by another detector are refused, not read
    other = tmp_path / "other_world"
    shutil.copytree(world, other)
    (other / VAL / "detections_tinyrobo2.hdf5").unlink()
    from tsnav.pipeline.detector_steps import write_learned_tables

    write_learned_tables(other, "tinyrobo2", shipped.shipped_detector(SIZE, DET), progress=False)
    argv = ["release", "eval", "--agent", str(agent), "--data", str(other), "--out", str(tmp_path / "eval2")]
    assert main(argv + ["--workers", "1", "--threads", "1", "--protocol", "lineage"]) == 2
    assert "tables were made by another detector" in capsys.readouterr().err
    # a card whose fingerprint is not its detector's is refused in one line
    card["detector_fingerprint"] = shipped.shipped_meta(DET)["fingerprint"]
    (agent / "card.json").write_text(json.dumps(card))
    assert main(args + ["--workers", "1", "--threads", "1", "--protocol", "lineage", "--force"]) == 2


def test_release_folders_of_another_world():
    from pathlib import Path

    robothor = {"world_preset": "robothor-real", "world_version": 1, "eval_split": "val"}
    assert release.release_folders(robothor, "a", "val") == (
        Path("out/release/world-robothor-real-v1"),
        Path("out/release/eval/a/val"),
    )
    # iTHOR keeps its folders, and its default split
    assert release.release_folders({"world_preset": "ithor-real", "world_version": 2}, "a", "test")[0] == Path(
        "out/release/world-v2"
    )
    assert release.eval_split(robothor) == "val" and release.eval_split({}) == "test"
    assert (
        release.split_rooms(robothor, "val")[0] == "FloorPlan_Val1_1"
        and len(release.split_rooms(robothor, "val")) == 15
    )
    assert release.split_rooms({"world_preset": "ithor-real"}, "test")[:2] == ["FloorPlan22", "FloorPlan24"]


@pytest.mark.parametrize("name", sorted(release.shipped_agents()))
def test_the_shipped_cards_markdown_is_unchanged(name):
    """The iTHOR agents' card.md is what card_markdown writes from their card.json, byte for byte."""
    folder = release.agent_folder(name)
    assert release.card_markdown(release.read_card(folder)) == (folder / "card.md").read_text()


def fake_challenge(data, folder, per_type: int = 6, seed: int = 0) -> int:
    """Challenge-format train records of the scene ``TRAIN`` (the challenge's own train episodes are not packaged):
    ``per_type`` starts at states of the scene for each target type present, written as ``folder/train/TRAIN
    .json.gz``; returns their number."""
    from tsnav.constants import ROBOTHOR12

    scene = load_scene(data / TRAIN)
    rng = np.random.default_rng(seed)
    types = sorted({ROBOTHOR12.categories[c] for c in np.unique(scene.object_category) if c >= 0})
    records = []
    for t in types:
        for s in rng.choice(scene.num_states, per_type, replace=False):
            x, z, rot, hor = str(scene.keys[s]).split("|")
            records.append(
                {
                    "id": f"{TRAIN}_{t}_{len(records)}",
                    "scene": TRAIN,
                    "object_type": t,
                    "initial_position": {"x": float(x), "y": 0.9, "z": float(z)},
                    "initial_orientation": float(rot),
                    "initial_horizon": float(hor),
                    "shortest_path_length": 2.0,
                }
            )
    (folder / "train").mkdir(parents=True, exist_ok=True)
    (folder / "train" / f"{TRAIN}.json.gz").write_bytes(gzip.compress(json.dumps(records).encode()))
    return len(records)


def test_checkpoints_scored_on_a_sample_of_the_challenges_train_episodes(robo, tmp_path):
    """[scoring] episodes = "challenge-train": the convergence chunks and the second selection score checkpoints on
    fixed samples of the challenge's train episodes converted on the train scenes (the same sample for the same
    seed, another for another), never on a val scene; "none" packs the last checkpoint."""
    from tsnav.pipeline.agent_recipe import MadeAgent, SelectSettings, select_again
    from tsnav.pipeline.steps import ensure_challenge_episodes
    from tsnav.sim.episodes import read_episodes

    challenge = tmp_path / "challenge"
    n = fake_challenge(robo["data"], challenge)
    full = ensure_challenge_episodes(robo["data"], "train", tmp_path / "all.json", "lineage", challenge=challenge)
    every, meta = read_episodes(full)
    assert meta["conversion"]["read"] == n and 0 < len(every) <= n and "sample" not in meta
    a = ensure_challenge_episodes(
        robo["data"], "train", tmp_path / "a.json", "lineage", challenge=challenge, per_room_type=5, seed=1
    )
    b = ensure_challenge_episodes(
        robo["data"], "train", tmp_path / "b.json", "lineage", challenge=challenge, per_room_type=5, seed=1
    )
    c = ensure_challenge_episodes(
        robo["data"], "train", tmp_path / "c.json", "lineage", challenge=challenge, per_room_type=5, seed=2
    )
    (ea, ma), (eb, _), (ec, _) = (read_episodes(p) for p in (a, b, c))
    assert len(ea) == 5 and [e.to_json() for e in ea] == [e.to_json() for e in eb] != [e.to_json() for e in ec]
    assert all(e.to_json() in [f.to_json() for f in every] for e in ea) and {e.scene for e in ea} == {TRAIN}
    assert ma["sample"] == {"per_room_type": 5, "seed": 1, "of": len(every)}
    assert ma["challenge"] == str(challenge.resolve())
    with pytest.raises(ValueError, match="drawn under the lineage protocol, not paper"):
        ensure_challenge_episodes(robo["data"], "train", a, "paper", challenge=challenge)
    # the second selection on such a sample: every milestone scored on it, the best chosen
    import shutil

    run = tmp_path / "run"
    shutil.copytree(robo["run"], run)
    copy = select_again(run, robo["data"], "lineage", SelectSettings(per_room_type=4, seed=1), tmp_path, challenge)
    sel = json.loads((copy / "selection.json").read_text())
    assert sel["episodes_file"] == str((tmp_path / "train_challenge_select_lineage.json").resolve())
    assert len(sel["scores"]) == 2 and (copy / "best" / "model.safetensors").exists()
    assert len(read_episodes(tmp_path / "train_challenge_select_lineage.json")[0]) == 4
    # scoring "none": the run's last checkpoint is the one packed
    made = MadeAgent(robo["data"], run, robo["root"] / "pre", robo["feats"], last=True)
    assert made.checkpoint == sorted((run / "checkpoints").iterdir())[-1]
    assert MadeAgent(robo["data"], run, robo["root"] / "pre", robo["feats"]).checkpoint == run / "best"


def test_convergence_chunks_scored_on_a_given_list(robo, tmp_path):
    """run_convergence with ``episodes``: each chunk scored on that list (the challenge's train sample of a RoboTHOR
    recipe), no val list drawn."""
    from tsnav.pipeline.convergence import run_convergence
    from tsnav.pipeline.steps import ensure_challenge_episodes
    from tsnav.rl.train import stored_config

    challenge = tmp_path / "challenge"
    fake_challenge(robo["data"], challenge)
    eps = ensure_challenge_episodes(
        robo["data"], "train", tmp_path / "s.json", "lineage", challenge=challenge, per_room_type=4, seed=0
    )
    cfg, agent = stored_config(robo["run"])
    points = run_convergence(cfg, agent, tmp_path / "conv", chunk=1, episodes=eps, say=lambda m: None)
    assert [p["update"] for p in points] == [1, 2]
    sel = json.loads((tmp_path / "conv" / "run" / "selection.json").read_text())
    assert sel["episodes_file"] == str(eps.resolve())
    assert not list((tmp_path / "conv").glob("val_episodes*.json"))


def test_release_eval_of_an_agent_whose_detector_reads_finer_frames(robo, tmp_path, monkeypatch, capsys):
    """A card whose shipped detector reads 64-px frames while the agent's rooms have 32-px ones (``tsnav detect
    --frames``): release eval builds the val scene again at 64 px beside --data, the detector writes its table
    there, and --data's scene gets it with the boxes scaled to 32 px; a second run reads the saved table."""

    from tsnav.data.detections import load_detections, rescale_detections
    from tsnav.detect import shipped

    monkeypatch.setitem(shipped.SHIPPED, "tinyrobohr", _save_tiny_detector(tmp_path / "dethr", 2, 2 * SIZE, 0.0))
    agent, card = _agent_evaluated_with(robo, tmp_path, "tinyrobohr")
    assert release.detector_frames(card) == 2 * SIZE
    world, ev = tmp_path / "val_world", tmp_path / "eval"
    argv = ["release", "eval", "--agent", str(agent), "--data", str(world), "--out", str(ev), "--build-world"]
    argv += ["--workers", "1", "--threads", "1", "--protocol", "lineage"]
    assert main(argv) == 0
    assert f"at {2 * SIZE} px (the detector's frames)" in capsys.readouterr().out
    fine = tmp_path / f"val_world-{2 * SIZE}px" / VAL
    assert load_scene(fine).image_size == 2 * SIZE and load_scene(world / VAL).image_size == SIZE
    native = load_detections(fine, "tinyrobohr")
    scaled = load_detections(world / VAL, "tinyrobohr")
    assert native.image_size == 2 * SIZE and scaled.image_size == SIZE
    assert (native.labels >= 0).any()
    ref = rescale_detections(native, SIZE)
    np.testing.assert_array_equal(scaled.boxes, ref.boxes)
    np.testing.assert_array_equal(scaled.scores, native.scores)
    assert scaled.config["frames_size"] == 2 * SIZE
    assert json.loads((ev / "lineage" / "agent" / "metrics.json").read_text())["detections"] == "tinyrobohr"
    assert main(argv) == 0  # nothing changed: the saved table
    assert "nothing changed since the evaluation" in capsys.readouterr().out


def test_frames_tables_refuse_rooms_that_are_not_the_detectors_build(robo, tmp_path):
    """write_learned_tables with frames: one-line errors for a frames folder without the scene, and for one whose frames are not
    the detector's side; nothing is written into the rooms."""
    import shutil

    from tsnav.detect.learned import LearnedDetector
    from tsnav.errors import CommandError
    from tsnav.pipeline.detector_steps import write_learned_tables

    data = tmp_path / "world"
    shutil.copytree(robo["data"] / TRAIN, data / TRAIN, ignore=shutil.ignore_patterns("detections_*"))
    det = LearnedDetector.load(_save_tiny_detector(tmp_path / "dethr", 2, 2 * SIZE, 0.0))
    (tmp_path / "empty").mkdir()
    with pytest.raises(CommandError, match=f"no complete scene {TRAIN}"):
        write_learned_tables(data, "x", det, progress=False, frames=tmp_path / "empty")
    with pytest.raises(CommandError, match=f"its frames are {SIZE} px"):
        write_learned_tables(data, "x", det, progress=False, frames=robo["data"])
    assert not list(data.rglob("detections_x.hdf5"))
