"""Batched A2C trainer: GAE against a slow reference, bootstrapping on truncation only, a short run that
lowers the loss, exact resume after an interruption, no retraining of a finished run, checkpoints."""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from tsnav.agent import agent_config
from tsnav.constants import DONE
from tsnav.rl.batched import train_batched
from tsnav.rl.checkpoint import latest_checkpoint, list_checkpoints, load_checkpoint
from tsnav.rl.config import TrainConfig
from tsnav.rl.logger import read_log
from tsnav.rl.rollout import RolloutCollector, gae, gae_reference
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


def test_gae_matches_reference_loop():
    rng = np.random.default_rng(0)
    T, B = 12, 7
    reward = rng.normal(size=(T, B))
    value = rng.normal(size=(T, B))
    boot = rng.normal(size=(T, B))
    finished = rng.random((T, B)) < 0.25
    terminated = finished & (rng.random((T, B)) < 0.5)
    for tau in (1.0, 0.95):
        adv, ret = gae(*(torch.tensor(x) for x in (reward, value, boot, terminated, finished)), gamma=0.99, tau=tau)
        ra, rr = gae_reference(reward, value, boot, terminated, finished, gamma=0.99, tau=tau)
        np.testing.assert_allclose(adv.numpy(), ra, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(ret.numpy(), rr, rtol=1e-10, atol=1e-10)


def test_gae_by_hand_truncation_bootstraps_termination_does_not():
    g = 0.5
    # one row, three steps: the episode is truncated at t=1 (bootstrap 10), a new one terminates at t=2
    r = torch.tensor([[1.0], [2.0], [3.0]])
    v = torch.tensor([[0.5], [1.0], [2.0]])
    boot = torch.tensor([[1.0], [10.0], [99.0]])  # within an episode the bootstrap is the next value
    fin = torch.tensor([[False], [True], [True]])
    term = torch.tensor([[False], [False], [True]])
    adv, ret = gae(r, v, boot, term, fin, gamma=g, tau=1.0)
    assert ret[:, 0].tolist() == [1 + g * (2 + g * 10), 2 + g * 10, 3.0]
    assert adv[:, 0].tolist() == [1 + g * (2 + g * 10) - 0.5, 2 + g * 10 - 1.0, 3.0 - 2.0]


def test_collector_bootstraps_from_the_final_observation(world):
    cfg = _cfg(world, max_steps=3, num_envs=4)
    bank, _ = load_bank(cfg)
    obs_fn = make_observer(bank, cfg)
    model = make_model(agent_config("cpu", dropout=0.0), obs_fn, 0)
    with torch.no_grad():
        model.actor.bias[DONE] = -50.0  # never Done: every episode is truncated after 3 steps
    col = RolloutCollector(
        make_train_env(bank, cfg, 4, seed=1), obs_fn, model, generator=torch.Generator().manual_seed(5)
    )
    col.start()
    first = dict(col.obs)
    with torch.no_grad():
        ro = col.collect(5)
    assert ro.finished[2].all() and not ro.terminated.any() and not ro.finished[[0, 1, 3, 4]].any()
    # replay the same episodes and actions: the bootstrap is the critic's value of the final observation with
    # the episode's own recurrent state (not the value of the next episode's first frame)
    env2 = make_train_env(bank, cfg, 4, seed=99)
    obs = env2.reset(episodes=(first["scene"], first["target"], first["state"]))
    gen = torch.Generator().manual_seed(5)
    state = model.initial_state(4)
    with torch.no_grad():
        for t in range(3):
            logits, _, state = model(obs_fn(obs["state"], obs["target"]), state)
            a = torch.multinomial(torch.distributions.Categorical(logits=logits).probs, 1, generator=gen)[:, 0]
            state = state.with_action(a)
            target = obs["target"]
            obs, _, _, trunc, info = env2.step(a.numpy())
        assert trunc.all()
        v_final = model(obs_fn(info["final_state"], target), state)[1]
    torch.testing.assert_close(ro.bootstrap[2], v_final)
    assert not torch.allclose(ro.bootstrap[2], ro.value[3])
    # bootstrap within an episode is the next step's value
    torch.testing.assert_close(ro.bootstrap[:2], ro.value[1:3])

    # terminated rows: forcing Done makes every step terminal, so the return is just the reward
    model2 = make_model(agent_config("cpu", dropout=0.0), obs_fn, 0)
    with torch.no_grad():
        model2.actor.bias[DONE] = 50.0
    col3 = RolloutCollector(make_train_env(bank, cfg, 4, seed=2), obs_fn, model2)
    with torch.no_grad():
        ro3 = col3.collect(4)
    assert ro3.terminated.all() and ro3.finished.all()
    adv, ret = gae(ro3.reward, ro3.value, ro3.bootstrap, ro3.terminated, ro3.finished)
    torch.testing.assert_close(ret, ro3.reward)


def test_an_update_lowers_the_loss_of_its_rollout(world):
    from rl_helpers import replay
    from tsnav.rl.rollout import a2c_loss

    cfg = _cfg(world, num_envs=16, rollout_steps=10)
    bank, _ = load_bank(cfg)
    obs_fn = make_observer(bank, cfg)
    model = make_model(agent_config("cpu", dropout=0.0), obs_fn, 0)
    col = RolloutCollector(make_train_env(bank, cfg, 16, seed=3), obs_fn, model)
    torch.manual_seed(0)
    for _ in range(3):
        # the paper's learning rate; a fresh optimizer per update, whose first step is a descent direction of
        # this rollout's loss (later steps also carry the momentum of earlier rollouts)
        opt = torch.optim.Adam(model.parameters(), lr=1e-4, amsgrad=True)
        ro = col.collect(10)
        adv, ret = gae(ro.reward, ro.value, ro.bootstrap, ro.terminated, ro.finished)
        loss, _ = a2c_loss(ro, adv, ret)
        logp, ent, val = replay(model, obs_fn, ro)  # the replay reproduces the rollout exactly
        torch.testing.assert_close(logp, ro.logp)
        torch.testing.assert_close(val, ro.value)
        opt.zero_grad()
        loss.backward()
        opt.step()
        with torch.no_grad():
            logp, ent, val = replay(model, obs_fn, ro)
            after, _ = a2c_loss(replace(ro, logp=logp, entropy=ent, value=val), adv, ret)
        assert after < loss.item(), (loss.item(), float(after))


def test_short_run_raises_the_return(world, tmp_path):
    # 80 updates: with failed looks no longer penalised as collisions, this seed's return first rises after
    # about 60 updates (0.40 over the first 15, 1.36 over the last 15; 0.44 -> 1.35 with the old penalty)
    cfg = _cfg(world, num_envs=16, rollout_steps=10, updates=80, log_every=1, checkpoint_every=1000, lr=3e-3)
    progress = train_batched(cfg, agent_config("cpu"), tmp_path / "run", progress_bar=False)
    assert progress["update"] == 80 and progress["finished"]
    log = read_log(tmp_path / "run")
    assert [r["update"] for r in log] == list(range(1, 81))
    first = np.mean([r["return"] for r in log[:15]])
    last = np.mean([r["return"] for r in log[-15:]])
    assert last > first + 0.1, (first, last)
    assert {"SR", "SPL", "SSSPL", "NSNPL", "reward/explore", "reward/distance", "steps_per_s"} <= set(log[-1])
    # the Done collapse monitor: the policy's mean Done probability and the share of Done actions taken
    assert all(0.0 < r["done_prob"] < 1.0 and 0.0 <= r["done_rate"] <= 1.0 for r in log)
    assert abs(np.mean([r["done_prob"] for r in log]) - np.mean([r["done_rate"] for r in log])) < 0.05


class Interrupt(Exception):
    pass


def _weights(run):
    from tsnav.checkpoint import load_tensors

    ck = latest_checkpoint(run)
    return load_tensors(ck / "model.safetensors")[0], load_tensors(ck / "optimizer.safetensors")[0], ck


def test_resume_equals_uninterrupted_run(world, tmp_path):
    cfg = _cfg(world, updates=8)
    agent = agent_config("cpu")
    full = _full_and_interrupted(cfg, agent, tmp_path, at=5)
    assert latest_checkpoint(tmp_path / "b").name == "ckpt_000000003"
    resumed = train_batched(cfg, agent, tmp_path / "b", progress_bar=False)
    assert resumed["update"] == full["update"] == 8
    assert resumed["episodes"] == full["episodes"] and resumed["env_steps"] == full["env_steps"]
    wa, oa, _ = _weights(tmp_path / "a")
    wb, ob, ck = _weights(tmp_path / "b")
    assert wa.keys() == wb.keys() and oa.keys() == ob.keys()
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    for k in oa:
        assert torch.equal(oa[k], ob[k]), k
    la, lb = read_log(tmp_path / "a"), read_log(tmp_path / "b")
    assert [r["update"] for r in lb] == [r["update"] for r in la] == [2, 3, 4, 6, 8]
    for ra, rb in zip(la, lb):
        assert ra["loss"] == rb["loss"] and ra["n_episodes"] == rb["n_episodes"]

    # a finished run is not retrained
    mtime = (ck / "model.safetensors").stat().st_mtime_ns
    again = train_batched(cfg, agent, tmp_path / "b", progress_bar=False)
    assert again["update"] == 8 and (ck / "model.safetensors").stat().st_mtime_ns == mtime
    assert len(list_checkpoints(tmp_path / "b")) <= 2
    state = load_checkpoint(ck)
    assert state["progress"]["finished"] and 0 in state["rng"]
    json.dumps(state["rng"][0])


def _full_and_interrupted(cfg, agent, tmp_path, at: int) -> dict:
    """Train ``cfg`` to its end in ``tmp_path/a`` (its progress is returned), and in ``tmp_path/b`` until an
    interruption after update ``at``."""
    full = train_batched(cfg, agent, tmp_path / "a", progress_bar=False)

    def kill(progress):
        if progress["update"] == at:
            raise Interrupt()

    with pytest.raises(Interrupt):
        train_batched(cfg, agent, tmp_path / "b", progress_bar=False, on_update=kill)
    return full


def test_truncated_newest_checkpoint_resumes_from_the_previous_one(world, tmp_path, capsys):
    """Issue 16 section 5: a broken newest checkpoint is named in one line, set aside, and the run resumes
    from the checkpoint before it, ending exactly like an uninterrupted run."""
    cfg = _cfg(world, updates=8)
    agent = agent_config("cpu")
    _full_and_interrupted(cfg, agent, tmp_path, at=7)
    newest = latest_checkpoint(tmp_path / "b")
    assert newest.name == "ckpt_000000006"
    broken = newest / "model.safetensors"
    broken.write_bytes(broken.read_bytes()[:100])  # a copy cut short
    capsys.readouterr()
    resumed = train_batched(cfg, agent, tmp_path / "b", progress_bar=False)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(broken) in err[0] and "resuming from ckpt_000000003" in err[0], err
    assert (newest.parent / "ckpt_000000006.broken" / "model.safetensors").exists()  # kept, not listed
    assert resumed["update"] == 8
    wa, oa, _ = _weights(tmp_path / "a")
    wb, ob, _ = _weights(tmp_path / "b")
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    for k in oa:
        assert torch.equal(oa[k], ob[k]), k


def test_checkpoint_retention_and_milestones(tmp_path):
    from tsnav.rl.checkpoint import save_checkpoint
    from tsnav.rl.batched import new_progress
    from tsnav.agent import ActorCritic

    model = ActorCritic(agent_config("cpu"), (3, 2, 2), 3)
    for u in range(1, 8):
        save_checkpoint(tmp_path, {**new_progress(), "update": u}, model, milestone_every=3)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["ckpt_000000003", "ckpt_000000006", "ckpt_000000007"]
    for u in range(8, 10):
        save_checkpoint(tmp_path, {**new_progress(), "update": u}, model)
    assert [p.name for p in list_checkpoints(tmp_path)][-2:] == ["ckpt_000000008", "ckpt_000000009"]
    with pytest.raises(ValueError, match="milestone_every"):
        TrainConfig(milestone_every=0)


def test_checkpoint_written_before_the_one_layout_still_loads(tmp_path):
    """Agent checkpoints written before the layouts were unified name the optimizer file optim.safetensors; it
    is still read (new ones write optimizer.safetensors)."""
    from tsnav.rl.checkpoint import save_checkpoint
    from tsnav.rl.batched import new_progress
    from tsnav.agent import ActorCritic

    torch.manual_seed(0)
    model = ActorCritic(agent_config("cpu"), (3, 2, 2), 3)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    sum(p.sum() for p in model.parameters()).backward()
    opt.step()
    ck = save_checkpoint(tmp_path, {**new_progress(), "update": 1}, model, opt)
    assert sorted(p.name for p in ck.iterdir()) == ["model.safetensors", "optimizer.safetensors", "state.json"]
    (ck / "optimizer.safetensors").rename(ck / "optim.safetensors")
    fresh = ActorCritic(agent_config("cpu"), (3, 2, 2), 3)
    fresh_opt = torch.optim.Adam(fresh.parameters(), lr=1e-3)
    load_checkpoint(ck, fresh, fresh_opt)
    for (k, a), b in zip(model.state_dict().items(), fresh.state_dict().values()):
        assert torch.equal(a, b), k
    sa, sb = opt.state_dict()["state"], fresh_opt.state_dict()["state"]
    assert sa.keys() == sb.keys() and len(sa) > 0
    for i in sa:
        for k in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(sa[i][k], sb[i][k]), (i, k)


def test_bf16_rollout_agrees_with_its_float32_replay(world):
    """The bf16 fast path (autocast forward passes) against float32: the same rollout replayed in float32 gives
    log-probabilities and values within bfloat16's precision, and the loss gradient points the same way."""
    from rl_helpers import replay
    from tsnav.rl.rollout import a2c_loss

    cfg = _cfg(world, num_envs=16, rollout_steps=10)
    bank, _ = load_bank(cfg)
    obs_fn = make_observer(bank, cfg)
    model = make_model(agent_config("paper", dropout=0.0), obs_fn, 0)
    with pytest.raises(ValueError, match="unknown precision 'fp16'"):
        RolloutCollector(make_train_env(bank, cfg, 16, seed=3), obs_fn, model, precision="fp16")
    col = RolloutCollector(make_train_env(bank, cfg, 16, seed=3), obs_fn, model, precision="bf16")
    torch.manual_seed(0)
    ro = col.collect(10)
    assert ro.logp.dtype == ro.value.dtype == torch.float32
    assert col.state.h.dtype == col.state.c.dtype == torch.float32
    logp, ent, val = replay(model, obs_fn, ro)
    assert not torch.equal(logp, ro.logp)  # bf16 arithmetic really ran
    torch.testing.assert_close(ro.logp, logp, atol=0.02, rtol=0.02)
    torch.testing.assert_close(ro.value, val, atol=0.02, rtol=0.05)

    def grad(logp, ent, value):
        adv, ret = gae(ro.reward, value, ro.bootstrap, ro.terminated, ro.finished)
        fake = type(ro)(
            logp=logp,
            entropy=ent,
            value=value,
            reward=ro.reward,
            bootstrap=ro.bootstrap,
            terminated=ro.terminated,
            finished=ro.finished,
        )
        model.zero_grad()
        a2c_loss(fake, adv, ret)[0].backward(retain_graph=True)
        return torch.cat([p.grad.flatten() for p in model.parameters() if p.grad is not None])

    g16, g32 = grad(ro.logp, ro.entropy, ro.value), grad(logp, ent, val)
    assert torch.nn.functional.cosine_similarity(g16, g32, dim=0) > 0.98
    assert (g16.norm() / g32.norm() - 1).abs() < 0.05


@pytest.mark.parametrize("seeded", [False, True])
def test_policy_is_torch_categorical_bit_for_bit(seeded):
    """The collector's :class:`Policy` against ``torch.distributions.Categorical``: the same actions from the same
    random state, the same log-probabilities, entropies and Done probabilities, and the same gradient of a loss
    that mixes them, bit for bit."""
    from tsnav.rl.rollout import Policy

    base = torch.randn(64, 6, dtype=torch.float64).float() * 3
    base[0] = torch.tensor([30.0, -30.0, 0.0, 0.0, 1e-3, -1e-3])  # near-one-hot row

    def run(make):
        logits = base.clone().requires_grad_()
        scaled = logits * 1.5  # not a leaf, as the network's output
        gen = torch.Generator().manual_seed(7) if seeded else None
        torch.manual_seed(3)
        pol = make(scaled)
        if isinstance(pol, Policy):
            action = pol.sample(gen)
        else:
            action = pol.sample() if gen is None else torch.multinomial(pol.probs.detach(), 1, generator=gen)[:, 0]
        done = pol.probs.detach()[:, DONE]
        logp, ent = pol.log_prob(action), pol.entropy()
        ((logp * torch.linspace(-1, 1, 64)).sum() - 0.01 * ent.sum()).backward()
        return action, logp, ent, done, logits.grad

    fast, slow = run(Policy), run(lambda lg: torch.distributions.Categorical(logits=lg))
    assert len(set(fast[0].tolist())) > 1
    for a, b in zip(fast, slow):
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b)
    with pytest.raises(RuntimeError):  # invalid logits still fail loudly
        Policy(torch.full((2, 6), float("nan"))).sample()


