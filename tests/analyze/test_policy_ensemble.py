"""``tsnav analyze policy-ensemble`` (issue 23 analysis): a one-member ensemble is the agent itself (the reference:
``tsnav eval --run``), a run doubled is the run, two different runs give a valid evaluation folder, bad input is
one line."""

import json

import numpy as np
import pytest

from rl_helpers import train_argv
from tsnav.cli import main
from tsnav.eval.runner import read_trajectories

from conftest import PIXEL_FEATURES as FEATS
from script_helpers import load_analysis

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def ens():
    return load_analysis("policy_ensemble")


@pytest.fixture(scope="module")
def two_runs(pixel_world, tmp_path_factory):
    base = tmp_path_factory.mktemp("ens")
    runs = []
    for seed in (0, 1):
        run = base / f"run{seed}"
        assert (
            main(
                train_argv(
                    str(pixel_world),
                    str(run),
                    FEATS,
                    "--reward",
                    "tsrm",
                    "--updates",
                    "3",
                    "--seed",
                    str(seed),
                    "--lr",
                    "1e-2",
                )
            )
            == 0
        )
        runs.append(run)
    eps = base / "eps.json"
    assert (
        main(["episodes", "--data", str(pixel_world), "--split", "test", "--per-room-type", "6", "--out", str(eps)])
        == 0
    )
    return pixel_world, runs, eps


def test_one_member_is_the_agent(ens, two_runs, tmp_path, capsys):
    world, (run, other), eps = two_runs
    ref = tmp_path / "ref"
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
                "--checkpoint",
                "latest",
                "--out",
                str(ref),
            ]
        )
        == 0
    )
    ref_traj = read_trajectories(ref / "trajectories.jsonl")
    for members, average in (([run], "prob"), ([run, run], "prob"), ([run, run, run], "logprob")):
        out = tmp_path / f"e{len(members)}{average}"
        argv = [
            "--data",
            str(world),
            "--episodes",
            str(eps),
            "--checkpoint",
            "latest",
            "--average",
            average,
            "--out",
            str(out),
        ]
        for r in members:
            argv += ["--run", str(r)]
        assert ens.main(argv) == 0
        traj = read_trajectories(out / "trajectories.jsonl")
        assert [t.actions for t in traj] == [t.actions for t in ref_traj]
        m, mr = (json.loads((d / "metrics.json").read_text()) for d in (out, ref))
        assert (
            m["metrics"]["ALL"] == mr["metrics"]["ALL"] and m["policy"] == "ensemble" and len(m["runs"]) == len(members)
        )
    assert "ensemble of 3 (logprob)" in capsys.readouterr().out
    # two different agents: still a complete evaluation, and the action is each step's argmax of the summed probabilities
    out = tmp_path / "pair"
    assert (
        ens.main(
            [
                "--data",
                str(world),
                "--episodes",
                str(eps),
                "--checkpoint",
                "latest",
                "--run",
                str(run),
                "--run",
                str(other),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    traj = read_trajectories(out / "trajectories.jsonl")
    assert len(traj) == len(ref_traj) and all(0 <= a < 6 for t in traj for a in t.actions)


def test_the_summed_probabilities_decide(ens):
    """By hand: two members whose logits disagree; the ensemble takes the action of the larger summed probability
    and tells both members that action."""
    import torch

    class Member:  # the two methods of AgentPolicy the ensemble calls
        def __init__(self, logits):
            self.out, self.told = torch.tensor([logits]), None

        def logits(self, obs):
            return self.out, "state"

        def commit(self, state, action):
            self.told = int(action[0])

    a, b = Member([3.0, 0.0, 0.0, 0.0, 0.0, 0.0]), Member([0.0, 2.0, 2.1, 0.0, 0.0, 0.0])
    obs = {"state": np.array([0]), "target": np.array([0])}
    # probabilities: a gives action 0 about 0.80; b gives actions 1 and 2 about 0.33 each and action 0 0.04
    assert ens.EnsemblePolicy([a, b]).act(obs).tolist() == [0] and a.told == b.told == 0
    a2, b2 = Member([0.0, 0.0, 0.0, 0.0, 0.0, 0.0]), Member([0.0, 0.0, 5.0, 0.0, 0.0, 0.0])
    assert ens.EnsemblePolicy([a2, b2], "logprob").act(obs).tolist() == [2] and a2.told == 2
    with pytest.raises(ValueError, match="average"):
        ens.EnsemblePolicy([a], "mean")
    with pytest.raises(ValueError, match="at least one"):
        ens.EnsemblePolicy([])


def test_bad_run_is_one_line(ens, two_runs, tmp_path, capsys):
    world, _, eps = two_runs
    assert (
        ens.main(
            [
                "--data",
                str(world),
                "--episodes",
                str(eps),
                "--run",
                str(tmp_path / "nothing"),
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "not a `tsnav train` run folder" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()
