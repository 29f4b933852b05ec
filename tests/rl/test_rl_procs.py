"""The batched trainer on N CPU processes (``TrainConfig.procs``, :func:`tsnav.distributed.run_ranks`): the
averaged gradient of two processes equals one process's over the same episodes, a 2-process run is
deterministic and resumes bit-exactly, failures of either side are reported, configurations are checked."""

from dataclasses import replace

import numpy as np
import pytest
import torch
import torch.distributed as dist

from tsnav.agent import agent_config
from tsnav.distributed import allreduce_gradients, init_distributed, run_ranks
from tsnav.rl.assemble import load_bank, make_model, make_observer, make_train_env
from tsnav.rl.batched import train_batched
from tsnav.rl.checkpoint import load_checkpoint
from tsnav.rl.config import TrainConfig
from tsnav.rl.logger import read_log
from tsnav.rl.rollout import Rollout, RolloutCollector, a2c_loss, collect_and_loss, gae
from tsnav.rl.train import check_resume

from conftest import PIXEL_FEATURES as FEATS


pytestmark = pytest.mark.usefixtures("one_torch_thread")

B, T = 8, 6


def _cfg(world, **kw):
    base = dict(
        data=str(world),
        features=FEATS,
        algo="batched",
        num_envs=8,
        rollout_steps=6,
        max_steps=30,
        checkpoint_every=3,
        log_every=2,
        lr=1e-3,
        device="cpu",
        detections="oracle",
    )
    return TrainConfig(**{**base, **kw})


def _rollout(world) -> tuple:
    """The same recorded rollout of ``B`` episodes on every call (fixed model, env seed and action generator)."""
    cfg = _cfg(world, num_envs=B)
    bank, _ = load_bank(cfg)
    observer = make_observer(bank, cfg)
    model = make_model(agent_config("cpu", dropout=0.0), observer, 0)
    col = RolloutCollector(
        make_train_env(bank, cfg, B, seed=11), observer, model, generator=torch.Generator().manual_seed(3)
    )
    with torch.no_grad():
        ro = col.collect(T)
    return model, observer, ro


def _rows_gradient(model, observer, ro: Rollout, rows: np.ndarray) -> None:
    """Backward of the actor-critic loss of the rollout's ``rows`` alone (re-run through the model with
    gradients, as the trainer computes it on a rank holding those rows)."""
    from rl_helpers import replay

    idx = torch.from_numpy(rows)
    part = Rollout(
        logp=ro.logp[:, idx],
        entropy=ro.entropy[:, idx],
        value=ro.value[:, idx],
        reward=ro.reward[:, idx],
        bootstrap=ro.bootstrap[:, idx],
        terminated=ro.terminated[:, idx],
        finished=ro.finished[:, idx],
        states=ro.states[:, rows],
        targets=ro.targets[:, rows],
        actions=ro.actions[:, rows],
        start=ro.start.index(idx),
    )
    logp, ent, value = replay(model, observer, part)
    adv, ret = gae(part.reward, value, part.bootstrap, part.terminated, part.finished)
    loss, _ = a2c_loss(replace(part, logp=logp, entropy=ent, value=value), adv, ret)
    model.zero_grad()
    loss.backward()


def _flat_grad(model) -> torch.Tensor:
    return torch.cat([p.grad.reshape(-1) for p in model.parameters() if p.grad is not None])


def _rank_gradient(world) -> np.ndarray:
    """One rank of two: the gradient of its half of the rows, all-reduced like the trainer's."""
    info = init_distributed(torch.device("cpu"))
    model, observer, ro = _rollout(world)
    rows = np.arange(B).reshape(info.world, -1)[info.rank]
    _rows_gradient(model, observer, ro, rows)
    allreduce_gradients(model, info)
    return _flat_grad(model).numpy()


