"""``tsnav thor``: AI2-THOR interoperability (docs/AI2THOR.md).

    tsnav thor import SRC --out DST            lineage offline data (one scene folder or a folder of them)
    tsnav thor check SCENE_DIR ...             list departures from the lineage's layout
    tsnav thor export-detections SCENE_DIR --detections detections_oracle.hdf5 [--out FILE]
    tsnav thor export-live --scenes FloorPlan1,FloorPlan2 --out DST [--size 300]   (needs tsnav[thor])
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import CommandError
from .reader import SceneFormatError
from .thor_export import check_lineage_layout, export_detections_22x264
from .thor_import import ImportConfig, import_lineage_dataset
from .thor_live import LiveExportError, ThorUnavailable, export_live, make_controller


def build_parser(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    imp = sub.add_parser("import", help="import AI2-THOR offline data of the SAVN/VTNet/DOA/IOM lineage")
    imp.add_argument("src", help="a lineage scene folder (holding graph.json) or a folder of them")
    imp.add_argument("--out", required=True, help="dataset folder to write (one sub-folder per scene)")
    imp.add_argument("--copy", choices=("link", "copy", "none"), default="link",
                     help="images / depth / features / metadata: hard-link (default), copy, or leave out")
    imp.add_argument("--overwrite", action="store_true", help="redo scenes that are already complete")
    imp.add_argument("--detection-size", type=int, default=300,
                     help="frame size the lineage's detection boxes refer to, pixels (default 300)")

    chk = sub.add_parser("check", help="check scene folders against the lineage's layout")
    chk.add_argument("scene_dirs", nargs="+", help="scene folders")

    exd = sub.add_parser("export-detections", help="write the lineage's 22 x 264 table from a tsnav detection table")
    exd.add_argument("scene_dir", help="a tsnav scene folder")
    exd.add_argument("--detections", required=True, help="detections_<name>.hdf5 (path or name in SCENE_DIR)")
    exd.add_argument("--out", default=None, help="output file (default SCENE_DIR/detr_features_22cls.hdf5)")
    exd.add_argument("--box-size", type=int, default=300, help="frame size of the written boxes (default 300)")

    live = sub.add_parser("export-live", help="export scenes from a live AI2-THOR (pip install 'tsnav[thor]')")
    live.add_argument("--scenes", required=True, help="comma-separated AI2-THOR scene names, e.g. FloorPlan1,FloorPlan2")
    live.add_argument("--out", required=True, help="dataset folder to write (one sub-folder per scene)")
    live.add_argument("--size", type=int, default=300, help="frame side, pixels (default 300, the lineage's)")


def run(args) -> int:
    try:
        return {"import": _import, "check": _check, "export-detections": _export_detections,
                "export-live": _export_live}[args.action](args)
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
        problems = check_lineage_layout(d)
        if problems:
            bad += 1
            for p in problems:
                print(f"{d}: {p}")
        else:
            print(f"{d}: ok")
    return 1 if bad else 0


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
                print(f"{name}: {st.states} states, {st.positions} positions, {st.objects} objects, "
                      f"{st.steps} controller steps, {st.seconds:.0f}s")
    except LiveExportError as e:
        raise CommandError(str(e)) from None
    finally:
        stop = getattr(controller, "stop", None)
        if stop is not None:
            stop()
    return 0