@pytest.mark.parametrize("preset", ["paper", "cpu"])
def test_bf16_cast_once_is_autocasts_per_step_cast_bit_for_bit(world, preset):
    """The fast path (the weights cast to bfloat16 once per rollout) against its reference (autocast's cast at
    every step): the same actions, log-probabilities, values and, after the backward of the loss, the same
    gradient of every parameter, bit for bit, with dropout on and with the truncated episodes' bootstrap passes."""
    from tsnav.rl.rollout import a2c_loss

    cfg = _cfg(world, num_envs=12, max_steps=7)
    bank, _ = load_bank(cfg)
    obs_fn = make_observer(bank, cfg)
    model = make_model(agent_config(preset), obs_fn, 0)
    model.train()
    names = model.autocast_weights()
    assert "lstm.weight_hh" in names and "image.weight" in names
    assert not {"action_embed.weight", "memory.query.weight", "memory.nothing", "memory.attn.in_proj_bias"} & set(names)

    def run(cast_once):
        col = RolloutCollector(
            make_train_env(bank, cfg, 12, seed=5), obs_fn, model, precision="bf16", cast_once=cast_once
        )
        torch.manual_seed(1)
        out = []
        for _ in range(2):  # the second rollout starts from the first one's recurrent state
            ro = col.collect(9)
            assert col.low is None
            adv, ret = gae(ro.reward, ro.value, ro.bootstrap, ro.terminated, ro.finished)
            model.zero_grad(set_to_none=True)
            a2c_loss(ro, adv, ret)[0].backward()
            out.append((ro, {k: p.grad.clone() for k, p in model.named_parameters() if p.grad is not None}))
        return out

    fast, slow = run(True), run(False)
    assert sum(int(ro.finished.sum()) for ro, _ in fast) > 0  # episodes ended (truncations bootstrap)
    for (ra, ga), (rb, gb) in zip(fast, slow):
        assert np.array_equal(ra.actions, rb.actions)
        for k in ("logp", "entropy", "value", "bootstrap"):
            assert torch.equal(getattr(ra, k), getattr(rb, k)), k
        assert ga.keys() == gb.keys() and len(ga) == len(list(model.parameters()))
        for k in ga:
            assert torch.equal(ga[k], gb[k]), k


