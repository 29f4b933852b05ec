"""A3C: the shared Adam keeps its state in shared memory, a worker update lowers the loss of its rollout on
the shared model, and a short run with 2 worker processes shares counters, checkpoints, resumes and stops."""

import numpy as np
import pytest
import torch

from tsnav.agent import agent_config
from tsnav.rl.a3c import SharedAdam, a3c_update, train_a3c
from tsnav.rl.checkpoint import latest_checkpoint, load_checkpoint
from tsnav.rl.config import TrainConfig
from tsnav.rl.logger import read_log
from tsnav.rl.rollout import RolloutCollector, a2c_loss, gae
from rl_helpers import replay
from tsnav.rl.assemble import load_bank, make_model, make_observer, make_train_env

from conftest import PIXEL_FEATURES as FEATS


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def world(pixel_world):
    return pixel_world


def _cfg(world, **kw):
    base = dict(
        data=str(world),
        features=FEATS,
        algo="a3c",
        workers=2,
        rollout_steps=8,
        lr=1e-3,
        device="cpu",
        log_every=4,
        checkpoint_every=5,
        detections="oracle",
    )
    return TrainConfig(**{**base, **kw})


def test_shared_adam_state_is_shared_and_matches_adam():
    torch.manual_seed(0)
    a = torch.nn.Linear(4, 3)
    b = torch.nn.Linear(4, 3)
    b.load_state_dict(a.state_dict())
    shared = SharedAdam(a.parameters(), lr=1e-2)
    plain = torch.optim.Adam(b.parameters(), lr=1e-2, amsgrad=True)
    for p in a.parameters():
        st = shared.state[p]
        assert all(st[k].is_shared() for k in ("step", "exp_avg", "exp_avg_sq", "max_exp_avg_sq"))
    x = torch.randn(8, 4)
    for _ in range(3):
        for m, opt in ((a, shared), (b, plain)):
            opt.zero_grad()
            (m(x) ** 2).sum().backward()
            opt.step()
    for pa, pb in zip(a.parameters(), b.parameters()):
        torch.testing.assert_close(pa, pb)
        assert float(shared.state[pa]["step"]) == 3.0


def test_worker_update_lowers_the_loss_on_the_shared_model(world):
    cfg = _cfg(world)
    bank, _ = load_bank(cfg)
    obs_fn = make_observer(bank, cfg)
    agent = agent_config("cpu", dropout=0.0)
    shared = make_model(agent, obs_fn, 0)
    shared.share_memory()
    local = make_model(agent, obs_fn, 123)  # other weights: the update must start from the shared ones
    col = RolloutCollector(make_train_env(bank, cfg, 1, seed=0), obs_fn, local)
    torch.manual_seed(0)
    for i in range(3):
        # a fresh optimizer per update: Adam's first step is a descent direction of this rollout's loss
        # (later steps also carry the momentum of earlier rollouts)
        opt = SharedAdam(shared.parameters(), lr=1e-4)
        before = {k: v.clone() for k, v in shared.state_dict().items()}
        parts, ro = a3c_update(local, shared, opt, col, cfg)
        for k, v in local.state_dict().items():  # the rollout ran with the shared weights
            assert torch.equal(v, before[k]), k
        assert any(not torch.equal(v, before[k]) for k, v in shared.state_dict().items())
        adv, ret = gae(ro.reward, ro.value, ro.bootstrap, ro.terminated, ro.finished)
        with torch.no_grad():
            logp, ent, val = replay(shared, obs_fn, ro)
            from dataclasses import replace

            after, _ = a2c_loss(replace(ro, logp=logp, entropy=ent, value=val), adv, ret)
        assert float(after) < parts["loss"], (parts["loss"], float(after))
        assert float(opt.state[next(shared.parameters())]["step"]) == 1


def test_two_worker_run_resume_and_finish(world, tmp_path):
    run = tmp_path / "run"
    agent = agent_config("cpu")
    cfg = _cfg(world, updates=12)
    init = make_model(agent, make_observer(load_bank(cfg)[0], cfg), cfg.seed).state_dict()
    p1 = train_a3c(cfg, agent, run, progress_bar=False, poll_seconds=0.05)
    assert p1["finished"] and p1["update"] >= 12 and p1["env_steps"] == 8 * p1["update"]
    ck = latest_checkpoint(run)
    st = load_checkpoint(ck)
    assert st["progress"]["update"] == p1["update"]
    # every worker update went through the one shared optimizer
    from tsnav.checkpoint import load_tensors

    opt_t, _ = load_tensors(ck / "optimizer.safetensors")
    steps = {float(v) for k, v in opt_t.items() if k.endswith("::step")}
    assert steps == {float(p1["update"])}
    w, _ = load_tensors(ck / "model.safetensors")
    assert any(not torch.equal(w[k], init[k]) for k in init)
    log = read_log(run)
    assert log and log[-1]["update"] == p1["update"] and np.isfinite(log[-1]["loss"])
    assert sum(r["n_episodes"] for r in log) > 0

    # a finished run is not retrained; a larger budget resumes from the counters
    assert train_a3c(cfg, agent, run, progress_bar=False)["update"] == p1["update"]
    p2 = train_a3c(_cfg(world, updates=p1["update"] + 6), agent, run, progress_bar=False, poll_seconds=0.05)
    assert p2["update"] >= p1["update"] + 6 and p2["sessions"] == 2
    assert p2["env_steps"] == 8 * p2["update"]


def test_workers_share_the_target_depth_maps(world, tmp_path, monkeypatch):
    """An agent with ``target_depth`` trains under A3C: the depth maps are made once, in the parent, and handed to
    the workers in shared memory (as the features are), and a worker's observer takes them as they are."""
    import tsnav.rl.a3c as a3c
    from tsnav.agent.observe import GROUND_TRUTH, TargetDepth
    from tsnav.checkpoint import load_tensors

    handed, original = [], a3c._Workers.__init__

    def spy(self, cfg, agent, scenes, shared, optimizer, features, depth, progress, session):
        handed.append(depth)
        original(self, cfg, agent, scenes, shared, optimizer, features, depth, progress, session)

    monkeypatch.setattr(a3c._Workers, "__init__", spy)
    agent = agent_config("cpu", target_depth=GROUND_TRUTH)
    p = train_a3c(_cfg(world, updates=4), agent, tmp_path / "run", progress_bar=False, poll_seconds=0.05)
    assert p["finished"] and p["update"] >= 4
    assert len(handed) == 1 and isinstance(handed[0], TargetDepth) and handed[0].maps.is_shared()
    w, _ = load_tensors(latest_checkpoint(tmp_path / "run") / "model.safetensors")
    assert "depth_in.weight" in w
    cfg = _cfg(world)
    bank, det = load_bank(cfg)
    assert make_observer(bank, cfg, det_features=det, agent=agent, target_depth=handed[0]).target_depth is handed[0]
