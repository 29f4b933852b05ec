"""A training run's recipe: the settings of :class:`~tsnav.rl.config.TrainConfig` (``[train]``), of the reward
(``[reward]``: the paper's constants, :class:`~tsnav.tsrm.reward.RewardConfig`) and of the network
(``[agent]``: :class:`~tsnav.agent.model.AgentConfig` fields over the ``train.preset`` preset), as command-line
options (:func:`add_run_options`) and as recipe sections (:func:`resolve_run`, :func:`run_recipe`), from one
source each: the fields and their docstrings (:mod:`tsnav.settings`).

Precedence, lowest first: the fields' defaults (or, when resuming, the run's saved configuration), the recipe
file (``--config``), ``--set SECTION.KEY=VALUE``, the options given on the command line.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from ..agent.model import AgentConfig, agent_config
from ..errors import CommandError
from ..settings import (
    add_options,
    add_shared,
    apply_sets,
    build,
    first_difference,
    given,
    merge,
    read_recipe,
    to_recipe,
)
from ..tsrm.reward import RewardConfig
from .config import BUDGET_FIELDS, REWARD_OWN, TrainConfig, reward_settings_of

#: The sections of a run's recipe.
SECTIONS = ("train", "reward", "agent")
#: The keys of a shipped agent's recipe (configs/agents/*.toml) that other steps read (``tsnav release make``):
#: ``tsnav train`` and ``tsnav convergence`` take such a recipe and read their own sections of it.
AGENT_RECIPE_KEYS = ("name", "world", "detections", "pretrain", "features", "scoring", "convergence", "select", "card")
#: TrainConfig fields that are no setting of the recipe's ``[train]`` (the ``[reward]`` section sets them).
TRAIN_HIDDEN = ("reward_settings",)


def add_run_options(parser: argparse.ArgumentParser, *, exclude_train=(), defaults: TrainConfig | None = None) -> None:
    """The options of a run's settings, one per field: ``[train]`` (less ``exclude_train``; ``defaults``: the
    defaults shown), ``[reward]`` and ``[agent]``, in three groups."""
    add_options(
        parser.add_argument_group("training (TrainConfig; recipe section [train])"),
        TrainConfig,
        "train",
        exclude=(*TRAIN_HIDDEN, *exclude_train),
        defaults=defaults,
    )
    add_options(
        parser.add_argument_group("reward: the paper's constants (RewardConfig; recipe section [reward])"),
        RewardConfig,
        "reward",
        exclude=REWARD_OWN,
    )
    add_options(
        parser.add_argument_group(
            "agent network over the preset (AgentConfig; recipe section [agent]; default: the preset's)"
        ),
        AgentConfig,
        "agent",
        defaults=agent_config("cpu") if defaults is not None and defaults.preset == "cpu" else None,
    )


def add_recipe_options(parser: argparse.ArgumentParser) -> None:
    """``--config RECIPE.toml`` and ``--set SECTION.KEY=VALUE``."""
    add_shared(parser, "config")
    add_shared(parser, "set")


def recipe_from_args(args: argparse.Namespace, sections=SECTIONS) -> dict:
    """The recipe the command line names: the ``--config`` file, then ``--set``, then the options given."""
    base = read_recipe(args.config) if getattr(args, "config", None) else {}
    if "train" in base and set(base) - set(sections) <= set(AGENT_RECIPE_KEYS):
        # an agent's recipe (configs/agents/): the run's sections are taken, the other steps' left to release make
        skipped = sorted(set(base) - set(sections))
        if skipped:
            print(
                f"{args.config}: an agent's recipe; this command reads its {', '.join(sections)} sections "
                f"(the others, {', '.join(skipped)}, are tsnav release make's)",
                file=sys.stderr,
            )
        base = {k: v for k, v in base.items() if k in sections}
    unknown = sorted(set(base) - set(sections))
    if unknown:
        raise CommandError(
            f"{args.config}: no section {', '.join(unknown)} in a run's recipe (sections: {', '.join(sections)})"
        )
    recipe = apply_sets(base, getattr(args, "set", None) or [], tuple(sections))
    return merge(recipe, {s: given(args, s) for s in sections})


def resolve_run(recipe: dict, stored: tuple[TrainConfig, AgentConfig] | None = None):
    """``(TrainConfig, AgentConfig)`` of ``recipe`` on top of the field defaults, or of ``stored`` (a run's saved
    configuration) when resuming. Bad keys and values are refused in one line (CommandError)."""
    train = dict(recipe.get("train") or {})
    if stored is not None and any(k in train for k in BUDGET_FIELDS):  # a budget given replaces the saved one
        train = {**{k: None for k in BUDGET_FIELDS}, **train}
    if "reward_settings" in train:
        raise CommandError("[train]: no setting reward_settings (the [reward] section sets the reward's constants)")
    cfg = build(TrainConfig, train, "train", base=stored[0] if stored else None)
    reward = dict(recipe.get("reward") or {})
    own = [k for k in REWARD_OWN if k in reward]
    if own:
        raise CommandError(
            f"[reward]: {', '.join(own)} is set in [train] (train.reward, train.distance_increase_scale)"
        )
    if reward:
        r = build(RewardConfig, reward, "reward", base=cfg.reward_config())
        cfg = build(TrainConfig, {}, "train", base=_with_reward(cfg, r))
    agent_base = stored[1] if stored else _preset(cfg.preset)
    agent = build(AgentConfig, recipe.get("agent") or {}, "agent", base=agent_base)
    return cfg, agent


def _with_reward(cfg: TrainConfig, reward: RewardConfig) -> TrainConfig:
    return replace(cfg, reward_settings=reward_settings_of(reward))


def _preset(name: str) -> AgentConfig:
    try:
        return agent_config(name)
    except ValueError as e:
        raise CommandError(str(e)) from None


def run_recipe(cfg: TrainConfig, agent: AgentConfig) -> dict:
    """The resolved recipe of a run: every setting of its three sections (what ``recipe.toml`` holds)."""
    train = {k: v for k, v in to_recipe(cfg).items() if k not in TRAIN_HIDDEN}
    reward = {k: v for k, v in to_recipe(cfg.reward_config()).items() if k not in REWARD_OWN}
    return {"train": train, "reward": reward, "agent": to_recipe(agent)}


def identity_recipe(cfg: TrainConfig, agent: AgentConfig) -> dict:
    """:func:`run_recipe` without the budget (which may change when a run is resumed); with a learning-rate
    schedule, its horizon (:attr:`TrainConfig.lr_horizon`, which the ``updates`` budget sets when
    ``lr_decay_updates`` is None) as ``lr_decay_updates``."""
    r = run_recipe(cfg, agent)
    r["train"] = {k: v for k, v in r["train"].items() if k not in BUDGET_FIELDS}
    if cfg.lr_schedule != "constant":
        r["train"]["lr_decay_updates"] = cfg.lr_horizon
    return r


def refuse_other_settings(out: str | Path, stored: tuple, now: tuple) -> None:
    """A one-line CommandError naming the first setting where ``now`` differs from the run's ``stored``
    configuration (the budget aside)."""
    d = first_difference(identity_recipe(*stored), identity_recipe(*now))
    if d is None:
        return
    key, was, new = d
    name = key.removeprefix("train.")
    if isinstance(was, bool) and isinstance(new, bool):
        option = "--" + key.split(".")[-1].replace("_", "-")
        detail = f"trained {'with' if was else 'without'} {option}, given {'with' if new else 'without'} it"
    else:
        detail = f"{was} saved, {new} given"
    if name == "lr_decay_updates":
        detail += f" (a scheduled run keeps its horizon: --lr-decay-updates {was} trains it past its budget)"
    raise CommandError(
        f"{out} holds a run with another configuration ({name}): {detail}; use another --out or the run's settings"
    )