def test_two_process_gradient_equals_one_process_gradient_over_the_same_episodes(pixel_world):
    """Each rank's loss is the mean over its B/2 rows; averaging the two ranks' gradients gives the gradient
    of the mean over all B rows, which one process stepping the B episodes computes: same learning rate."""
    model, observer, ro = _rollout(pixel_world)
    _rows_gradient(model, observer, ro, np.arange(B))
    one = _flat_grad(model).numpy()
    two = run_ranks(_rank_gradient, 2, pixel_world)
    assert not dist.is_initialized()
    np.testing.assert_allclose(two, one, rtol=1e-5, atol=1e-7)
    # the rows' halves differ, so this is not a trivial equality; a sum of the two (not a mean) would be twice
    _rows_gradient(model, observer, ro, np.arange(B // 2))
    half = _flat_grad(model).numpy()
    assert np.abs(half - one).max() > 1e-3 * np.abs(one).max()


class Interrupt(Exception):
    pass


def _weights(run):
    from tsnav.checkpoint import load_tensors
    from tsnav.rl.checkpoint import latest_checkpoint

    ck = latest_checkpoint(run)
    return load_tensors(ck / "model.safetensors")[0], load_tensors(ck / "optimizer.safetensors")[0]


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_two_process_run_is_deterministic_and_resumes_exactly(pixel_world, tmp_path):
    cfg = _cfg(pixel_world, procs=2, updates=8)
    agent = agent_config("cpu")
    full = train_batched(cfg, agent, tmp_path / "a", progress_bar=False)
    assert full["update"] == 8 and full["env_steps"] == 8 * 8 * 6

    seen = []

    def kill(progress):
        seen.append(progress["update"])
        if progress["update"] == 5:
            raise Interrupt()

    with pytest.raises(Interrupt):  # rank 0 is interrupted; rank 1 is stopped with it
        train_batched(cfg, agent, tmp_path / "b", progress_bar=False, on_update=kill)
    assert seen == [1, 2, 3, 4, 5] and not dist.is_initialized()
    resumed = train_batched(cfg, agent, tmp_path / "b", progress_bar=False)
    assert (resumed["update"], resumed["episodes"], resumed["env_steps"]) == (8, full["episodes"], full["env_steps"])
    wa, oa = _weights(tmp_path / "a")
    wb, ob = _weights(tmp_path / "b")
    assert _same(wa, wb) and _same(oa, ob)
    la, lb = read_log(tmp_path / "a"), read_log(tmp_path / "b")
    assert [r["update"] for r in la] == [r["update"] for r in lb] == [2, 3, 4, 6, 8]
    assert [(r["loss"], r["n_episodes"]) for r in la] == [(r["loss"], r["n_episodes"]) for r in lb]
    assert all(r["steps_per_cpu_s"] > 0 for r in la)

    # both ranks wrote their RNG state; they agreed on the weights
    state = load_checkpoint(sorted((tmp_path / "a" / "checkpoints").iterdir())[-1])
    assert sorted(state["rng"]) == [0, 1]
    assert state["rng"][0]["weights"] == state["rng"][1]["weights"]
    assert state["rng"][0]["env"] != state["rng"][1]["env"]  # each rank draws its own episodes

    # (the interrupted run's first session, updates 1-3, repeated the same (seed, procs) exactly); one process
    # draws other episodes
    train_batched(replace(cfg, updates=3, procs=1), agent, tmp_path / "d", progress_bar=False)
    assert [r["loss"] for r in read_log(tmp_path / "d")] != [r["loss"] for r in la[:2]]


def _staggered_reference(cfg: TrainConfig, agent, rounds: int) -> dict:
    """``ranks="staggered"`` computed in one process: per round, each "rank" (its own env seed, torch RNG stream
    and collector) collects a rollout from the same weights and computes its gradient; then the gradients are
    clipped and stepped by Adam one after another, rank 0's first."""
    bank, det = load_bank(cfg)
    observer = make_observer(bank, cfg, det_features=det)
    model = make_model(agent, observer, cfg.seed)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, amsgrad=cfg.amsgrad)
    cols, rngs = [], []
    for r in range(cfg.procs):
        torch.manual_seed(cfg.seed * 1000 + 7919 * r + 1)
        col = RolloutCollector(make_train_env(bank, cfg, cfg.num_envs, seed=cfg.seed * 1000 + r), observer, model)
        col.start()
        cols.append(col)
        rngs.append(torch.get_rng_state())
    for _ in range(rounds):
        grads = []
        for r, col in enumerate(cols):
            torch.set_rng_state(rngs[r])
            model.train()
            _, loss, _ = collect_and_loss(col, cfg)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            grads.append([p.grad.clone() for p in model.parameters()])
            rngs[r] = torch.get_rng_state()
        for g in grads:
            for p, gp in zip(model.parameters(), g):
                p.grad = gp
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.max_grad_norm)
            opt.step()
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def test_staggered_ranks_apply_each_ranks_update_in_turn(pixel_world, tmp_path):
    """``ranks="staggered"`` on two processes: each rank steps all ``num_envs`` episodes, a round makes two
    updates, and the weights are those of the one-process reference above, bit for bit; the run resumes exactly
    after an interruption; its boundaries must fall on rounds."""
    agent = agent_config("cpu")
    cfg = _cfg(pixel_world, procs=2, ranks="staggered", updates=4, checkpoint_every=4)
    p = train_batched(cfg, agent, tmp_path / "a", progress_bar=False)
    assert (p["update"], p["env_steps"]) == (4, 4 * 8 * 6)
    want = _staggered_reference(cfg, agent, rounds=2)
    got = _weights(tmp_path / "a")[0]
    assert _same(got, want)
    # not what split computes (two rows each, one update per round)
    train_batched(replace(cfg, ranks="split"), agent, tmp_path / "s", progress_bar=False)
    assert not _same(_weights(tmp_path / "s")[0], got)

    cfg = replace(cfg, updates=6, checkpoint_every=2)
    full = train_batched(cfg, agent, tmp_path / "b", progress_bar=False)
    seen = []

    def kill(progress):
        seen.append(progress["update"])
        if progress["update"] == 4:
            raise Interrupt()

    with pytest.raises(Interrupt):
        train_batched(cfg, agent, tmp_path / "c", progress_bar=False, on_update=kill)
    assert seen == [2, 4]
    resumed = train_batched(cfg, agent, tmp_path / "c", progress_bar=False)
    assert (resumed["update"], resumed["episodes"]) == (6, full["episodes"])
    assert _same(_weights(tmp_path / "b")[0], _weights(tmp_path / "c")[0])
    assert _same(_weights(tmp_path / "b")[1], _weights(tmp_path / "c")[1])

    for name, kw in (
        ("checkpoint_every", {"checkpoint_every": 3}),
        ("log_every", {"log_every": 5}),
        ("milestone_every", {"milestone_every": 7}),
        ("updates", {"updates": 9}),
    ):
        with pytest.raises(ValueError, match=f"{name} must be a multiple of procs=2"):
            _cfg(pixel_world, procs=2, ranks="staggered", **{"updates": 4, "checkpoint_every": 2, **kw})
    with pytest.raises(ValueError, match="unknown ranks mode 'both'"):
        _cfg(pixel_world, ranks="both")
    _cfg(pixel_world, procs=2, ranks="staggered", num_envs=9, checkpoint_every=2)  # each rank steps all 9: no split


