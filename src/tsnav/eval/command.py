"""``tsnav eval``: evaluate a policy on a fixed episode list; writes records.jsonl and metrics.json."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..constants import C_TARGET
from ..errors import CommandError
from ..sim.episodes import read_episodes
from ..metrics import format_table, summarize, write_json, write_records
from .policies import make_policy
from .runner import EvalConfig, config_dict, evaluate, load_bank_for_episodes


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, help="dataset root (scene folders)")
    parser.add_argument("--episodes", required=True, help="episode list JSON (from 'tsnav episodes')")
    parser.add_argument("--policy", default="explorer",
                        help="random | oracle | explorer | package.module:factory (default: explorer)")
    parser.add_argument("--run", default=None,
                        help="evaluate the trained agent of this `tsnav train` run folder (instead of --policy)")
    parser.add_argument("--checkpoint", default="auto",
                        help="--run: auto (the run's best checkpoint chosen by `tsnav select`, else the latest), "
                             "best, latest, or a checkpoint folder")
    parser.add_argument("--out", required=True, help="output folder for records.jsonl and metrics.json")
    parser.add_argument("--seed", type=int, default=0, help="seed of stochastic policies (default: 0)")
    parser.add_argument("--sample", action="store_true",
                        help="--run: sample the agent's actions (seeded by --seed) instead of the default greedy "
                             "argmax, the lineage's test-time rule")
    parser.add_argument("--max-steps", type=int, default=100, help="episode length limit (paper: 100)")
    parser.add_argument("--c-target", type=float, default=C_TARGET, help=f"stage-switch threshold (paper: {C_TARGET})")
    parser.add_argument("--success-distance", type=float, default=None,
                        help="success distance in metres (default: the episode list's)")
    parser.add_argument("--batch-size", type=int, default=4096, help="episodes stepped together")


def run(args: argparse.Namespace) -> int:
    if not Path(args.data).is_dir():
        raise CommandError(f"--data {args.data}: no such dataset folder")
    if args.max_steps < 1 or args.batch_size < 1:
        raise CommandError("--max-steps and --batch-size must be >= 1")
    if not 0.0 <= args.c_target <= 1.0:
        raise CommandError(f"--c-target must be in [0, 1], got {args.c_target}")
    episodes, meta = read_episodes(args.episodes)
    if not episodes:
        raise CommandError(f"{args.episodes}: the episode list is empty")
    dist = args.success_distance if args.success_distance is not None else float(meta.get("success_distance", 1.0))
    bank = load_bank_for_episodes(args.data, episodes, success_distance=dist, c_target=args.c_target)
    if args.run is not None:
        # lazy: rl.checkpoint imports torch (about 1.9 s, `python -X importtime`), which scripted policies never need
        from ..rl.checkpoint import load_policy

        try:
            policy = load_policy(args.run, bank, greedy=not args.sample, seed=args.seed, checkpoint=args.checkpoint)
        except FileNotFoundError as e:
            raise CommandError(str(e)) from None
        args.policy = f"run:{Path(args.run).resolve()}"
    else:
        policy = make_policy(args.policy, bank, seed=args.seed, c_target=args.c_target)
    config = EvalConfig(max_steps=args.max_steps, c_target=args.c_target, batch_size=args.batch_size)
    t0 = time.perf_counter()
    records = evaluate(bank, episodes, policy, config)
    seconds = time.perf_counter() - t0
    summary = summarize(records, config.min_optimal_length)
    out = Path(args.out)
    write_records(out / "records.jsonl", records)
    write_json(out / "metrics.json", {
        "metrics": summary, "policy": args.policy, "seed": args.seed, "sample": bool(args.sample),
        "checkpoint": str(args.checkpoint) if args.run is not None else None,
        "episodes_file": str(args.episodes),
        "data": str(Path(args.data).resolve()), "success_distance": dist, "config": config_dict(config),
        "detector_confidence": bank.confidence is not None, "seconds": seconds})
    print(f"policy {args.policy}: {len(records)} episodes in {seconds:.2f} s "
          f"(stage switch: {'detector' if bank.confidence is not None else 'ground-truth visibility'})")
    print(format_table(summary))
    print(f"wrote {out / 'records.jsonl'} and {out / 'metrics.json'}")
    return 0