def test_bf16_run_resumes_exactly(world, tmp_path):
    cfg = _cfg(world, updates=6, precision="bf16")
    agent = agent_config("cpu")
    _full_and_interrupted(cfg, agent, tmp_path, at=4)
    train_batched(cfg, agent, tmp_path / "b", progress_bar=False)
    wa, wb = _weights(tmp_path / "a")[0], _weights(tmp_path / "b")[0]
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    train_batched(replace(cfg, precision="fp32"), agent, tmp_path / "c", progress_bar=False)
    wc = _weights(tmp_path / "c")[0]
    assert any(not torch.equal(wa[k], wc[k]) for k in wc)  # the precision changes the arithmetic
    with pytest.raises(ValueError, match="unknown precision"):
        _cfg(world, precision="half")


def test_distance_increase_scale_reaches_the_reward_and_the_run(world, tmp_path, capsys):
    """The deviation ``distance_increase_scale`` (off at 1.0): the trainer's reward uses it, config.json records
    it, a resume with another value is refused, and ``tsnav train`` keeps the run's own value on resume."""
    from tsnav.cli import main
    from tsnav.rl.assemble import make_reward
    from tsnav.rl.train import train_run

    cfg = _cfg(world, updates=2, distance_increase_scale=2.0)
    bank, _ = load_bank(cfg)
    assert make_reward(bank, cfg).config.distance_increase_scale == 2.0
    assert (
        make_reward(bank, replace(cfg, distance_increase_scale=1.0)).config
        == make_reward(bank, TrainConfig(data=cfg.data)).config
    )  # the paper's reward by default
    with pytest.raises(ValueError, match="distance_increase_scale"):
        _cfg(world, distance_increase_scale=-0.5)
    out = tmp_path / "run"
    assert train_run(cfg, agent_config("cpu"), out, progress_bar=False)["update"] == 2
    saved = json.loads((out / "config.json").read_text())
    assert saved["train"]["distance_increase_scale"] == 2.0 and saved["reward"]["distance_increase_scale"] == 2.0
    with pytest.raises(ValueError, match="distance_increase_scale"):
        train_run(replace(cfg, distance_increase_scale=1.0, updates=3), agent_config("cpu"), out, progress_bar=False)
    assert main(["train", "--out", str(out), "--updates", "3", "--quiet"]) == 0
    assert "after 3 updates" in capsys.readouterr().out
    assert json.loads((out / "config.json").read_text())["train"]["distance_increase_scale"] == 2.0


