"""``tsnav train``: train a navigation agent (paper III-D) with A3C or the batched A2C trainer.

A run folder holds ``config.json`` (resolved configuration), ``checkpoints/``, ``log.jsonl`` and ``tb/``.
Rerunning the same command (or just ``tsnav train --out RUN``) resumes from the last checkpoint; a finished
run is not retrained; a larger budget continues it. Data parallel on one machine: ``tsnav train --algo batched
--procs N ...`` (or ``torchrun --nproc-per-node N -m tsnav train --algo batched ...``).
"""

from __future__ import annotations

import argparse
import os
from dataclasses import replace
from pathlib import Path

from ..agent import agent_config
from ..constants import C_TARGET
from ..errors import CommandError
from .config import PRECISIONS, RANK_MODES, TrainConfig
from .checkpoint import latest_checkpoint
from .train import stored_config, train_run


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, help="run folder (created; an existing one is resumed)")
    parser.add_argument("--data", default=None, help="dataset root (required for a new run)")
    parser.add_argument("--features", default=None, help="feature cache name: features_<NAME>.hdf5 in every scene "
                                                          "(required for a new run; see `tsnav features`)")
    parser.add_argument("--reward", default=None, choices=["tsrm", "baseline", "explore", "distance"],
                        help="reward variant (default: tsrm)")
    parser.add_argument("--algo", default=None, choices=["a3c", "batched"], help="trainer (default: a3c, the paper's)")
    budget = parser.add_argument_group("budget (default: the paper's 1.5 M episodes)")
    budget.add_argument("--minutes", type=float, default=None, help="training minutes (summed over sessions)")
    budget.add_argument("--episodes", type=int, default=None, help="finished training episodes")
    budget.add_argument("--updates", type=int, default=None, help="optimizer updates")
    parser.add_argument("--lr", type=float, default=None, help="Adam learning rate (paper: 1e-4)")
    parser.add_argument("--num-envs", type=int, default=None,
                        help="batched: episodes per update over all processes (default: 16)")
    parser.add_argument("--procs", type=int, default=None,
                        help="batched: CPU processes sharing each update's episodes (default 1; 2 uses both cores "
                             "of a 2-core machine; the run is deterministic for a given seed and --procs)")
    parser.add_argument("--ranks", default=None, choices=RANK_MODES,
                        help="batched, --procs > 1: split (default) shares each update's episodes over the processes; "
                             "staggered gives each process --num-envs episodes of its own and applies their gradients "
                             "in turn (--procs updates per round, A3C-like staleness; BENCHMARKS.md)")
    parser.add_argument("--workers", type=int, default=None, help="a3c: worker processes (paper: 14)")
    parser.add_argument("--c-target", type=float, default=None, help=f"stage-switch threshold (paper: {C_TARGET})")
    parser.add_argument("--seed", type=int, default=None, help="seed (default: 0)")
    parser.add_argument("--preset", default=None, help="agent size: paper or cpu (default: paper)")
    parser.add_argument("--blocked-action", action="store_true", default=None,
                        help="a deviation from the paper: the previous-action input tells a MoveAhead that left the "
                             "agent where it was (AgentConfig.blocked_action); new runs only")
    parser.add_argument("--detections", default=None,
                        help="detection tables detections_<NAME>.hdf5 (`tsnav detect`), e.g. learned or oracle; "
                             "required (the agent never falls back to ground truth)")
    parser.add_argument("--mirror", action="store_true", default=None,
                        help="a deviation from the paper: also train on the mirror image of every training room "
                             "(TrainConfig.mirror; needs `tsnav features --mirror` and `tsnav detect --mirror`)")
    parser.add_argument("--distance-increase-scale", type=float, default=None,
                        help="a deviation from the paper (default 1.0, the paper's symmetric distance reward): "
                             "multiply the distance reward of a step that increases the distance to the target by "
                             "this (TrainConfig.distance_increase_scale)")
    parser.add_argument("--protocol", default=None,
                        help="success protocol: paper (in view within 1.0 m, the default) or lineage (the 1.5 m "
                             "visibility map, as the lineage's evaluator); sets the success mask of the reward and "
                             "the training episodes, and is recorded in config.json")
    parser.add_argument("--split", default=None, help="training scenes (default: train)")
    parser.add_argument("--rollout-steps", type=int, default=None, help="steps per update (default: 30)")
    parser.add_argument("--max-steps", type=int, default=None, help="training episode length (lineage: 30)")
    parser.add_argument("--checkpoint-every", type=int, default=None, help="updates between checkpoints")
    parser.add_argument("--milestone-every", type=int, default=None,
                        help="keep every checkpoint at a multiple of this many updates (default: only the newest two)")
    parser.add_argument("--log-every", type=int, default=None, help="updates between log lines")
    parser.add_argument("--device", default=None, help="auto, cpu or cuda (batched trainer)")
    parser.add_argument("--precision", default=None, choices=PRECISIONS,
                        help="forward passes of the rollouts in float32 (default) or bfloat16 autocast (faster on "
                             "CPUs with AVX512-BF16 / AMX and on GPUs)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


#: command-line option -> TrainConfig field
_FIELDS = {"data": "data", "features": "features", "reward": "reward", "algo": "algo", "lr": "lr",
           "num_envs": "num_envs", "procs": "procs", "ranks": "ranks", "workers": "workers", "c_target": "c_target",
           "seed": "seed",
           "preset": "preset", "detections": "detections", "split": "split", "rollout_steps": "rollout_steps",
           "max_steps": "max_steps", "checkpoint_every": "checkpoint_every", "log_every": "log_every",
           "milestone_every": "milestone_every",
           "device": "device", "precision": "precision", "protocol": "protocol", "mirror": "mirror",
           "distance_increase_scale": "distance_increase_scale"}


def resolve(args: argparse.Namespace):
    """``(TrainConfig, AgentConfig)`` from the arguments, on top of the run's saved configuration if any."""
    out = Path(args.out)
    given = {f: getattr(args, a) for a, f in _FIELDS.items() if getattr(args, a) is not None}
    budget = {k: getattr(args, k) for k in ("minutes", "episodes", "updates") if getattr(args, k) is not None}
    if (out / "config.json").exists():
        cfg, agent = stored_config(out)
        if given.get("data") is not None:
            given["data"] = str(Path(given["data"]).resolve())
        if "preset" in given and given["preset"] != cfg.preset:
            raise CommandError(f"{out} was trained with --preset {cfg.preset}; use another --out")
        if args.blocked_action and not agent.blocked_action:
            raise CommandError(f"{out} was trained without --blocked-action; use another --out")
        cfg = replace(cfg, **given, **({"episodes": None, "updates": None, "minutes": None, **budget} if budget else {}))
        return cfg, agent
    for need in ("data", "features", "detections"):  # detections: no fallback to ground truth (issue 14)
        if need not in given:
            raise CommandError(f"--{need} is required for a new run ({out} has no config.json)")
    if not Path(given["data"]).is_dir():
        raise CommandError(f"--data {given['data']}: no such dataset folder")
    given["data"] = str(Path(given["data"]).resolve())
    preset = given.get("preset", "paper")
    try:
        agent = agent_config(preset, blocked_action=bool(args.blocked_action))
    except ValueError as e:
        raise CommandError(str(e)) from None
    return TrainConfig(**given, **budget), agent


def run(args: argparse.Namespace) -> int:
    cfg, agent = resolve(args)
    before = latest_checkpoint(args.out)
    progress = train_run(cfg, agent, args.out, progress_bar=not args.quiet)
    if int(os.environ.get("RANK", "0")) != 0:
        return 0
    done = "finished" if progress.get("finished") else "stopped"
    if before is not None and latest_checkpoint(args.out) == before and progress.get("finished"):
        print(f"{args.out}: already finished ({progress['episodes']} episodes, {progress['update']} updates); "
              f"not retrained (pass a larger budget to continue)")
    else:
        print(f"{args.out}: {done} after {progress['update']} updates, {progress['env_steps']} env steps, "
              f"{progress['episodes']} episodes, {progress['seconds'] / 60:.1f} min ({cfg.algo}, reward {cfg.reward})")
    return 0
