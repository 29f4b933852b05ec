"""``tsnav train``: train a navigation agent (paper III-D) with A3C or the batched A2C trainer.

A run folder holds ``config.json`` (resolved configuration), ``recipe.toml`` (the same settings as a recipe
file: ``tsnav train --config RUN/recipe.toml --out OTHER`` trains the run again), ``checkpoints/``, ``log.jsonl``
and ``tb/``. Rerunning the same command (or just ``tsnav train --out RUN``) resumes from the last checkpoint; a
finished run is not retrained; a larger budget continues it; any other setting that differs from the run's is
refused in one line naming it. Data parallel on one machine: ``tsnav train --algo batched --procs N ...`` (or
``torchrun --nproc-per-node N -m tsnav train --algo batched ...``).

Every setting is an option made from its field (:mod:`tsnav.rl.recipe`): ``--lr``, ``--k-distance``,
``--dropout`` ...; a recipe file (``--config configs/train/...toml``) sets many at once, ``--set
reward.k_distance=0.3`` one of them.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from ..atomic import atomic_write_text
from ..errors import CommandError
from ..settings import add_shared, dump_recipe
from .checkpoint import latest_checkpoint
from .recipe import (
    add_recipe_options,
    add_run_options,
    recipe_from_args,
    refuse_other_settings,
    resolve_run,
    run_recipe,
)
from .train import feature_info, stored_config, train_run

#: Settings a new run must name (detections: no fallback to ground truth, issue 14).
REQUIRED = ("data", "features", "detections")


def build_parser(parser: argparse.ArgumentParser) -> None:
    add_shared(parser, "out", required=True, help="run folder (created; an existing one is resumed)")
    add_recipe_options(parser)
    add_shared(parser, "quiet")
    add_run_options(parser)


def resolve(args: argparse.Namespace):
    """``(TrainConfig, AgentConfig)`` from the arguments, on top of the run's saved configuration if any."""
    out = Path(args.out)
    recipe = recipe_from_args(args)
    data = recipe.get("train", {}).get("data")
    if data:
        recipe["train"]["data"] = str(Path(data).resolve())
    if (out / "config.json").exists():
        stored = stored_config(out)
        now = resolve_run(recipe, stored)
        refuse_other_settings(out, stored, now)
        return now
    for need in REQUIRED:
        if not recipe.get("train", {}).get(need):
            raise CommandError(f"--{need} is required for a new run ({out} has no config.json)")
    if not Path(data).is_dir():
        raise CommandError(f"--data {data}: no such dataset folder")
    return resolve_run(recipe)


def run(args: argparse.Namespace) -> int:
    cfg, agent = resolve(args)
    feature_info(cfg)  # a missing feature cache stops here, in one line
    before = latest_checkpoint(args.out)
    progress = train_run(cfg, agent, args.out, progress_bar=not args.quiet)
    if int(os.environ.get("RANK", "0")) != 0:
        return 0
    atomic_write_text(
        Path(args.out) / "recipe.toml",
        dump_recipe(
            run_recipe(cfg, agent), header=f"The resolved recipe of the run {Path(args.out).name} (tsnav train)."
        ),
    )
    done = "finished" if progress.get("finished") else "stopped"
    if before is not None and latest_checkpoint(args.out) == before and progress.get("finished"):
        print(
            f"{args.out}: already finished ({progress['episodes']} episodes, {progress['update']} updates); "
            f"not retrained (pass a larger budget to continue)"
        )
    else:
        print(
            f"{args.out}: {done} after {progress['update']} updates, {progress['env_steps']} env steps, "
            f"{progress['episodes']} episodes, {progress['seconds'] / 60:.1f} min ({cfg.algo}, reward {cfg.reward})"
        )
    return 0