def test_lr_schedule_by_hand_and_its_checks(world):
    """TrainConfig.lr_schedule (issue 47, off by default): the rate of each update by hand, the horizon (the updates
    budget unless named) in the run's identity, and one-line refusals."""
    import math

    const = _cfg(world, updates=10)
    assert [const.lr_at(u) for u in (0, 5, 50)] == [1e-3] * 3 and const.lr_horizon is None
    lin = _cfg(world, updates=10, lr_schedule="linear", lr_final=1e-4)
    assert lin.lr_horizon == 10 and lin.identity()["lr_decay_updates"] == 10
    assert lin.lr_at(0) == 1e-3 and lin.lr_at(10) == lin.lr_at(25) == 1e-4
    assert lin.lr_at(5) == pytest.approx(5.5e-4, rel=1e-12)
    cos = _cfg(world, updates=10, lr_schedule="cosine", lr_final=1e-4, lr_decay_updates=20)
    assert cos.lr_horizon == 20 and cos.lr_at(0) == 1e-3 and cos.lr_at(20) == 1e-4
    assert cos.lr_at(5) == pytest.approx(1e-4 + 0.9e-3 * 0.5 * (1 + math.cos(math.pi / 4)), rel=1e-12)
    assert const.identity().get("lr_decay_updates") is None  # a constant rate keeps the identity it had
    for kw, msg in (
        (dict(lr_schedule="step"), "unknown lr_schedule"),
        (dict(lr_final=1e-4), "not constant"),
        (dict(lr_decay_updates=5), "not constant"),
        (dict(lr_schedule="linear", updates=None, episodes=100), "needs a horizon"),
        (dict(lr_schedule="linear", lr_final=1e-2), "lr_final must be in"),
    ):
        with pytest.raises(ValueError, match=msg):
            _cfg(world, **{"updates": 10, **kw})