def _fail_on_rank1():
    info = init_distributed(torch.device("cpu"))
    if info.rank == 1:
        raise ValueError("rank 1 stops here")
    t = torch.ones(3)
    dist.all_reduce(t)  # rank 1 never joins: its sockets close when it exits
    return t


def test_a_failing_rank_is_reported_by_rank_0(capfd):
    with pytest.raises(RuntimeError, match="rank 1 of 2 failed"):
        run_ranks(_fail_on_rank1, 2)
    assert "rank 1 stops here" in capfd.readouterr().err
    assert not dist.is_initialized()


def test_procs_configuration_is_checked(pixel_world, tmp_path):
    with pytest.raises(ValueError, match="num_envs 9 does not split evenly over procs=2"):
        _cfg(pixel_world, procs=2, num_envs=9)
    with pytest.raises(ValueError, match="procs must be >= 1"):
        _cfg(pixel_world, procs=0)
    with pytest.raises(ValueError, match="batched trainer"):
        _cfg(pixel_world, algo="a3c", procs=2)
    # procs is part of the run's identity: resuming with another value is refused
    from tsnav.rl.train import train_run

    agent = agent_config("cpu")
    train_run(_cfg(pixel_world, updates=1), agent, tmp_path / "r", progress_bar=False)
    with pytest.raises(ValueError, match=r"another configuration \(procs\)"):
        check_resume(tmp_path / "r", _cfg(pixel_world, updates=1, procs=2), agent)


def test_train_command_refuses_procs_that_do_not_split_the_episodes(pixel_world, tmp_path, capsys):
    from tsnav.cli import main

    rc = main(
        [
            "train",
            "--data",
            str(pixel_world),
            "--features",
            FEATS,
            "--detections",
            "oracle",
            "--algo",
            "batched",
            "--out",
            str(tmp_path / "run"),
            "--updates",
            "1",
            "--num-envs",
            "8",
            "--procs",
            "3",
            "--quiet",
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert rc != 0 and len(err) == 1 and "num-envs 8 does not split evenly over procs=3" in err[0], err
    assert not (tmp_path / "run" / "config.json").exists()
