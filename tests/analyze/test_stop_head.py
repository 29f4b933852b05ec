"""``tsnav analyze stop-head`` (issue 47): the replay of a stop rule on the agent's walk without Done against real
evaluations (the agent's own Done replayed equals ``tsnav eval --run``; the head's replay equals the agent run with the
head deciding Done, checked inside the command), the pieces by hand, and bad input in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rl_helpers import train_argv
from tsnav.analyze import stop_head as sh
from tsnav.cli import main
from tsnav.metrics import EpisodeRecord, read_records

from conftest import PIXEL_FEATURES as FEATS

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_first_fire_matches_its_reference():
    rng = np.random.default_rng(0)
    for _ in range(20):
        fire = rng.random((7, 9)) < 0.2
        active = rng.random((7, 9)) < 0.8
        assert sh.first_fire(fire, active).tolist() == sh.first_fire_reference(fire, active)


def test_replay_by_hand():
    recs = [EpisodeRecord(success=False, path_length=100, optimal_length=3, steps=100) for _ in range(3)]
    label = np.array([[0, 0, 1, 1], [0, 1, 0, 0], [0, 0, 0, 0]], dtype=bool)
    out = sh.replay(recs, label, np.array([3, 2, -1]))
    # Done at step 3 on a success state: a success after 3 movement actions; at step 2 on a state that is not
    # one: a failure that stopped there; never: the record of the walk unchanged
    assert [(r.success, r.path_length, r.steps) for r in out] == [(True, 3, 4), (False, 2, 3), (False, 100, 100)]
    assert sh.sr_spl(out, "paper") == pytest.approx({"SR": 100 / 3, "SPL": 100 / 3})
    with pytest.raises(ValueError, match="records for"):
        sh.replay(recs, label, np.array([1]))


def _episodes_argv(world, split: str, per_room_type: int, seed: int, out, protocol: str = "paper") -> list[str]:
    return ["episodes", "--data", str(world), "--split", split, "--per-room-type", str(per_room_type)] + [
        "--seed",
        str(seed),
        "--protocol",
        protocol,
        "--out",
        str(out),
    ]


@pytest.fixture(scope="module")
def setting(pixel_world, tmp_path_factory):
    base = tmp_path_factory.mktemp("stophead")
    run = base / "run"
    assert (
        main(train_argv(str(pixel_world), str(run), FEATS, "--reward", "tsrm", "--updates", "3", "--lr", "1e-2")) == 0
    )
    lists = {}
    for name, split, seed in (("train", "train", 0), ("val", "val", 1), ("test", "test", 2)):
        lists[name] = base / f"{name}.json"
        assert main(_episodes_argv(pixel_world, split, 8, seed, lists[name])) == 0
    return pixel_world, run, lists


def test_command_replays_what_real_evaluations_give(setting, tmp_path, capsys):
    world, run, lists = setting
    out_json, out = tmp_path / "sh.json", tmp_path / "head"
    argv = ["analyze", "stop-head", "--run", str(run), "--data", str(world), "--checkpoint", "latest"]
    argv += ["--train", str(lists["train"]), "--val", str(lists["val"]), "--test", str(lists["test"]), "--epochs", "2"]
    argv += ["--detections", "oracle"]  # the run's own table, named: it reaches the agent and the record
    assert main([*argv, "--json", str(out_json), "--out", str(out)]) == 0
    res = json.loads(out_json.read_text())
    assert res["format"] == "tsnav-stop-head" and res["protocol"] == "paper" and res["inputs"] == ["state", "detection"]
    assert res["detections"] == "oracle"
    # the agent's row is what `tsnav eval --run` gives on the same list (the command also checked it against its own
    # evaluation, and the head's replayed rows against the agent run with the head deciding Done)
    ref = tmp_path / "ref"
    assert (
        main(
            ["eval", "--data", str(world), "--episodes", str(lists["test"]), "--run", str(run)]
            + ["--checkpoint", "latest", "--out", str(ref)]
        )
        == 0
    )
    m = json.loads((ref / "metrics.json").read_text())["metrics"]["ALL"]
    test = res["test"][0]
    assert test["rows"]["agent"] == pytest.approx({"SR": 100 * m["SR"], "SPL": 100 * m["SPL"]})
    tau = res["val"]["chosen_threshold"]
    assert tau in sh.THRESHOLDS and len(res["val"]["sweep"]) == len(sh.THRESHOLDS)
    best = max(s["head"]["SPL"] for s in res["val"]["sweep"])
    assert next(s for s in res["val"]["sweep"] if s["threshold"] == tau)["head"]["SPL"] == best
    # no stop rule beats Done at the first success state of the same walk
    ceiling = test["rows"]["Done at the first success state of the walk"]
    assert all(s["head"]["SR"] <= ceiling["SR"] + 1e-9 for s in test["sweep"])
    # the head's evaluation folder, for lever-table: one record per test episode, its figures the head's row
    recs = read_records(out / "paper" / "records.jsonl")
    meta = json.loads((out / "paper" / "metrics.json").read_text())
    assert len(recs) == test["episodes"] and meta["protocol"] == "paper" and meta["stop_head"]["threshold"] == tau
    assert 100 * meta["metrics"]["ALL"]["SR"] == pytest.approx(test["rows"][f"head at {tau}"]["SR"])
    assert "head trained on" in capsys.readouterr().out


def test_refusals(setting, tmp_path, capsys):
    world, run, lists = setting
    base = ["analyze", "stop-head", "--run", str(run), "--data", str(world), "--checkpoint", "latest"]
    good = ["--train", str(lists["train"]), "--val", str(lists["val"]), "--test", str(lists["test"])]
    lineage = tmp_path / "lin.json"
    assert main(_episodes_argv(world, "test", 4, 0, lineage, "lineage")) == 0
    capsys.readouterr()
    cases = [
        ([*base, *good, "--inputs", "state,depth"], "choose from"),
        ([*base, *good, "--test", str(lists["test"]), str(lists["val"]), "--out", str(tmp_path / "o")], "one --test"),
        ([*base, *good[:-1], str(tmp_path / "missing.json")], "no such episode list"),
        (["analyze", "stop-head", "--run", str(tmp_path), "--data", str(world), *good], "not a training run"),
        (
            [*base, "--train", str(lists["train"]), "--val", str(lists["val"]), "--test", str(lineage)],
            "another protocol",
        ),
    ]
    for argv, msg in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert msg in err and len(err.splitlines()) == 1


def test_true_depth_in_the_box_by_hand():
    depth = object.__new__(sh.BankDepth)
    depth.depth = np.full((2, sh.DEPTH_GRID, sh.DEPTH_GRID), 5.0, dtype=np.float16)
    depth.depth[1, 0:4, 8:16] = np.arange(32, dtype=np.float16).reshape(4, 8) / 8  # 0 ... 3.875 m
    boxes = np.array([[0.25, 0.0, 0.5, 0.125], [0.25, 0.0, 0.5, 0.125], [0.99, 0.99, 1.0, 1.0]])
    out = depth.in_box(np.array([1, 0, 1]), boxes, np.array([0.9, 0.0, 0.8]))
    vals = np.arange(32) / 8
    assert out[0] == pytest.approx([np.median(vals), 0.0, np.percentile(vals, 10)], abs=1e-3)
    assert out[1].tolist() == [9.0, 9.0, 9.0]  # nothing detected
    assert out[2] == pytest.approx([5.0, 5.0, 5.0])  # a box at the edge still reads one cell
    rng = np.random.default_rng(0)  # the batch code against the loop, on random boxes and scores
    depth.depth = rng.uniform(0.2, 6.0, (5, sh.DEPTH_GRID, sh.DEPTH_GRID)).astype(np.float16)
    corners = np.sort(rng.random((200, 2, 2)), axis=1)
    boxes = corners.transpose(0, 2, 1).reshape(200, 4)[:, [0, 2, 1, 3]]  # x0 y0 x1 y1, x0 <= x1 and y0 <= y1
    states, scores = rng.integers(0, 5, 200), np.where(rng.random(200) < 0.2, 0.0, rng.random(200))
    assert np.allclose(depth.in_box(states, boxes, scores), depth.in_box_reference(states, boxes, scores), atol=1e-5)


def test_true_depth_is_recorded_as_a_diagnostic(setting, tmp_path):
    world, run, lists = setting
    out_json = tmp_path / "d.json"
    argv = ["analyze", "stop-head", "--run", str(run), "--data", str(world), "--checkpoint", "latest"]
    argv += ["--train", str(lists["train"]), "--val", str(lists["val"]), "--test", str(lists["test"]), "--epochs", "1"]
    assert main([*argv, "--inputs", "state,detection,true-depth", "--json", str(out_json)]) == 0
    res = json.loads(out_json.read_text())
    assert res["inputs"][-1] == "true-depth" and res["diagnostic_inputs"] == ["true-depth"]


def test_check_same_names_the_first_episode_that_differs():
    a = [EpisodeRecord(success=True, path_length=4, optimal_length=3, steps=5) for _ in range(3)]
    b = [*a[:2], EpisodeRecord(success=False, path_length=4, optimal_length=3, steps=5)]
    sh.check_same(a, list(a), "same")
    with pytest.raises(RuntimeError, match="episode 2"):
        sh.check_same(a, b, "x")


def test_detections_reach_the_agent(setting, tmp_path, monkeypatch):
    import tsnav.rl.checkpoint as ck

    world, run, lists = setting
    seen, original = [], ck.load_policy

    def spy(*args, **kwargs):
        seen.append(kwargs.get("detections"))
        return original(*args, **kwargs)

    monkeypatch.setattr(ck, "load_policy", spy)
    argv = ["--run", str(run), "--data", str(world), "--checkpoint", "latest", "--detections", "oracle"]
    argv += ["--train", str(lists["train"]), "--val", str(lists["val"]), "--test", str(lists["test"]), "--epochs", "1"]
    assert sh.main(argv) == 0
    # the training walk; the val walk and its real evaluation; the test walk, its real evaluation and the two rules'
    assert seen == ["oracle"] * 7


def test_bank_depth_reads_the_world_frames(setting):
    import h5py

    from tsnav.eval.runner import load_bank_for_episodes
    from tsnav.sim.episodes import read_episodes

    world, _, lists = setting
    episodes, _ = read_episodes(lists["test"])
    bank = load_bank_for_episodes(world, episodes[:1])
    depth = sh.BankDepth(bank)
    scene = bank.scenes[0]
    with h5py.File(scene.depth_path(), "r") as f:
        frame = np.asarray(f[str(scene.keys[3])], dtype=np.float32)
    k = frame.shape[0] // sh.DEPTH_GRID
    want = frame.reshape(sh.DEPTH_GRID, k, sh.DEPTH_GRID, k).mean(axis=(1, 3))
    assert np.allclose(depth.depth[bank.offsets[0] + 3].astype(np.float32), want, atol=1e-2)


def test_depth_readout_command_and_est_depth(setting, tmp_path, capsys):
    world, run, lists = setting
    readout, scores = tmp_path / "readout.safetensors", tmp_path / "scores.json"
    argv = ["analyze", "depth-readout", "--data", str(world), "--features", FEATS, "--out", str(readout)]
    assert main([*argv, "--epochs", "1", "--json", str(scores)]) == 0
    res = json.loads(scores.read_text())
    assert res["features"] == FEATS and res["scores"]["val"]["frames"] > 0
    out_json = tmp_path / "head.json"
    argv = ["analyze", "stop-head", "--run", str(run), "--data", str(world), "--checkpoint", "latest"]
    argv += ["--train", str(lists["train"]), "--val", str(lists["val"]), "--test", str(lists["test"]), "--epochs", "1"]
    assert main([*argv, "--inputs", "state,est-depth", "--depth-readout", str(readout), "--json", str(out_json)]) == 0
    head = json.loads(out_json.read_text())
    assert head["inputs"] == ["state", "est-depth"] and head["diagnostic_inputs"] == []
    assert head["depth_readout"]["features"] == FEATS
    capsys.readouterr()
    # est-depth without a readout, and a file that is not one: one line each
    assert main([*argv, "--inputs", "state,est-depth"]) == 2
    assert "--depth-readout goes with --inputs ...,est-depth" in capsys.readouterr().err
    assert main([*argv, "--inputs", "state", "--depth-readout", str(readout)]) == 2
    assert "and only with it" in capsys.readouterr().err
    assert main([*argv, "--inputs", "state,est-depth", "--depth-readout", str(scores)]) == 2
    err = capsys.readouterr().err.strip()
    assert "broken" in err and len(err.splitlines()) == 1
    missing = tmp_path / "none"
    assert main(["analyze", "depth-readout", "--data", str(missing), "--features", FEATS, "--out", str(readout)]) == 2
    err = capsys.readouterr().err.strip()
    assert "no such dataset folder" in err and len(err.splitlines()) == 1
    assert readout.is_file()  # a failed run leaves the existing file alone


def _detected(observer, n=200):
    """Up to ``n`` (state, target) pairs the observer's detection table has a box for (score above 0)."""
    states, targets = np.nonzero(observer.detections.score > 0)
    pick = np.linspace(0, len(states) - 1, min(n, len(states))).astype(int)
    assert len(pick) >= 10
    return states[pick], targets[pick]