def test_levers_train_and_resume_exactly(world, tmp_path, capsys):
    """The three levers of issue 47 together (memory_history, the tsrm-regret reward, a linear lr schedule) train,
    are recorded in config.json, and a run interrupted and resumed equals the uninterrupted one bit for bit (the
    scheduled rate follows the update counter); the log's ``lr`` column is the schedule; resuming a scheduled run
    with another ``updates`` budget is refused in one line unless the horizon is named."""
    from tsnav.cli import main
    from tsnav.rl.train import train_run

    cfg = _cfg(world, updates=6, lr_schedule="linear", lr_final=1e-4, reward="tsrm-regret")
    agent = agent_config("cpu", memory_history=True)
    train_run(cfg, agent, tmp_path / "a", progress_bar=False)

    def kill(progress):
        if progress["update"] == 4:
            raise Interrupt()

    with pytest.raises(Interrupt):
        train_batched(cfg, agent, tmp_path / "b", progress_bar=False, on_update=kill)
    train_batched(cfg, agent, tmp_path / "b", progress_bar=False)
    (wa, oa, _), (wb, ob, _) = _weights(tmp_path / "a"), _weights(tmp_path / "b")
    assert "memory.history.weight" in wa and wa.keys() == wb.keys()
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    for k in oa:
        assert torch.equal(oa[k], ob[k]), k
    la, lb = read_log(tmp_path / "a"), read_log(tmp_path / "b")
    assert [(r["update"], r["lr"], r["loss"]) for r in la] == [(r["update"], r["lr"], r["loss"]) for r in lb]
    want = {
        2: (cfg.lr_at(0) + cfg.lr_at(1)) / 2,
        3: cfg.lr_at(2),
        4: cfg.lr_at(3),
        6: (cfg.lr_at(4) + cfg.lr_at(5)) / 2,
    }
    assert {r["update"]: r["lr"] for r in la} == pytest.approx(want, rel=1e-12)
    assert all("reward/regret" in r for r in la if r.get("n_episodes"))
    saved = json.loads((tmp_path / "a" / "config.json").read_text())
    assert saved["agent"]["memory_history"] and saved["reward"]["variant"] == "tsrm-regret"
    assert (saved["train"]["lr_schedule"], saved["train"]["lr_final"]) == ("linear", 1e-4)
    # a constant run logs no lr column (its log is as before)
    train_run(_cfg(world, updates=2), agent_config("cpu"), tmp_path / "c", progress_bar=False)
    assert not any("lr" in r for r in read_log(tmp_path / "c"))
    # another budget would stretch the schedule: refused, unless the horizon it started with is named
    capsys.readouterr()
    assert main(["train", "--out", str(tmp_path / "a"), "--updates", "8", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert (
        len(err.splitlines()) == 1 and "(lr_decay_updates): 6 saved, 8 given" in err and "--lr-decay-updates 6" in err
    )
    args = ["train", "--out", str(tmp_path / "a"), "--updates", "8", "--lr-decay-updates", "6", "--quiet"]
    assert main(args) == 0 and "after 8 updates" in capsys.readouterr().out
    assert read_log(tmp_path / "a")[-1]["lr"] == pytest.approx(1e-4, rel=1e-12)
