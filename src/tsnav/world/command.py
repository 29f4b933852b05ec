"""``tsnav world``: build an offline dataset of procedurally generated houses or real iTHOR rooms;
``tsnav world fidelity``: check a built world against recorded real trajectories (:mod:`tsnav.world.fidelity`)."""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import replace
from pathlib import Path

from ..errors import CommandError
from ..render.gl import RendererUnavailable
from .build import BuildConfig, build_dataset
from .presets import PRESETS


def build_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "action",
        nargs="?",
        default="build",
        choices=("build", "fidelity"),
        help="build (default): build a dataset; fidelity: check --data against --trajectories "
        "(iTHOR) or --episodes (RoboTHOR)",
    )
    p.add_argument("--preset", default="tiny", help=f"scene set: {', '.join(PRESETS)} (default tiny)")
    p.add_argument(
        "--out",
        default=None,
        help="dataset folder (one sub-folder per scene); for fidelity the report folder (default DATA/fidelity)",
    )
    p.add_argument(
        "--world-version",
        type=int,
        default=None,
        help="version of the ithor-real or robothor-real rules (default: the newest; ithor-real 1 rebuilds worlds "
        "made before issue 24, robothor-real 1 the val targets fitted by their centre)",
    )
    p.add_argument("--data", default=None, help="fidelity: a built dataset folder")
    p.add_argument(
        "--trajectories",
        default=None,
        help="fidelity: real trajectories file (format of ai2thor/real_trajectories/dev_scenes.json)",
    )
    p.add_argument(
        "--episodes",
        default=None,
        help="fidelity of a robothor-real world: the RoboTHOR challenge's "
        "episodes folder (EPISODES/{train,val}/SCENE.json.gz; robothor-challenge dataset/ layout)",
    )
    p.add_argument("--no-pictures", action="store_true", help="fidelity: do not draw the per-scene PNGs")
    p.add_argument(
        "--no-drift", action="store_true", help="fidelity: skip the pose-drift what-ifs (about 1 s per scene)"
    )
    p.add_argument(
        "--infer-train-objects",
        default=None,
        metavar="CHALLENGE",
        help="robothor-real: rebuild the train scenes the way the val ones are (furniture from the plans, targets "
        "inferred from 120 of each scene's challenge train episodes, CHALLENGE/train/SCENE.json.gz), not from their "
        "object records: a world whose train scenes look like its val scenes",
    )
    p.add_argument(
        "--camera-height",
        type=float,
        default=None,
        metavar="METRES",
        help="camera height above the floor the frames and visibility tables are rendered from (default 1.5, the "
        "lineage's; the RoboTHOR challenge's LoCoBot sees from about 0.87)",
    )
    p.add_argument("--scenes", default=None, help="comma-separated scene names instead of the preset's")
    p.add_argument("--size", type=int, default=None, help="image side in pixels (default: the preset's)")
    p.add_argument("--no-images", action="store_true", help="do not store images.hdf5 / depth.hdf5")
    p.add_argument(
        "--no-compression",
        action="store_true",
        help="store frames raw (default: gzip level 1, about 4.5x smaller at 128 px; stock h5py reads both)",
    )
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="worker processes")
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="world seed (same name + seed = same scene). robothor-real: any seed but 0 redraws the train "
        "apartments' floor and wall materials, per scene instead of per apartment (training frames for a detector or an "
        "agent that must not learn the apartments' surfaces); the val apartments, the benchmark, keep seed 0's; "
        "ithor-real: 0 only",
    )
    p.add_argument("--compact", action="store_true", default=None, help="small rooms (default: the preset's)")


def run_robothor_fidelity(args) -> int:
    from .robothor_fidelity import EpisodesError, markdown, robothor_fidelity_report

    if not os.path.isdir(args.episodes):
        raise CommandError(f"--episodes {args.episodes}: no such folder")
    try:
        doc, out = robothor_fidelity_report(args.data, args.episodes, args.out, pictures=not args.no_pictures)
    except (EpisodesError, FileNotFoundError) as e:
        raise CommandError(str(e)) from None
    print(markdown(doc).split("\n\n")[0])
    print(f"report in {out}")
    return 0


