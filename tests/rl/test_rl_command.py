"""`tsnav train` and `tsnav eval --run`: run folder contents, resume / no retraining, one-line errors, and the
trained agent as an evaluation policy (per-episode state, batch independence)."""

import json

import numpy as np
import pytest
import torch

from rl_helpers import train_argv
from tsnav.cli import main
from tsnav.eval.policies import Policy
from tsnav.eval.runner import EvalConfig, eval_policy, evaluate
from tsnav.rl.checkpoint import list_checkpoints, load_policy
from tsnav.sim.batch import SceneBank
from tsnav.sim.episodes import read_episodes

from conftest import PIXEL_FEATURES as FEATS


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def trained(pixel_world, tmp_path_factory):
    tiny_world = pixel_world
    run = tmp_path_factory.mktemp("cmd") / "run"
    rc = main(
        train_argv(
            str(tiny_world),
            str(run),
            FEATS,
            "--reward",
            "tsrm",
            "--updates",
            "4",
            "--checkpoint-every",
            "2",
            "--log-every",
            "1",
            "--lr",
            "1e-3",
        )
    )
    assert rc == 0
    return tiny_world, run


def test_run_folder(trained):
    _, run = trained
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["format"] == "tsnav-train-run" and cfg["train"]["algo"] == "batched"
    assert cfg["train"]["updates"] == 4 and cfg["train"]["gamma"] == 0.99 and cfg["train"]["max_grad_norm"] == 100.0
    assert cfg["agent"]["dropout"] == 0.45 and cfg["reward"]["variant"] == "tsrm" and cfg["reward"]["k_explore"] == 0.1
    assert cfg["features"]["shape"] == [3, 4, 4] and cfg["features"]["name"] == FEATS
    assert [p.name for p in list_checkpoints(run)] == ["ckpt_000000002", "ckpt_000000004"]
    assert len((run / "log.jsonl").read_text().splitlines()) == 4
    assert any((run / "tb").iterdir())


