"""The mirror-symmetric policy (AgentConfig.mirror_policy, a deviation): its logits in an observation's mirror image are
its logits with the two turns traded, step after step; an agent trained with it walks a room's mirror image as the
mirror of its walk in the room, state for state; and a missing cache of the flipped frames gets one line."""

from __future__ import annotations

import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch

from tsnav.agent import agent_config
from tsnav.agent.model import MIRROR_ACTIONS, ActorCritic
from tsnav.agent.observe import AgentObs
from tsnav.cli import main
from tsnav.data.reader import MIRROR_ACTIONS as READER_MIRROR_ACTIONS
from tsnav.data.reader import MIRROR_SUFFIX, list_scenes, load_scene
from tsnav.eval.runner import record_trajectories
from tsnav.pretrain.pixels import cache_pixel_features
from tsnav.rl.checkpoint import load_policy
from tsnav.rl.config import TrainConfig
from tsnav.rl.train import train_run
from tsnav.sim.batch import SceneBank
from tsnav.sim.episodes import make_episodes

from conftest import PIXEL_FEATURES

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _obs(g: torch.Generator, b: int) -> AgentObs:
    box = torch.rand(b, 4, generator=g)
    return AgentObs(
        image=torch.rand(b, 3, 4, 4, generator=g),
        target=torch.randint(0, 22, (b,), generator=g),
        det_score=torch.rand(b, generator=g),
        det_box=torch.cat([box[:, :2] * 0.5, 0.5 + box[:, 2:] * 0.5], dim=1),
        det_feat=torch.rand(b, 3, generator=g),
        pose=torch.cat(
            [torch.rand(b, 2, generator=g), torch.randint(0, 8, (b, 1), generator=g) * 45.0, torch.zeros(b, 1)], dim=1
        ),
    )


def test_the_permutation_is_the_readers():
    assert list(MIRROR_ACTIONS) == READER_MIRROR_ACTIONS.tolist()


def test_logits_in_the_mirror_are_the_logits_with_the_turns_traded():
    torch.manual_seed(0)
    net = ActorCritic(agent_config("cpu", mirror_policy=True, blocked_action=True), (3, 4, 4), 3).eval()
    g = torch.Generator().manual_seed(1)
    b = 5
    sa, sb = net.initial_state(b), net.initial_state(b)
    perm = torch.as_tensor(MIRROR_ACTIONS)
    with torch.no_grad():
        for _ in range(7):
            o, m = _obs(g, b), _obs(g, b)
            o.mirror, m.mirror = m, o  # the same steps seen from the other side
            la, va, sa = net(o, sa)
            lb, vb, sb = net(m, sb)
            assert torch.equal(la[:, perm], lb) and torch.equal(va, vb)
            act = la.argmax(dim=1)
            sa, sb = sa.with_action(act), sb.with_action(perm[act])
    # without a mirror image the symmetric network refuses in one line
    with pytest.raises(ValueError, match="mirror_policy"):
        net(_obs(g, b), net.initial_state(b))
    plain = ActorCritic(agent_config("cpu", blocked_action=True), (3, 4, 4), 3)
    assert plain.initial_state(2).mirror is None
    assert sum(p.numel() for p in plain.parameters()) == sum(p.numel() for p in net.parameters())


@pytest.fixture(scope="module")
def world(pixel_world, tmp_path_factory):
    root = tmp_path_factory.mktemp("mirror_policy") / "world"
    shutil.copytree(pixel_world, root)
    return root


def test_a_trained_agent_walks_the_mirror_as_the_mirror_of_its_walk(world, tmp_path):
    cfg = TrainConfig(
        data=str(world),
        features=PIXEL_FEATURES,
        algo="batched",
        num_envs=8,
        rollout_steps=6,
        updates=4,
        checkpoint_every=4,
        log_every=1,
        lr=3e-3,
        device="cpu",
        detections="oracle",
    )
    agent = agent_config("cpu", mirror_policy=True, blocked_action=True)
    run = tmp_path / "run"
    if not any(world.glob("*/detections_oracle-mirror.hdf5")):
        with pytest.raises(FileNotFoundError, match="detect --mirror --name oracle"):
            train_run(cfg, agent, run, progress_bar=False)
    assert main(["detect", "--data", str(world), "--detector", "oracle", "--mirror", "--no-eval", "--quiet"]) == 0
    if not any(world.glob(f"*/features_{PIXEL_FEATURES}-mirror.hdf5")):
        with pytest.raises(FileNotFoundError, match=f"features --mirror --name {PIXEL_FEATURES}"):
            train_run(cfg, agent, run, progress_bar=False)
    cache_pixel_features(world, PIXEL_FEATURES, grid=4, mirror=True)
    assert train_run(cfg, agent, run, progress_bar=False)["update"] == 4
    with pytest.raises(ValueError, match="batched"):
        train_run(replace(cfg, algo="a3c", workers=1), agent, tmp_path / "a3c", progress_bar=False)

    scenes = [load_scene(p) for p in list_scenes(world, "test")]
    bank = SceneBank(scenes)
    mirrored = SceneBank([s.mirrored() for s in scenes])
    episodes = make_episodes(bank, per_room_type=4, seed=0)
    mirror_eps = [replace(e, scene=e.scene + MIRROR_SUFFIX) for e in episodes]
    recs, traj = record_trajectories(bank, episodes, load_policy(run, bank, checkpoint="latest"))
    mrecs, mtraj = record_trajectories(mirrored, mirror_eps, load_policy(run, mirrored, checkpoint="latest"))
    turns = 0
    for r, t, mr, mt in zip(recs, traj, mrecs, mtraj):
        assert mt.keys == t.keys  # the mirror image has the room's state ids and keys
        assert mt.actions == [MIRROR_ACTIONS[a] for a in t.actions]
        assert (mr.success, mr.path_length) == (r.success, r.path_length)
        turns += sum(a in (1, 2) for a in t.actions)
    assert turns > 0  # the walks turn, so the test sees the two turns traded
    assert np.mean([len(t.actions) for t in traj]) > 1
    # a measured lever, not a shippable agent: release pack refuses it in one line
    from tsnav.errors import CommandError
    from tsnav.pipeline.release import pack

    with pytest.raises(CommandError, match="mirror-symmetric"):
        pack(run, run, run, tmp_path / "packed", {})
    assert not (tmp_path / "packed").exists()
