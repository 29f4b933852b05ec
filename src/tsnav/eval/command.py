"""``tsnav eval``: evaluate a policy on a fixed episode list (:func:`~tsnav.eval.runner.evaluate_to_folder`);
writes records.jsonl, trajectories.jsonl and metrics.json (and, with ``--video N``, clips of N episodes:
:mod:`tsnav.eval.video`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..constants import C_TARGET
from ..errors import CommandError
from ..metrics import format_table
from .outcomes import OUTCOMES_FILE, format_outcomes
from .runner import evaluate_to_folder
from ..settings import add_shared


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, help="dataset root (scene folders)")
    parser.add_argument("--episodes", required=True, help="episode list JSON (from 'tsnav episodes')")
    parser.add_argument(
        "--policy", default="explorer", help="random | oracle | explorer | package.module:factory (default: explorer)"
    )
    parser.add_argument(
        "--run", default=None, help="evaluate the trained agent of this `tsnav train` run folder (instead of --policy)"
    )
    parser.add_argument(
        "--checkpoint",
        default="auto",
        help="--run: auto (the run's best checkpoint chosen by `tsnav select`, else the latest), "
        "best, latest, or a checkpoint folder",
    )
    parser.add_argument(
        "--out", required=True, help="output folder for records.jsonl, trajectories.jsonl and metrics.json"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of stochastic policies (default: 0)")
    parser.add_argument(
        "--sample",
        action="store_true",
        help="--run: sample the agent's actions (seeded by --seed) instead of the default greedy "
        "argmax, the lineage's test-time rule",
    )
    parser.add_argument("--max-steps", type=int, default=100, help="episode length limit (paper: 100)")
    parser.add_argument("--c-target", type=float, default=C_TARGET, help=f"stage-switch threshold (paper: {C_TARGET})")
    parser.add_argument(
        "--success-distance", type=float, default=None, help="success distance in metres (default: the episode list's)"
    )
    add_shared(
        parser,
        "protocol",
        default=None,
        help="success protocol (paper | lineage; default: the episode list's). Naming it lets an "
        "agent trained under the other protocol be evaluated; it must be the list's (draw a "
        "list under each with `tsnav episodes --protocol`)",
    )
    parser.add_argument("--batch-size", type=int, default=4096, help="episodes stepped together")
    parser.add_argument(
        "--detections",
        default=None,
        help="detection table (detections_NAME.hdf5 in every scene) that drives the stage switch "
        "and, with --run, feeds the agent instead of its training table (default: --run: the "
        "run's own; scripted policies: ground-truth visibility)",
    )
    parser.add_argument(
        "--video",
        type=int,
        default=0,
        metavar="N",
        help="also write clips of N episodes (successes and failures) into OUT/videos/: the "
        "first-person frame beside the map with the path coloured by stage, the switch, the "
        "target's score and the action at each step (MP4, or GIF without imageio-ffmpeg)",
    )


def run(args: argparse.Namespace) -> int:
    if not Path(args.data).is_dir():
        raise CommandError(f"--data {args.data}: no such dataset folder")
    if args.max_steps < 1 or args.batch_size < 1:
        raise CommandError("--max-steps and --batch-size must be >= 1")
    if args.video < 0:
        raise CommandError(f"--video must be >= 0, got {args.video}")
    if not 0.0 <= args.c_target <= 1.0:
        raise CommandError(f"--c-target must be in [0, 1], got {args.c_target}")
    out = Path(args.out)
    summary = evaluate_to_folder(
        out,
        args.data,
        args.episodes,
        policy=args.policy,
        run=args.run,
        detections=args.detections,
        c_target=args.c_target,
        seed=args.seed,
        max_steps=args.max_steps,
        sample=args.sample,
        checkpoint=args.checkpoint,
        success_distance=args.success_distance,
        batch_size=args.batch_size,
        protocol=args.protocol,
        videos=args.video,
    )
    meta = json.loads((out / "metrics.json").read_text())
    n = sum(1 for line in (out / "records.jsonl").read_text().splitlines() if line.strip())
    print(
        f"{meta['label']}: {n} episodes in {meta['seconds']:.2f} s "
        f"(stage switch: {'detector' if meta['detector_confidence'] else 'ground-truth visibility'})"
    )
    print(format_table(summary, trained=meta.get("trained_protocol")))
    print(format_outcomes(json.loads((out / OUTCOMES_FILE).read_text())))
    print(
        f"wrote {out / 'records.jsonl'}, {out / 'trajectories.jsonl'}, {out / OUTCOMES_FILE} and {out / 'metrics.json'}"
    )
    if args.video:
        from .video import VIDEO_DIR, read_video_index

        clips = read_video_index(out)
        print(f"wrote {len(clips)} clips into {out / VIDEO_DIR}: " + ", ".join(c.file for c in clips))
    return 0
