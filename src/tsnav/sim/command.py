"""``tsnav episodes``: write a fixed validation / test episode list (JSON) for a dataset split."""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

from ..constants import SUCCESS_DISTANCE
from ..errors import CommandError
from ..protocol import DEFAULT_PROTOCOL, check_protocol, protocol_of
from .batch import SceneBank
from .episodes import EpisodeConfig, class_set_meta, make_episodes, read_episodes, write_episodes
from ..settings import add_shared


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, help="dataset root (scene folders)")
    parser.add_argument("--split", default="test", help="scene split to draw from (default: test)")
    parser.add_argument(
        "--per-room-type",
        type=int,
        default=250,
        help="episodes per room type; fewer when the split has fewer (default: 250)",
    )
    parser.add_argument("--out", required=True, help="output JSON file")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    add_shared(
        parser,
        "protocol",
        default=DEFAULT_PROTOCOL,
        help="success protocol: paper (in view within --success-distance, start-success episodes "
        "left out) or lineage (the 1.5 m visibility map as the lineage's evaluator reads it; "
        "start-success episodes kept) (default: paper)",
    )
    parser.add_argument(
        "--success-distance",
        type=float,
        default=SUCCESS_DISTANCE,
        help="success distance of the paper protocol in metres (default: 1.0)",
    )
    parser.add_argument(
        "--start-horizon",
        type=int,
        default=-1,
        help="camera horizon of start states in degrees (0 or 30); -1 for both, about half each, "
        "as the lineage's test splits (default: -1)",
    )
    parser.add_argument(
        "--all-targets", action="store_true", help="allow every category present, not only the room type's target list"
    )
    parser.add_argument("--force", action="store_true", help="replace an existing, different episode list")


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if args.per_room_type < 1:
        raise CommandError(f"--per-room-type must be >= 1, got {args.per_room_type}")
    if not Path(args.data).is_dir():
        raise CommandError(f"--data {args.data}: no such dataset folder")
    try:
        protocol = check_protocol(args.protocol)
    except ValueError as e:
        raise CommandError(f"--protocol: {e}") from None
    bank = SceneBank.from_root(args.data, args.split, success_distance=args.success_distance, protocol=protocol)
    config = EpisodeConfig(
        start_horizon=None if args.start_horizon < 0 else args.start_horizon, room_targets=not args.all_targets
    )
    episodes = make_episodes(bank, args.per_room_type, args.seed, config)
    if not episodes:
        raise CommandError(f"{args.data}: no valid episode in split {args.split!r}")
    meta = {
        "split": args.split,
        "seed": args.seed,
        "protocol": protocol,
        "success_distance": args.success_distance,
        "per_room_type": args.per_room_type,
        "start_horizon": config.start_horizon,
        "room_targets": config.room_targets,
        "data": str(Path(args.data).resolve()),
        **class_set_meta(bank),
    }
    if out.exists():
        try:
            old, old_meta = read_episodes(out)
            old_protocol = protocol_of(old_meta)
        except ValueError:
            old, old_protocol = None, None
        if old == episodes and old_protocol == protocol:
            print(f"{out}: up to date ({len(episodes)} episodes)")
            return 0
        if not args.force:
            raise CommandError(f"{out} exists with different episodes; pass --force to replace it")
    write_episodes(out, episodes, **meta)
    per_room = Counter(e.room_type for e in episodes)
    mean_opt = sum(e.optimal_length for e in episodes) / len(episodes)
    print(
        f"wrote {len(episodes)} episodes to {out} ({bank.num_scenes} scenes of split {args.split!r}; "
        + ", ".join(f"{k}: {v}" for k, v in sorted(per_room.items()))
        + f"; mean optimal length {mean_opt:.1f}; protocol {protocol}"
        + (f", {sum(e.optimal_length == 0 for e in episodes)} start already succeeds" if protocol != "paper" else "")
        + ")"
    )
    return 0