def run_fidelity(args) -> int:
    from .fidelity import TrajectoriesError, fidelity_report, markdown_table, summary

    if args.data and args.episodes and not args.trajectories:
        return run_robothor_fidelity(args)
    if not args.data or not (args.trajectories or args.episodes):
        raise CommandError("fidelity needs --data DIR and --trajectories FILE (iTHOR) or --episodes DIR (RoboTHOR)")
    if args.trajectories and args.episodes:
        raise CommandError("fidelity takes --trajectories FILE or --episodes DIR, not both")
    try:
        results, out = fidelity_report(
            args.data, args.trajectories, args.out, pictures=not args.no_pictures, drift=not args.no_drift
        )
    except TrajectoriesError as e:
        raise CommandError(str(e)) from None
    print(markdown_table(results), end="")
    c = summary(results)["counts"]
    pct = lambda a, n: 100.0 * a / n if n else float("nan")  # noqa: E731
    print(
        f"positions {pct(c['positions_kept'], c['positions']):.1f} %, moves kept {pct(c['moves_kept'], c['moves']):.1f}"
        f" %, blocked blocked {pct(c['blocked_kept'], c['blocked']):.1f} %; report in {out}"
    )
    w = json.loads((out / "fidelity.json").read_text())["summary"].get("without_drift")
    if w:
        print(
            f"without the pose drift its what-ifs find (fitted to these trajectories, not measured): "
            f"positions {w['positions']:.1f} %, moves kept {w['moves_kept']:.1f} %, blocked blocked "
            f"{w['blocked_blocked']:.1f} % (fidelity.md, 'Pose drift')"
        )
    return 0


def run(args) -> int:
    if args.action == "fidelity":
        return run_fidelity(args)
    if not args.out:
        raise CommandError("--out DIR is required to build a dataset")
    if args.preset not in PRESETS:
        raise CommandError(f"unknown preset {args.preset!r} (choose from {', '.join(PRESETS)})")
    cfg = BuildConfig.from_preset(
        args.preset,
        store_images=not args.no_images,
        seed=args.seed,
        **({"compression": None} if args.no_compression else {}),
        **({"image_size": args.size} if args.size else {}),
        **({"compact": True} if args.compact else {}),
        **({"world_version": args.world_version} if args.world_version is not None else {}),
        **({"infer_train": str(Path(args.infer_train_objects).resolve())} if args.infer_train_objects else {}),
    )
    if args.camera_height is not None:
        try:
            cfg = replace(cfg, camera_height=args.camera_height)
        except ValueError as e:  # BuildConfig's own check
            raise CommandError(f"--camera-height: {e}") from None
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()] if args.scenes else None
    if args.seed < 0:
        raise CommandError(f"--seed must be 0 or more, got {args.seed}")
    if args.seed and cfg.world == "ithor-real":
        raise CommandError(
            "--seed applies to the procedural and robothor-real worlds; ithor-real rooms are their records"
        )
    if cfg.infer_train is not None:
        if cfg.world != "robothor-real":
            raise CommandError(f"--infer-train-objects applies to the robothor-real world, not preset {args.preset!r}")
        from .presets import preset_scenes
        from .robothor_real import missing_train_episodes

        why = missing_train_episodes(cfg.infer_train, scenes or preset_scenes(args.preset))
        if why:
            raise CommandError(f"--infer-train-objects {args.infer_train_objects}: {why}")
    if cfg.world_version is not None and cfg.world not in ("ithor-real", "robothor-real"):
        raise CommandError(
            f"--world-version applies to the ithor-real and robothor-real worlds, not preset {args.preset!r}"
        )
    if cfg.world_version is not None:
        if cfg.world == "ithor-real":
            from .real import VERSIONS
        else:
            from .robothor_real import VERSIONS

        if cfg.world_version not in VERSIONS:
            raise CommandError(
                f"unknown --world-version {cfg.world_version} (choose from {', '.join(map(str, VERSIONS))})"
            )
    if cfg.image_size < 16 or cfg.image_size > 1024:
        raise CommandError(f"--size {cfg.image_size} is out of range (16..1024)")
    if args.workers < 1:
        raise CommandError("--workers must be at least 1")
    try:
        stats = build_dataset(args.out, args.preset, scenes, cfg, workers=args.workers)
    except RendererUnavailable as e:
        raise CommandError(str(e)) from None
    built = [s for s in stats if not s.skipped]
    print(f"{len(stats)} scenes in {args.out}: {len(built)} built, {len(stats) - len(built)} already complete")
    if built:
        states = sum(s.states for s in built)
        print(
            f"{states} states, {sum(s.positions for s in built)} positions, "
            f"{sum(s.objects for s in built)} target objects; render {sum(s.render_s for s in built):.1f}s, "
            f"write {sum(s.write_s for s in built):.1f}s"
        )
    return 0