def test_an_agent_reading_the_target_depth_trains_and_evaluates(setting, tmp_path, capsys):
    """AgentConfig.target_depth end to end: a readout of the world's features, an agent trained with it (recorded
    in its config), its observations carry the readout's depth in the target's box (on detected targets), `tsnav eval`
    runs it, and a readout of another encoder's features is refused in one line."""
    import torch

    from tsnav.agent.observe import box_depth_stats
    from tsnav.checkpoint import load_tensors, save_tensors
    from tsnav.eval.runner import load_bank_for_episodes
    from tsnav.pretrain.depth_readout import load_readout
    from tsnav.rl.checkpoint import load_policy
    from tsnav.sim.episodes import read_episodes

    world, _, lists = setting
    readout = tmp_path / "readout.safetensors"
    assert main(["analyze", "depth-readout", "--data", str(world), "--features", FEATS, "--out", str(readout)]) == 0
    run = tmp_path / "run"
    argv = train_argv(str(world), str(run), FEATS, "--updates", "2", "--target-depth", str(readout))
    assert main(argv) == 0
    assert json.loads((run / "config.json").read_text())["agent"]["target_depth"] == str(readout)
    episodes, _ = read_episodes(lists["test"])
    bank = load_bank_for_episodes(world, episodes)
    policy = load_policy(run, bank, checkpoint="latest")
    states, targets = _detected(policy.observer)
    obs = policy.observer(states, targets)
    assert (obs.det_depth[:, 3] == 1).all() and (obs.det_depth[:, :3] < 1).any()
    model, _ = load_readout(readout)
    with torch.no_grad():
        maps = model(policy.observer.features[states].float()).half()
    assert torch.equal(obs.det_depth, box_depth_stats(maps, obs.det_box, obs.det_score))
    out = tmp_path / "eval"
    argv = ["eval", "--data", str(world), "--episodes", str(lists["test"]), "--run", str(run), "--out", str(out)]
    assert main(argv) == 0 and (out / "metrics.json").is_file()
    # the same readout said to come from another encoder: refused when the agent is loaded
    tensors, meta = load_tensors(readout)
    save_tensors(readout, tensors, {**meta, "fingerprint": "0123456789abcdef"})
    capsys.readouterr()
    assert main([*argv[:-1], str(tmp_path / "eval2")]) == 2
    err = capsys.readouterr().err.strip()
    assert "a readout of the features of encoder 0123456789abcdef" in err and len(err.splitlines()) == 1