def test_resume_budget_and_errors(trained, tmp_path, capsys):
    world, run = trained
    assert main(["train", "--out", str(run), "--quiet"]) == 0
    assert "already finished" in capsys.readouterr().out
    assert main(["train", "--out", str(run), "--updates", "6", "--quiet"]) == 0
    assert "after 6 updates" in capsys.readouterr().out
    assert json.loads((run / "config.json").read_text())["train"]["updates"] == 6
    assert main(["train", "--out", str(run), "--lr", "0.5", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "another configuration (lr)" in err and len(err.splitlines()) == 1
    assert main(["train", "--out", str(tmp_path / "new"), "--data", str(world), "--quiet"]) == 2
    assert "--features is required" in capsys.readouterr().err
    assert (
        main(
            [
                "train",
                "--out",
                str(tmp_path / "new"),
                "--data",
                str(world),
                "--features",
                "nothing",
                "--detections",
                "oracle",
                "--quiet",
            ]
        )
        == 2
    )
    assert "no feature cache" in capsys.readouterr().err
    assert main(["train", "--out", str(tmp_path / "new"), "--data", str(world), "--features", FEATS, "--quiet"]) == 2
    assert "--detections is required" in capsys.readouterr().err  # no silent fallback to ground truth


def test_eval_run_and_policy(trained, tmp_path, capsys):
    world, run = trained
    eps = tmp_path / "eps.json"
    assert main(["episodes", "--data", str(world), "--split", "test", "--per-room-type", "6", "--out", str(eps)]) == 0
    out = tmp_path / "eval"
    assert main(["eval", "--data", str(world), "--episodes", str(eps), "--run", str(run), "--out", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["policy"] == "agent" and m["run"] == str(run.resolve())
    assert m["metrics"]["ALL"]["episodes"] > 0 and m["sample"] is False
    assert (
        main(
            [
                "eval",
                "--data",
                str(world),
                "--episodes",
                str(eps),
                "--run",
                str(run),
                "--out",
                str(tmp_path / "eval_s"),
                "--sample",
                "--seed",
                "3",
            ]
        )
        == 0
    )
    assert json.loads((tmp_path / "eval_s" / "metrics.json").read_text())["sample"] is True

    episodes, _ = read_episodes(eps)
    bank = SceneBank.from_root(world, "test")
    pol = load_policy(run, bank, greedy=True)
    assert isinstance(pol, Policy)
    together = evaluate(bank, episodes, pol, EvalConfig(max_steps=20))
    alone = [
        evaluate(bank, [e], load_policy(run, bank, greedy=True), EvalConfig(max_steps=20))[0] for e in episodes[:4]
    ]
    for a, b in zip(alone, together[:4]):  # each episode keeps its own LSTM state and memory
        assert (a.success, a.path_length, a.steps) == (b.success, b.path_length, b.steps)
    again = evaluate(bank, episodes, pol, EvalConfig(max_steps=20))  # greedy: deterministic, state reset
    assert [r.steps for r in again] == [r.steps for r in together]
    # sampled (--sample): reproducible for a seed, different for another
    runs = [
        evaluate(bank, episodes, load_policy(run, bank, greedy=False, seed=s), EvalConfig(max_steps=20))
        for s in (3, 3, 4)
    ]
    assert [r.steps for r in runs[0]] == [r.steps for r in runs[1]] != [r.steps for r in runs[2]]
    a = load_policy(run, bank).act({"state": np.array([0, 1]), "target": np.array([0, 0])})
    assert a.shape == (2,) and a.dtype == np.int64


def test_eval_with_another_detection_table(trained, tmp_path, capsys):
    """`tsnav eval --detections NAME`: the stage switch follows that table, and a trained agent reads it instead
    of its training table (a detector swapped at test time); a missing table is a one-line error."""
    import dataclasses
    import shutil

    from tsnav.data.detections import load_detections, write_detections
    from tsnav.data.reader import list_scenes

    world0, run = trained
    world = tmp_path / "world"
    shutil.copytree(world0, world)
    for scene in list_scenes(world):  # a detector that never sees anything
        det = load_detections(scene, "oracle")
        blind = dataclasses.replace(
            det,
            scores=np.zeros_like(det.scores),
            labels=np.full_like(det.labels, -1),
            boxes=np.full_like(det.boxes, -1),
            features=np.zeros_like(det.features),
            fingerprint="blind-test",
        )
        write_detections(scene, "blind", blind)
    eps = tmp_path / "eps.json"
    assert main(["episodes", "--data", str(world), "--split", "test", "--per-room-type", "6", "--out", str(eps)]) == 0
    for policy in (["--policy", "explorer"], ["--run", str(run)]):
        out = tmp_path / f"eval_{policy[0][2:]}"
        assert (
            main(
                [
                    "eval",
                    "--data",
                    str(world),
                    "--episodes",
                    str(eps),
                    *policy,
                    "--detections",
                    "blind",
                    "--out",
                    str(out),
                ]
            )
            == 0
        )
        m = json.loads((out / "metrics.json").read_text())
        assert m["detections"] == "blind" and m["detector_confidence"] is True
        assert m["metrics"]["ALL"]["SSR"] == 0.0 and m["metrics"]["ALL"]["episodes"] > 0  # the switch never fires
    # the explorer with the oracle's table does switch
    assert (
        main(
            [
                "eval",
                "--data",
                str(world),
                "--episodes",
                str(eps),
                "--policy",
                "explorer",
                "--detections",
                "oracle",
                "--out",
                str(tmp_path / "eval_oracle"),
            ]
        )
        == 0
    )
    assert json.loads((tmp_path / "eval_oracle" / "metrics.json").read_text())["metrics"]["ALL"]["SSR"] > 0
    # the agent's detection inputs are the swapped table's (zeros), its own table's otherwise
    swapped = load_policy(run, SceneBank.from_root(world, "test"), detections="blind")
    own = load_policy(run, SceneBank.from_root(world, "test"))
    assert not swapped.observer.detections.features.any() and own.observer.detections.features.any()
    capsys.readouterr()
    assert (
        main(
            [
                "eval",
                "--data",
                str(world),
                "--episodes",
                str(eps),
                "--policy",
                "explorer",
                "--detections",
                "nosuch",
                "--out",
                str(tmp_path / "eval_x"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "detections_nosuch.hdf5" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "eval_x").exists()


def test_greedy_is_the_default_and_takes_the_argmax(trained):
    """Evaluation is greedy by default (the lineage's test-time rule): the action is the argmax of the
    policy's logits, and the seed does not matter."""
    world, run = trained
    bank = SceneBank.from_root(world, "test")
    pol = load_policy(run, bank, seed=1)
    assert pol.greedy and not load_policy(run, bank, greedy=False).greedy
    rng = np.random.default_rng(0)
    states = rng.integers(0, bank.num_states, 32)
    targets = rng.integers(0, 22, 32)
    state = pol.model.initial_state(32, pol.observer.device)
    with torch.no_grad():
        logits, _, _ = pol.model(pol.observer(states, targets), state)
    first = pol.act({"state": states, "target": targets})
    assert np.array_equal(first, logits.argmax(dim=1).numpy())
    assert logits.softmax(1).max(1).values.min() < 0.999  # a real distribution, so sampling could differ
    other = load_policy(run, bank, seed=2)
    assert np.array_equal(other.act({"state": states, "target": targets}), first)
    # report re-rolls: greedy when the folder recorded greedy, sampled for folders that predate the key
    assert eval_policy({"run": str(run), "seed": 0, "sample": False}, bank).greedy
    assert not eval_policy({"run": str(run), "seed": 0, "sample": True}, bank).greedy
    assert not eval_policy({"run": str(run), "seed": 0}, bank).greedy


def test_torchrun_two_ranks(trained, tmp_path):
    """Data parallel under torchrun (gloo): both ranks step their own episodes and keep identical weights."""
    import os
    import socket
    import subprocess
    import sys

    world, _ = trained
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    run = tmp_path / "ddp"
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc-per-node",
        "2",
        "--master-port",
        str(port),
        "-m",
        "tsnav",
        "train",
        "--data",
        str(world),
        "--features",
        FEATS,
        "--detections",
        "oracle",
        "--algo",
        "batched",
        "--out",
        str(run),
        "--updates",
        "2",
        "--num-envs",
        "6",
        "--rollout-steps",
        "4",
        "--preset",
        "cpu",
        "--checkpoint-every",
        "1",
        "--device",
        "cpu",
        "--quiet",
    ]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=240, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert res.returncode == 0, res.stderr[-2000:]
    from tsnav.rl.checkpoint import latest_checkpoint, load_checkpoint

    st = load_checkpoint(latest_checkpoint(run))
    assert st["progress"]["env_steps"] == 2 * 3 * 4 * 2  # --num-envs is per update: 3 episodes on each rank
    assert json.loads((run / "config.json").read_text())["train"]["procs"] == 2  # torchrun's processes are the run's
    assert set(st["rng"]) == {0, 1} and st["rng"][0]["weights"] == st["rng"][1]["weights"]
    assert st["rng"][0]["env"] != st["rng"][1]["env"]  # each rank its own episodes


def test_protocol_of_a_run_is_recorded_and_checked(trained, tmp_path, capsys):
    """A run trained under `--protocol lineage` records it; evaluating it on a paper list needs `--protocol paper`,
    and the output then names both protocols. The paper-trained run is evaluated on a lineage list the same way."""
    world, paper_run = trained
    run = tmp_path / "lineage_run"
    assert (
        main(
            train_argv(
                str(world),
                str(run),
                FEATS,
                "--updates",
                "2",
                "--checkpoint-every",
                "2",
                "--log-every",
                "1",
                "--protocol",
                "lineage",
            )
        )
        == 0
    )
    cfg = json.loads((run / "config.json").read_text())
    assert (
        cfg["train"]["protocol"] == "lineage" and cfg["protocol"] == "lineage" and cfg["sim"]["protocol"] == "lineage"
    )
    assert main(["train", "--out", str(run), "--protocol", "paper", "--quiet"]) == 2  # a run keeps its protocol
    assert "another configuration (protocol)" in capsys.readouterr().err
    eps = {p: tmp_path / f"{p}.json" for p in ("paper", "lineage")}
    for p, f in eps.items():
        assert (
            main(
                [
                    "episodes",
                    "--data",
                    str(world),
                    "--split",
                    "test",
                    "--per-room-type",
                    "6",
                    "--protocol",
                    p,
                    "--out",
                    str(f),
                ]
            )
            == 0
        )
    capsys.readouterr()
    assert (
        main(
            [
                "eval",
                "--data",
                str(world),
                "--episodes",
                str(eps["paper"]),
                "--run",
                str(run),
                "--out",
                str(tmp_path / "x"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "trained under the lineage protocol" in err and "--protocol paper" in err
    assert not (tmp_path / "x").exists()
    for r, p, trained_under in ((run, "paper", "lineage"), (paper_run, "lineage", "paper"), (run, "lineage", None)):
        out = tmp_path / f"ev_{r.name}_{p}"
        extra = ["--protocol", p] if trained_under else []
        assert (
            main(["eval", "--data", str(world), "--episodes", str(eps[p]), "--run", str(r), "--out", str(out), *extra])
            == 0
        )
        text = capsys.readouterr().out
        m = json.loads((out / "metrics.json").read_text())
        assert m["protocol"] == p and m["trained_protocol"] == (trained_under or p)
        assert (
            f"protocol: {p} (agent trained under {trained_under})"
            if trained_under
            else f"protocol: {p} (trained and evaluated)"
        ) in text
    assert (
        main(
            [
                "train",
                "--out",
                str(tmp_path / "bad"),
                "--data",
                str(world),
                "--features",
                FEATS,
                "--detections",
                "oracle",
                "--protocol",
                "1.5m",
                "--quiet",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "unknown success protocol '1.5m'" in err


def test_blocked_action_run(trained, tmp_path, capsys):
    """`tsnav train --blocked-action` (a deviation from the paper, off by default): recorded in the run's agent
    config, kept on resume without the flag, refused for a run trained without it; the trained agent evaluates
    with it (its previous position travels with the per-episode state)."""
    world, plain = trained
    run = tmp_path / "blocked"

    def args(out):
        return train_argv(str(world), str(out), FEATS, "--lr", "1e-3")

    assert main(args(run) + ["--updates", "2", "--blocked-action"]) == 0
    assert json.loads((run / "config.json").read_text())["agent"]["blocked_action"] is True
    assert json.loads((plain / "config.json").read_text())["agent"]["blocked_action"] is False
    assert main(["train", "--out", str(run), "--updates", "3", "--quiet"]) == 0
    assert json.loads((run / "config.json").read_text())["agent"]["blocked_action"] is True
    capsys.readouterr()
    assert main(["train", "--out", str(plain), "--blocked-action", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "without --blocked-action" in err and len(err.splitlines()) == 1
    # a run written before the field existed resumes (the missing field is its default)
    old = tmp_path / "old"
    assert main(args(old) + ["--updates", "1"]) == 0
    cfg = json.loads((old / "config.json").read_text())
    del cfg["agent"]["blocked_action"]
    (old / "config.json").write_text(json.dumps(cfg))
    assert main(["train", "--out", str(old), "--updates", "2", "--quiet"]) == 0
    assert "after 2 updates" in capsys.readouterr().out
    bank = SceneBank.from_root(world, "test")
    pol = load_policy(run, bank, greedy=True)
    assert pol.model.config.blocked_action and pol.model.action_embed.num_embeddings == 8
    eps = tmp_path / "eps.json"
    assert main(["episodes", "--data", str(world), "--split", "test", "--per-room-type", "3", "--out", str(eps)]) == 0
    episodes, _ = read_episodes(eps)
    together = evaluate(bank, episodes, pol, EvalConfig(max_steps=15))
    alone = [
        evaluate(bank, [e], load_policy(run, bank, greedy=True), EvalConfig(max_steps=15))[0] for e in episodes[:3]
    ]
    for a, b in zip(alone, together[:3]):
        assert (a.success, a.path_length, a.steps) == (b.success, b.path_length, b.steps)
