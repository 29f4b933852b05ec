"""Build what a trainer needs from a :class:`~tsnav.rl.config.TrainConfig`: the scene bank (with detections
when configured), the observer over the cached features, the reward and the training env."""

from __future__ import annotations

import numpy as np
import torch

from ..agent.model import ActorCritic, AgentConfig
from ..agent.observe import NO_DETECTIONS, DetectionTable, Observer, TargetDepth, load_bank_features
from ..data.reader import list_scenes, load_scene
from ..sim.batch import BatchEnv, SceneBank, SimConfig
from ..sim.episodes import make_env
from ..tsrm.reward import TSRMReward
from .config import TrainConfig


def load_bank(cfg: TrainConfig, scenes=None) -> tuple[SceneBank, np.ndarray | None]:
    """The training bank (scenes of ``cfg.split`` under ``cfg.data``, or ``scenes``; with ``cfg.mirror`` each
    followed by its mirror image, after all of them), with the detection tables ``cfg.detections`` installed;
    returns ``(bank, detection features or None)``."""
    if scenes is None:
        paths = list_scenes(cfg.data, cfg.split)
        if not paths:
            raise ValueError(f"{cfg.data}: no complete scenes" + (f" in split {cfg.split!r}" if cfg.split else ""))
        scenes = [load_scene(p) for p in paths]
    scenes = list(scenes)
    if cfg.mirror:
        scenes = scenes + [s.mirrored() for s in scenes]
    bank = SceneBank(scenes, success_distance=cfg.success_distance, c_target=cfg.c_target, protocol=cfg.protocol)
    return bank, install(bank, cfg.detections)


def install(bank: SceneBank, detections: str | None) -> np.ndarray | None:
    """Install the detection tables named ``detections`` into ``bank``; returns their per-class features
    ``(S, 22, F)``. ``ValueError`` (:data:`~tsnav.agent.observe.NO_DETECTIONS`) when ``detections`` is None:
    the agent never falls back to ground truth."""
    if detections is None:
        raise ValueError(NO_DETECTIONS)
    return bank.install_detections(detections).features


def make_observer(
    bank: SceneBank,
    cfg: TrainConfig,
    features: torch.Tensor | None = None,
    det_features: np.ndarray | None = None,
    device="cpu",
    agent: AgentConfig | None = None,
    target_depth: TargetDepth | None = None,
) -> Observer:
    """Observer over the feature caches ``cfg.features`` of the bank's scenes (or the given tensor); with
    ``agent.target_depth``, the depth maps it names (or the given :class:`TargetDepth`, made once for A3C's
    workers)."""
    if features is None:
        features = load_bank_features(bank, cfg.features)
    depth = target_depth
    if depth is None and agent is not None and agent.target_depth:
        depth = TargetDepth.of(agent.target_depth, bank, features, cfg.features)
    mirror = None
    if agent is not None and agent.mirror_policy:
        mirror = mirror_observer(bank, cfg.features, cfg.detections, device, agent.target_depth)
    return Observer(
        bank, features, DetectionTable(bank, det_features), device=device, target_depth=depth, mirror=mirror
    )


def mirror_observer(
    bank: SceneBank, features: str, detections: str | None, device="cpu", target_depth: str | None = None
) -> Observer:
    """The observer of the mirror images of the bank's scenes, in the bank's state ids, for a mirror-symmetric agent
    (``AgentConfig.mirror_policy``): the caches of the flipped frames, ``features_<features>-mirror.hdf5`` and
    ``detections_<detections>-mirror.hdf5`` (``tsnav features --mirror``, ``tsnav detect --mirror``; a missing one
    is a ``FileNotFoundError`` naming the command), and, with ``target_depth``, its depth maps of them."""
    scenes = [s.mirrored() for s in bank.scenes]
    mb = SceneBank(scenes, success_distance=bank.success_distance, c_target=bank.c_target, protocol=bank.protocol)
    det = install(mb, detections)
    feats = load_bank_features(mb, features)
    depth = TargetDepth.of(target_depth, mb, feats, features) if target_depth else None
    return Observer(mb, feats, DetectionTable(mb, det), device=device, target_depth=depth)


def make_reward(bank: SceneBank, cfg: TrainConfig) -> TSRMReward:
    """The reward variant ``cfg.reward`` with the paper's constants (its stage comes from the env's switch,
    at the bank's C_target: ``cfg.c_target``, :func:`load_bank`)."""
    return TSRMReward(bank, cfg.reward_config())


def make_train_env(bank: SceneBank, cfg: TrainConfig, num_envs: int, seed: int) -> BatchEnv:
    """Auto-resetting training env of ``num_envs`` episodes, truncated at ``cfg.max_steps``."""
    sim = SimConfig(
        success_distance=cfg.success_distance, max_steps=cfg.max_steps, autoreset=True, protocol=cfg.protocol
    )
    return make_env(bank, num_envs, sim, reward_fn=make_reward(bank, cfg), seed=seed)


def make_model(agent: AgentConfig, observer: Observer, seed: int) -> ActorCritic:
    """The actor-critic for the observer's feature shape, initialised from ``seed`` (the same on every rank)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return ActorCritic(agent, observer.feature_shape, observer.det_dim, observer.class_set)