def test_a_relative_readout_path_is_read_from_the_working_directory(setting, tmp_path, monkeypatch):
    """A run trained with a relative --target-depth path reads that path from the working directory when loaded, and
    names the file when it is not there."""
    from tsnav.eval.runner import load_bank_for_episodes
    from tsnav.rl.checkpoint import load_policy
    from tsnav.sim.episodes import read_episodes

    world, _, lists = setting
    monkeypatch.chdir(tmp_path)
    assert main(["analyze", "depth-readout", "--data", str(world), "--features", FEATS, "--out", "r.safetensors"]) == 0
    run = tmp_path / "run"
    assert main(train_argv(str(world), str(run), FEATS, "--updates", "1", "--target-depth", "r.safetensors")) == 0
    episodes, _ = read_episodes(lists["test"])
    bank = load_bank_for_episodes(world, episodes[:2])
    assert load_policy(run, bank, checkpoint="latest").observer.target_depth.source == "r.safetensors"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    with pytest.raises(ValueError, match="r.safetensors: no such depth readout file"):
        load_policy(run, bank, checkpoint="latest")


def test_the_ground_truth_depth_diagnostic_reads_the_world_frames(setting, tmp_path):
    """target_depth ``ground-truth`` (a diagnostic): the agent's depth input is the world's depth frames averaged to
    the readout's grid (flipped in a mirrored room, as its frames are), and such a run is refused by `tsnav release
    pack` in one line."""
    import h5py
    import torch

    from tsnav.agent.observe import GROUND_TRUTH, TargetDepth, box_depth_stats
    from tsnav.errors import CommandError
    from tsnav.eval.runner import load_bank_for_episodes
    from tsnav.pipeline.release import pack
    from tsnav.pretrain.depth_readout import average_depth
    from tsnav.rl.checkpoint import load_policy
    from tsnav.sim.batch import SceneBank
    from tsnav.sim.episodes import read_episodes

    world, _, lists = setting
    run = tmp_path / "run"
    assert main(train_argv(str(world), str(run), FEATS, "--updates", "1", "--target-depth", GROUND_TRUTH)) == 0
    episodes, _ = read_episodes(lists["test"])
    bank = load_bank_for_episodes(world, episodes)
    policy = load_policy(run, bank, checkpoint="latest")
    states, targets = _detected(policy.observer)
    obs = policy.observer(states, targets)
    frames = []
    for s in states:
        i = int(np.searchsorted(bank.offsets, s, side="right")) - 1
        scene = bank.scenes[i]
        with h5py.File(scene.depth_path(), "r") as f:
            frames.append(average_depth(f[str(scene.keys[s - int(bank.offsets[i])])][()]))
    want = box_depth_stats(torch.from_numpy(np.stack(frames)).half(), obs.det_box, obs.det_score)
    assert torch.equal(obs.det_depth, want) and (obs.det_depth[:, 3] == 1).all()
    scene = bank.scenes[0]
    mirrored = TargetDepth.from_world(SceneBank([scene.mirrored()]))
    plain = policy.observer.target_depth.maps[: scene.num_states]
    assert torch.equal(mirrored.maps, plain.flip(-1)) and not torch.equal(mirrored.maps, plain)
    with pytest.raises(CommandError, match="reads a target depth"):
        pack(run, run / "checkpoints", tmp_path, tmp_path / "out", {})
    assert not (tmp_path / "out").exists()
