"""``tsnav thor``: AI2-THOR interoperability (docs/AI2THOR.md).

It lives in ``eval`` because ``export-lineage`` and ``episodes`` draw on every layer below (scene format,
simulator episodes and shortest paths, the ResNet18 encoder); the format work itself is in ``tsnav.data``.

    tsnav thor import SRC --out DST            lineage offline data (one scene folder or a folder of them)
    tsnav thor check DIR ... [--complete] [--image-size 300]   departures from the lineage's layout (a scene
                                               folder, or a dataset folder: every scene and test_val_split/)
    tsnav thor export-detections SCENE_DIR --detections detections_oracle.hdf5 [--out FILE]
    tsnav thor export-lineage DIR --encoder SPEC --detections NAME   every file the lineage's code reads
    tsnav thor episodes SPLIT.pkl [...] --data DIR --out FILE        the lineage's episode lists -> tsnav JSON
    tsnav thor export-live --scenes FloorPlan1,FloorPlan2 --out DST [--size 300]   (needs tsnav[thor])
    tsnav thor challenge-episodes --challenge DIR --split val --data DIR --out FILE   the RoboTHOR challenge's
                                               episodes -> tsnav JSON (tsnav.sim.challenge)
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..constants import ROBOTHOR12
from ..data.lineage import GRAPH_FILE
from ..data.lineage_splits import SplitFormatError
from ..data.thor_export import check_lineage_dataset, check_lineage_layout, export_detections_22x264
from ..data.thor_import import ImportConfig, import_lineage_dataset
from ..data.thor_live import LiveExportError, ThorUnavailable, export_live, make_controller
from ..errors import CommandError
from ..protocol import check_protocol
from ..data.reader import SceneFormatError, is_complete, load_scene
from ..sim.batch import SceneBank
from ..sim.challenge import (
    CHALLENGE_SOURCE,
    HEADING_RULE,
    challenge_episodes,
    ratio_summary,
    read_challenge_episodes,
    take_sample,
)
from ..sim.episodes import write_episodes
from ..sim.lineage import episodes_from_splits
from ..settings import add_shared


def build_parser(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    imp = sub.add_parser("import", help="import AI2-THOR offline data of the SAVN/VTNet/DOA/IOM lineage")
    imp.add_argument("src", help="a lineage scene folder (holding graph.json) or a folder of them")
    imp.add_argument("--out", required=True, help="dataset folder to write (one sub-folder per scene)")
    imp.add_argument(
        "--copy",
        choices=("link", "copy", "none"),
        default="link",
        help="images / depth / features / metadata: hard-link (default), copy, or leave out",
    )
    imp.add_argument("--overwrite", action="store_true", help="redo scenes that are already complete")
    imp.add_argument(
        "--detection-size",
        type=int,
        default=300,
        help="frame size the lineage's detection boxes refer to, pixels (default 300)",
    )

    chk = sub.add_parser("check", help="check scene folders (or dataset folders) against the lineage's layout")
    chk.add_argument("scene_dirs", nargs="+", help="scene folders, or dataset folders holding scene folders")
    chk.add_argument(
        "--complete",
        action="store_true",
        help="require every file the lineage's trainer and evaluator read (ResNet features, DETR "
        "table, optimal actions, images; for a dataset folder also test_val_split/)",
    )
    chk.add_argument("--image-size", type=int, default=None, help="require images of this side (the lineage's: 300)")

    exl = sub.add_parser("export-lineage", help="write every file the lineage's trainer and evaluator read")
    exl.add_argument("data", help="tsnav dataset folder (scene folders); written in place")
    exl.add_argument(
        "--encoder",
        default=None,
        help="ResNet18 encoder for resnet18_featuremap.hdf5: a `tsnav pretrain --method resnet18-sup` "
        "run, resnet18:PATH (torchvision-layout weights) or untrained:resnet18",
    )
    exl.add_argument(
        "--detections",
        default=None,
        help="name of the detection table (detections_<NAME>.hdf5) for "
        "detr_features_22cls.hdf5, e.g. oracle or learned",
    )
    exl.add_argument(
        "--success-distance",
        type=float,
        default=1.5,
        help="success radius of optimal_action.json and the episode lists, metres (default 1.5, the "
        "lineage's visibility map; 1.0 is the paper's rule)",
    )
    exl.add_argument("--per-room-type", type=int, default=1000, help="episodes per room type and split (default 1000)")
    exl.add_argument("--seed", type=int, default=0, help="seed of the episode lists (default 0)")
    exl.add_argument("--batch-size", type=int, default=16, help="frames per ResNet batch (default 16)")
    exl.add_argument("--no-splits", action="store_true", help="do not write test_val_split/")
    exl.add_argument("--overwrite", action="store_true", help="replace ResNet features made by another encoder")
    exl.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")

    epi = sub.add_parser("episodes", help="read the lineage's episode lists (pickles, read safely) as tsnav episodes")
    epi.add_argument("splits", nargs="+", help="split files, e.g. test_val_split/kitchen_test_22.pkl")
    epi.add_argument("--data", required=True, help="dataset folder; episodes of scenes not in it are dropped")
    epi.add_argument("--out", required=True, help="tsnav episode list (JSON) to write")
    add_shared(
        epi,
        "protocol",
        default="paper",
        help="success protocol: paper (in view within --success-distance; starts that already succeed "
        "are dropped) or lineage (the visibility map, as the lineage's evaluator; such starts are "
        "kept and counted, as its lists have them) (default: paper)",
    )
    epi.add_argument(
        "--success-distance",
        type=float,
        default=1.0,
        help="success radius for the optimal lengths, metres (default 1.0, the paper's; 1.5 the lineage's)",
    )
    epi.add_argument("--force", action="store_true", help="replace an existing episode list")

    che = sub.add_parser(
        "challenge-episodes",
        help="read the RoboTHOR ObjectNav challenge's episodes (*.json.gz) as a tsnav episode list",
    )
    che.add_argument(
        "--challenge",
        required=True,
        help="the challenge's episode folder holding train/ and val/ (e.g. "
        "../shared/robothor/challenge_episodes); nothing is read unless it is given",
    )
    che.add_argument("--split", required=True, choices=("train", "val"), help="challenge split to convert")
    che.add_argument(
        "--data",
        required=True,
        help="dataset folder of the RoboTHOR scenes (one folder per scene, named as the challenge "
        "names it, e.g. FloorPlan_Val1_1); episodes of scenes not in it are dropped and counted",
    )
    che.add_argument("--out", required=True, help="tsnav episode list (JSON) to write")
    che.add_argument(
        "--protocol",
        default="paper",
        help="success protocol: paper (in view within --success-distance; starts that already succeed "
        "are dropped) or lineage (the visibility map; such starts are kept) (default: paper)",
    )
    che.add_argument(
        "--success-distance",
        type=float,
        default=1.0,
        help="success radius of the paper protocol, metres (default 1.0, the paper's and the challenge's)",
    )
    che.add_argument(
        "--sample",
        type=int,
        default=None,
        metavar="N",
        help="keep a fixed sample of N converted episodes (per room type; RoboTHOR's apartments are one), drawn "
        "with --seed as tsnav release make draws the checkpoint-scoring sample (default: every episode)",
    )
    che.add_argument("--seed", type=int, default=0, help="seed of --sample's draw (default 0)")
    che.add_argument("--force", action="store_true", help="replace an existing episode list")

    exd = sub.add_parser("export-detections", help="write the lineage's 22 x 264 table from a tsnav detection table")
    exd.add_argument("scene_dir", help="a tsnav scene folder")
    exd.add_argument("--detections", required=True, help="detections_<name>.hdf5 (path or name in SCENE_DIR)")
    exd.add_argument("--out", default=None, help="output file (default SCENE_DIR/detr_features_22cls.hdf5)")
    exd.add_argument("--box-size", type=int, default=300, help="frame size of the written boxes (default 300)")

    live = sub.add_parser("export-live", help="export scenes from a live AI2-THOR (pip install 'tsnav[thor]')")
    live.add_argument(
        "--scenes", required=True, help="comma-separated AI2-THOR scene names, e.g. FloorPlan1,FloorPlan2"
    )
    live.add_argument("--out", required=True, help="dataset folder to write (one sub-folder per scene)")
    live.add_argument("--size", type=int, default=300, help="frame side, pixels (default 300, the lineage's)")


def run(args) -> int:
    try:
        return {
            "import": _import,
            "check": _check,
            "export-detections": _export_detections,
            "export-live": _export_live,
            "export-lineage": _export_lineage,
            "episodes": _episodes,
            "challenge-episodes": _challenge_episodes,
        }[args.action](args)
    except SceneFormatError as e:
        raise CommandError(str(e)) from None


def _import(args) -> int:
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise CommandError(f"cannot write {out}: {e.strerror}") from None
    cfg = ImportConfig(copy_mode=args.copy, overwrite=args.overwrite, detection_image_size=args.detection_size)

    def show(st):
        if st.skipped:
            print(f"{st.name}: already complete")
            return
        extra = ", distances from metadata.json" if st.distances else ", success from the visibility map"
        det = ", detections" if st.detections else ""
        print(f"{st.name}: {st.states} states, {st.positions} positions, {st.objects} objects{extra}{det}")
        for w in st.warnings:
            print(f"{st.name}: warning: {w}")

    stats = import_lineage_dataset(args.src, out, cfg, progress=show)
    done = sum(not s.skipped for s in stats)
    print(f"{len(stats)} scenes in {out}: {done} imported, {len(stats) - done} already complete")
    return 0


def _check(args) -> int:
    bad = 0
    for d in args.scene_dirs:
        p = Path(d)
        if p.is_dir() and not (p / GRAPH_FILE).exists() and any((c / GRAPH_FILE).exists() for c in p.iterdir()):
            report = {
                f"{d.rstrip('/')}/{k}": v for k, v in check_lineage_dataset(p, args.complete, args.image_size).items()
            }
        else:
            report = {d: check_lineage_layout(d, args.complete, args.image_size)}
        for name, problems in report.items():
            if problems:
                bad += 1
                for prob in problems:
                    print(f"{name}: {prob}")
            else:
                print(f"{name}: ok")
    return 1 if bad else 0


def _export_lineage(args) -> int:
    from .lineage_export import export_lineage  # imports torch: only this subcommand encodes frames

    data = Path(args.data)
    if not data.is_dir():
        raise CommandError(f"{data}: no such dataset folder")
    if args.encoder is None and args.detections is None:
        raise CommandError(
            "name at least the --encoder (resnet18_featuremap.hdf5) or the --detections "
            "(detr_features_22cls.hdf5); the lineage's code reads both"
        )
    if not 0 < args.success_distance <= 10 or args.per_room_type < 1:
        raise CommandError("--success-distance must be in (0, 10] m and --per-room-type >= 1")
    encoder = None
    if args.encoder is not None:
        from ..pretrain.features import load_encoder  # torch, as above

        try:
            encoder = load_encoder(args.encoder, img_size=224, device=args.device)
        except (FileNotFoundError, ValueError) as e:
            raise CommandError(" ".join(str(e).split())) from None
        if encoder.arch != "resnet18":
            raise CommandError(
                f"--encoder {args.encoder} is a {encoder.arch}; the lineage's "
                f"resnet18_featuremap.hdf5 needs a ResNet18 (e.g. untrained:resnet18 or resnet18:PATH)"
            )
    try:
        st = export_lineage(
            data,
            encoder,
            args.detections,
            args.success_distance,
            args.per_room_type,
            args.seed,
            args.batch_size,
            args.overwrite,
            splits=not args.no_splits,
        )
    except ValueError as e:
        raise CommandError(" ".join(str(e).split())) from None
    print(
        f"{data}: {st.scenes} scenes, {st.states} states; resnet18_featuremap.hdf5 written in {st.resnet_written}, "
        f"detr_features_22cls.hdf5 in {st.detections_written}, optimal_action.json in {st.optimal_written}"
    )
    if st.split_files:
        print(
            f"{data / 'test_val_split'}: "
            + ", ".join(f"{k} ({v})" for k, v in st.split_files.items())
            + f"; made for success within {args.success_distance} m (tsnav_split_info.json)"
        )
    if st.image_sizes != [300]:
        print(
            f"note: images are {'/'.join(map(str, st.image_sizes))} px; the lineage's are 300 "
            f"(tsnav world --size 300); boxes are written in 300 px either way"
        )
    return 0


def _episodes(args) -> int:
    out = Path(args.out)
    if not Path(args.data).is_dir():
        raise CommandError(f"--data {args.data}: no such dataset folder")
    if out.exists() and not args.force:
        raise CommandError(f"{out} exists; pass --force to replace it")
    try:
        protocol = check_protocol(args.protocol)
        eps, st = episodes_from_splits(args.splits, args.data, args.success_distance, protocol=protocol)
    except SplitFormatError as e:
        raise CommandError(str(e)) from None
    except ValueError as e:
        raise CommandError(f"--protocol: {e}") from None
    print(st.summary())
    if not eps:
        raise CommandError(f"no episode of {', '.join(args.splits)} is in {args.data}")
    write_episodes(
        out,
        eps,
        split="lineage",
        source=[str(Path(p)) for p in args.splits],
        protocol=protocol,
        success_distance=args.success_distance,
        start_horizon=None,
        room_targets=True,
        data=str(Path(args.data).resolve()),
        dropped=st.dropped,
    )
    print(f"wrote {len(eps)} episodes to {out}")
    return 0


def _challenge_episodes(args) -> int:
    out, data = Path(args.out), Path(args.data)
    if not data.is_dir():
        raise CommandError(f"--data {data}: no such dataset folder")
    if not Path(args.challenge).is_dir():
        raise CommandError(f"--challenge {args.challenge}: no such folder")
    if out.exists() and not args.force:
        raise CommandError(f"{out} exists; pass --force to replace it")
    if args.sample is not None and args.sample < 1:
        raise CommandError(f"--sample must be >= 1, got {args.sample}")
    try:
        protocol = check_protocol(args.protocol)
    except ValueError as e:
        raise CommandError(f"--protocol: {e}") from None
    try:
        records = read_challenge_episodes(args.challenge, args.split)
    except ValueError as e:
        raise CommandError(str(e)) from None
    names = sorted({str(r["scene"]) for r in records})
    have = [n for n in names if is_complete(data / n)]
    if not have:
        raise CommandError(
            f"--data {data}: holds none of the {len(names)} scenes of the challenge's {args.split} "
            f"split (e.g. {names[0]})"
        )
    scenes = [load_scene(data / n) for n in have]
    other = [s for s in scenes if s.class_set is not ROBOTHOR12]
    if other:
        raise CommandError(
            f"{other[0].path}: declares class set {other[0].class_set.name}, but the challenge's 12 "
            f'target types are robothor12\'s (scene.json "class_set": "robothor12")'
        )
    bank = SceneBank(scenes, success_distance=args.success_distance, protocol=protocol)
    eps, st = challenge_episodes(records, bank)
    print(st.summary())
    for scene, c in sorted(st.per_scene.items()):
        lost = {k: v for k, v in c.items() if k not in ("read", "looked up", "kept")}
        if lost:
            print(
                f"  {scene}: {c['kept']} of {c['read']} kept; dropped "
                + ", ".join(f"{v} {k}" for k, v in sorted(lost.items()))
            )
    if not eps:
        raise CommandError(f"no episode of the challenge's {args.split} split could be converted on {data}")
    eps, sample = take_sample(eps, args.sample, args.seed)
    if sample:
        print(f"kept a sample of {len(eps)} of the {st.kept} converted episodes (seed {args.seed})")
    lengths = ratio_summary(eps)
    write_episodes(
        out,
        eps,
        split=args.split,
        source=CHALLENGE_SOURCE.format(split=args.split),
        challenge=str(Path(args.challenge).resolve()),
        protocol=protocol,
        success_distance=args.success_distance,
        class_set=bank.class_set.name,
        start_horizon=30,
        room_targets=False,
        heading_rule=HEADING_RULE,
        data=str(data.resolve()),
        conversion=st.to_json(),
        lengths=lengths,
        **sample,
    )
    if lengths.get("episodes"):
        print(
            f"tsnav grid metres / navmesh shortest_path_length over {lengths['episodes']} episodes: median "
            f"{lengths['median']:.3f} (quartiles {lengths['q1']:.3f}-{lengths['q3']:.3f}), "
            f"{100 * lengths['within_25pct']:.1f} % within +-25 %; mean L* {lengths['mean_optimal_actions']:.1f} "
            f"actions, {lengths['mean_optimal_metres']:.2f} m on the grid, {lengths['mean_navmesh_metres']:.2f} m "
            f"on the navmesh"
        )
    print(f"wrote {len(eps)} episodes to {out} (protocol {protocol}, class set {bank.class_set.name})")
    return 0


def _export_detections(args) -> int:
    path = export_detections_22x264(args.scene_dir, args.detections, args.out, box_size=args.box_size)
    print(f"wrote {path}")
    return 0


def _export_live(args) -> int:
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    if not scenes:
        raise CommandError("--scenes names no scene")
    if not 16 <= args.size <= 1024:
        raise CommandError(f"--size {args.size} is out of range (16..1024)")
    try:
        controller = make_controller(args.size)
    except ThorUnavailable as e:
        raise CommandError(str(e)) from None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        for name in scenes:
            st = export_live(controller, name, out, args.size)
            if st.skipped:
                print(f"{name}: already complete")
            else:
                print(
                    f"{name}: {st.states} states, {st.positions} positions, {st.objects} objects, "
                    f"{st.steps} controller steps, {st.seconds:.0f}s"
                )
    except LiveExportError as e:
        raise CommandError(str(e)) from None
    finally:
        stop = getattr(controller, "stop", None)
        if stop is not None:
            stop()
    return 0
