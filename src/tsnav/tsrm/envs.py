"""The Gymnasium env ``tsnav/ObjectNav-v1`` with the paper's reward (the factories its ids, ``v1`` and the first
release's ``v0``, are registered to; :mod:`tsnav.sim.gym_env` holds the version history).

    import gymnasium as gym
    env = gym.make("tsnav.sim:tsnav/ObjectNav-v1", data="out/world", split="train", reward="tsrm",
                   detections="oracle")
    envs = gym.make_vec("tsnav.sim:tsnav/ObjectNav-v1", num_envs=64, vectorization_mode="vector_entry_point",
                        data="out/world", reward="tsrm", detections="oracle")

(``"tsnav.sim:"`` makes Gymnasium import :mod:`tsnav.sim`, which registers the id.) The spaces, dynamics and
start states are those of :mod:`tsnav.sim.gym_env`; this module chooses the reward and the stage switch:

=================  ==========================================================================================
argument           meaning
=================  ==========================================================================================
``reward``         ``"tsrm"`` (default: exploration + distance terms, paper III-B), ``"explore"``,
                   ``"distance"``, ``"baseline"`` (collision, slack, success: Table II), or ``"sparse"``
                   (-0.01 per step, +5 on success, no collision penalty); or a ``RewardConfig``
``detections``     name of the detection tables ``detections_<name>.hdf5`` to install (``tsnav detect``;
                   ``"learned"`` or ``"oracle"``): their scores drive the stage switch and fill the
                   ``detections`` observation. Required with ``data`` / ``scenes`` (a one-line ``ValueError``
                   otherwise: no silent fallback to ground-truth visibility, issue 14); a given ``bank`` keeps
                   what its caller installed; the analytic toy room (no world) has no detector
``c_target``       stage-switch threshold C_target of the bank the env builds (default 0.7, paper IV-A); a
                   given ``bank`` carries its own (``SceneBank(c_target=)``), so not both
``protocol``       success protocol (:mod:`tsnav.protocol`): ``"paper"`` (default; in view within 1.0 m) or
                   ``"lineage"`` (the 1.5 m visibility map); a given ``bank`` keeps its own
=================  ==========================================================================================

``info`` holds every reward term of the step as ``reward/<term>`` (``explore``, ``distance``, ``collision``,
``slack``, ``success`` and any registered term; zeros for terms the variant switches off); the stage itself is the wrapped
``BatchEnv``'s (``env.unwrapped.batch.stage``). The rewards are those of the batched trainer (:mod:`tsnav.rl`)
for the same episodes and actions: the same :class:`~tsnav.tsrm.reward.TSRMReward` over the same bank, handed
the stage by the env's one stage switch (:attr:`~tsnav.sim.batch.BatchEnv.stage`).
"""

from __future__ import annotations

from ..constants import C_TARGET, SUCCESS_DISTANCE
from ..sim.batch import RewardFn, SceneBank
from ..sim.gym_env import ObjectNavEnv, ObjectNavVectorEnv, make_bank
from .reward import VARIANTS, RewardConfig, TSRMReward

#: Reward names the env accepts: the variants of :mod:`tsnav.tsrm.terms` (the paper's four and the sparse reward,
#: plus any registered), a live view.
REWARDS = VARIANTS


def _bank_and_reward(
    reward: str | RewardConfig,
    detections: str | None,
    c_target: float | None,
    bank: SceneBank | None,
    scenes,
    data,
    split,
    success_distance: float,
    protocol: str | None = None,
) -> tuple[SceneBank, RewardFn]:
    if not isinstance(reward, RewardConfig) and reward not in REWARDS:
        raise ValueError(f"unknown reward {reward!r} (choose from {', '.join(REWARDS)})")
    if bank is not None and c_target is not None:
        raise ValueError("a given bank carries its own c_target (SceneBank(c_target=...)); pass one or the other")
    if bank is not None and protocol is not None and bank.protocol != protocol:
        raise ValueError(f"protocol {protocol!r} differs from the given bank's {bank.protocol!r}")
    if detections is None and (data is not None or scenes is not None) and bank is None:
        raise ValueError(
            "name the detection table the env reads: detections='learned' or detections='oracle' "
            "(`tsnav detect`); there is no fallback to ground truth"
        )
    bank = make_bank(
        bank,
        scenes,
        data,
        split,
        success_distance,
        c_target=C_TARGET if c_target is None else c_target,
        protocol=protocol or "paper",
    )
    if detections is not None:
        bank.install_detections(detections)
    config = reward if isinstance(reward, RewardConfig) else RewardConfig(variant=reward)
    return bank, TSRMReward(bank, config)


def make_objectnav(
    reward: str | RewardConfig = "tsrm",
    detections: str | None = None,
    c_target: float | None = None,
    data: str | None = None,
    split: str | None = "train",
    scenes=None,
    bank: SceneBank | None = None,
    success_distance: float = SUCCESS_DISTANCE,
    protocol: str | None = None,
    **kwargs,
) -> ObjectNavEnv:
    """One episode at a time with ``reward`` (see the module docstring); other arguments as
    :class:`~tsnav.sim.gym_env.ObjectNavEnv`."""
    bank, reward_fn = _bank_and_reward(
        reward, detections, c_target, bank, scenes, data, split, success_distance, protocol
    )
    return ObjectNavEnv(bank=bank, reward_fn=reward_fn, **kwargs)


def make_objectnav_vector(
    num_envs: int = 1,
    reward: str | RewardConfig = "tsrm",
    detections: str | None = None,
    c_target: float | None = None,
    data: str | None = None,
    split: str | None = "train",
    scenes=None,
    bank: SceneBank | None = None,
    success_distance: float = SUCCESS_DISTANCE,
    protocol: str | None = None,
    **kwargs,
) -> ObjectNavVectorEnv:
    """``num_envs`` episodes stepped together with ``reward``; other arguments as
    :class:`~tsnav.sim.gym_env.ObjectNavVectorEnv`."""
    bank, reward_fn = _bank_and_reward(
        reward, detections, c_target, bank, scenes, data, split, success_distance, protocol
    )
    return ObjectNavVectorEnv(num_envs, bank=bank, reward_fn=reward_fn, **kwargs)
