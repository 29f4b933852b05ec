"""``tsnav detect``: write the per-state detection table of every scene (DESIGN.md "Detector").

    tsnav detect --data DIR --detector oracle
    tsnav detect --data DIR --detector learned [--checkpoint CKPT] [--train-steps N]
    tsnav detect --data DIR --detector shipped
    tsnav detect --data DIR --detector learned --checkpoint CKPT_I --fold I/K --name NAME   (once per fold I)
    tsnav detect --data DIR --frames DIR256 --detector learned --checkpoint CKPT [--retarget] --name NAME

The detectors are those of :mod:`tsnav.detect.registry`. ``oracle`` reads the renderer's instance statistics (:mod:`tsnav.detect.oracle`). ``learned`` trains the
grid detector on the TRAIN scenes if the checkpoint (default ``DIR/detectors/learned``) is missing or
has fewer than ``--train-steps`` steps (resumable: rerun the command after an interruption), fits its
temperature on the VAL scenes, then detects in every scene. ``shipped`` detects with the learned detector that
comes with tsnav (:mod:`tsnav.detect.shipped`; 128-px ithor-real rooms). Each scene gets
``detections_<name>.hdf5`` (name: ``--name``, default the detector kind, ``learned`` for ``shipped``); scenes
whose table was made by the same detector are skipped, a table made by another detector is only replaced with
``--overwrite``. ``--fold I/K`` cross-fits: the detector trains only on the train apartments outside fold I
(:mod:`tsnav.data.folds`) and writes fold I's train tables alone, so that an agent trained on the K folds' tables
meets the errors the detector makes in rooms it never saw. ``--frames DIR256`` gives the detector finer frames than
the agent's: it trains and detects on DIR256, a build of the same scenes at another side (``tsnav world --size``),
and DIR's tables get its boxes scaled to DIR's frames (:func:`tsnav.data.detections.rescale_detections`);
``--retarget`` lets a checkpoint trained at one side go on at another (:func:`tsnav.detect.train.retarget_model`). Finally the detector is evaluated on the VAL scenes (per-class AP, reliability table) unless ``--no-eval``; the report is printed
and saved as ``DIR/detectors/<name>_eval_<split>.json``.
"""

from __future__ import annotations

import argparse
import json
import signal
import threading
from pathlib import Path

from tqdm import tqdm

from ..atomic import atomic_write_text
from ..data.detections import check_name, load_detections, read_fingerprint, write_rescaled
from ..data.folds import assign_folds, parse_fold
from ..data.reader import MIRROR_SUFFIX, list_scenes, load_scene
from ..distributed import set_threads
from ..errors import CommandError
from .data import frame_twins
from .evaluate import evaluate_detections
from .registry import DETECTORS, detector_kind
from .shipped import DEFAULT_SHIPPED, SHIPPED


def build_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", required=True, help="dataset root (one folder per scene)")
    p.add_argument(
        "--detector",
        required=True,
        choices=tuple(DETECTORS),
        help="which detector (shipped: the learned detector that comes with tsnav, for 128-px ithor-real "
        "rooms; nothing trained, table name learned by default)",
    )
    p.add_argument(
        "--checkpoint",
        default=None,
        help="learned: checkpoint folder (default DATA/detectors/learned); trained there if needed",
    )
    p.add_argument(
        "--train-steps",
        type=int,
        default=None,
        help="learned: train up to this many steps (default for a new checkpoint: 9000 for frames of "
        "128px or more, else 2500; an existing checkpoint's own target)",
    )
    p.add_argument("--batch-size", type=int, default=None, help="learned: frames per training step (default 64)")
    p.add_argument(
        "--max-states-per-scene",
        type=int,
        default=None,
        help="learned: train on at most this many random states per train scene",
    )
    p.add_argument(
        "--repeat-threshold",
        type=float,
        default=None,
        help="learned: class-balanced sampling of training frames (repeat-factor sampling with this "
        "threshold, e.g. 0.1; 0 or absent: uniform); given for an existing checkpoint it applies "
        "from that checkpoint's step on",
    )
    p.add_argument(
        "--hard-negative-weight",
        type=float,
        default=None,
        help="learned: draw the training frames on which the checkpoint, as it stands, scores a class with "
        "no pixel in view above --hard-negative-threshold this many times as often (e.g. 4); given "
        "for an existing checkpoint it applies from that checkpoint's step on (absent or 0: the "
        "checkpoint's own setting, off for a new one); the mined frames are kept beside the "
        "checkpoint (hard_negatives.json)",
    )
    p.add_argument(
        "--hard-negative-threshold",
        type=float,
        default=None,
        help="learned, with --hard-negative-weight: score that makes such a frame a hard negative (default 0.5)",
    )
    p.add_argument(
        "--presence-pos-weight",
        type=float,
        default=None,
        help="learned: weight of the classes in view in the presence cross-entropy (default 1; e.g. 4 "
        "favours recall of targets in view over false positives); given for an existing checkpoint "
        "it applies from that checkpoint's step on (recorded in its loss_changes)",
    )
    p.add_argument(
        "--focal-alpha",
        type=float,
        default=None,
        help="learned: focal-loss weight of the positive cells (default 0.25); like "
        "--presence-pos-weight for an existing checkpoint",
    )
    p.add_argument(
        "--stem",
        type=int,
        default=None,
        help="learned, new checkpoint: space-to-depth factor of the input (default: frame side / 64, so "
        "128px frames cost what 64px ones do)",
    )
    p.add_argument(
        "--widths",
        default=None,
        help="learned, new checkpoint: channels of the three backbone stages, e.g. 24,48,96 "
        "(default 32,64,128 for frames of 128px or more, else 16,32,64)",
    )
    p.add_argument(
        "--fine",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="learned, new checkpoint: output cells of stride 4 after the stem instead of 8 (an FPN-style "
        "lateral from the second stage; better for small objects; default on for frames of 128px "
        "or more)",
    )
    p.add_argument(
        "--retarget",
        action="store_true",
        help="learned, existing checkpoint: train it on in train scenes whose frames have another side than those "
        "it learned on (its weights carry over, the network being convolutional; recorded in the checkpoint's "
        "size_changes), e.g. a 128-px detector going on at 256 px with --frames",
    )
    p.add_argument(
        "--frames",
        default=None,
        metavar="DIR",
        help="learned, shipped: train and detect on the frames of DIR, a build of the same scenes at another side "
        "(tsnav world --size; the same states), and write DATA's tables with the boxes scaled to DATA's frames: a "
        "detector that sees finer frames than the agent (DIR's scenes keep the tables at their own side too)",
    )
    p.add_argument(
        "--shipped",
        choices=sorted(SHIPPED),
        default=None,
        help=f"shipped: which shipped detector (default: the one --name names, if any, else "
        f"{DEFAULT_SHIPPED}; learned3 wrote the tables of the "
        "medium-scale experiments; learned6 favours recall; learned7, twice as wide, ranks better; "
        "robothor1, robothor2 (trained longer), robothor3 (trained on in train apartments rebuilt the val way) and "
        "robothor4 (robothor3 trained longer), robothor5 (the same steps on redrawn surfaces), robothor5hr "
        "(robothor5 trained on at 256 px: give it --frames): "
        "the 12 RoboTHOR targets, for robothor-real worlds; see "
        "tsnav.detect.shipped)",
    )
    p.add_argument("--name", default=None, help="table name detections_<name>.hdf5 (default: the detector kind)")
    p.add_argument("--split", default=None, help="only write tables for scenes of this split (default: all)")
    p.add_argument(
        "--fold",
        default=None,
        metavar="I/K",
        help="learned: cross-fitting; train only on the train apartments outside fold I of K (the apartments, "
        "sorted by name, dealt to the folds in turn; a RoboTHOR apartment's five variants stay together) and "
        "write the tables of fold I's train scenes alone, so that no train table is the detector's own "
        "training data; run once per fold with one --name and a --checkpoint per fold; the evaluation "
        "then scores fold I's scenes",
    )
    p.add_argument("--eval-split", default="val", help="split to evaluate on (default val)")
    p.add_argument("--no-eval", action="store_true", help="skip the evaluation")
    p.add_argument(
        "--no-calibrate",
        action="store_true",
        help="learned: keep temperature 1, fit nothing on the val scenes (the default in a world without test "
        "scenes, such as robothor-real, whose val scenes are the benchmark)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace tables made by another detector")
    p.add_argument(
        "--mirror",
        action="store_true",
        help="the tables of the rooms' mirror images (frames flipped left to right), written as "
        "detections_<name>-mirror.hdf5, for training on mirrored rooms (`tsnav train --mirror`); the "
        "evaluation then scores them against the mirrored ground truth",
    )
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        help="learned and shipped detectors: CPU processes sharing the rooms' tables, one thread each "
        "(e.g. 2 on a 2-core machine; the same tables for any value; default 1: this process)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _fold_scenes(args: argparse.Namespace, root: Path) -> tuple[list[Path], list[str], str]:
    """``--fold I/K``: (fold I's train scene folders, whose tables are written; the names of the other folds' train
    scenes, the detector's training data; "I/K"), with one-line errors for what cannot be cross-fitted."""
    try:
        i, k = parse_fold(args.fold)
    except ValueError as e:
        raise CommandError(f"--fold: {e}") from None
    if args.detector != "learned":
        raise CommandError(
            f"--fold cross-fits a detector trained here: it needs --detector learned, not {args.detector}"
        )
    if args.split not in (None, "train"):
        raise CommandError(f"--fold writes the tables of train scenes only; --split {args.split} cannot go with it")
    train = list_scenes(root, split="train")
    try:
        folds = assign_folds([p.name for p in train], k)
    except ValueError as e:
        raise CommandError(f"--fold {args.fold}: {root}'s train scenes: {e}") from None
    return [p for p in train if folds[p.name] == i], [p.name for p in train if folds[p.name] != i], f"{i}/{k}"


def _frame_scenes(args: argparse.Namespace, root: Path, scenes: list[Path]) -> tuple[Path, list[Path], list[int]]:
    """``--frames DIR``: (DIR, DIR's folder of each of ``scenes``, each of ``scenes``' frame side), with a one-line
    error for a detector, an option or a folder that cannot go with it: every scene must be a complete scene of DIR
    with the same states."""
    frames = Path(args.frames)
    if args.detector not in ("learned", "shipped"):
        raise CommandError(
            f"--frames gives a network detector DIR's frames: it needs --detector learned or shipped, not "
            f"{args.detector}"
        )
    if args.mirror or args.fold is not None:
        raise CommandError(f"--frames does not go with {'--mirror' if args.mirror else '--fold'}")
    if not frames.is_dir():
        raise CommandError(f"--frames {frames}: no such dataset folder")
    if frames.resolve() == root.resolve():
        raise CommandError(f"--frames {frames} is --data itself; give a build of the same scenes at another --size")
    twins = frame_twins(scenes, frames, f"--frames {frames}")
    out, sizes = [q for _, q, _, _ in twins], [size for _, _, size, _ in twins]
    return frames, out, sizes


def _sigterm_interrupts() -> None:
    """Turn SIGTERM into KeyboardInterrupt so that training saves a checkpoint before the process ends
    (background jobs ignore SIGINT)."""
    if threading.current_thread() is threading.main_thread():

        def handler(signum, frame):
            raise KeyboardInterrupt

        signal.signal(signal.SIGTERM, handler)


def _load(path: Path, mirror: bool):
    """The room of ``path``, or its mirror image (:meth:`~tsnav.data.reader.Scene.mirrored`)."""
    scene = load_scene(path)
    return scene.mirrored() if mirror else scene


def run(args: argparse.Namespace) -> int:
    root = Path(args.data)
    if not root.is_dir():
        raise CommandError(f"--data {root}: no such dataset folder")
    if args.threads < 1:
        raise CommandError("--threads must be at least 1")
    if args.workers < 1:
        raise CommandError("--workers must be at least 1")
    set_threads(args.threads)
    _sigterm_interrupts()
    kind = detector_kind(args.detector)
    name = check_name(args.name or kind.table)
    scenes = list_scenes(root, split=args.split)
    if not scenes:
        raise CommandError(f"{root}: no complete scene folder" + (f" of split {args.split}" if args.split else ""))
    fold = None
    if args.fold is not None:
        scenes, args.train_scenes, fold = _fold_scenes(args, root)
    # the scene folders the detector reads and each scene's frame side (only --frames reads them: DIR's folders)
    frames_root, source, sizes = None, scenes, [0] * len(scenes)
    if args.frames is not None:
        frames_root, source, sizes = _frame_scenes(args, root, scenes)
    # the detector, ready to write tables (trained first if needed, on the frames it reads)
    maker = kind.open(args, frames_root or root, source, name)
    fingerprint = maker.fingerprint

    own = name + MIRROR_SUFFIX if args.mirror else name  # the tables' file name
    todo, done = [], 0
    for p, q, size in zip(scenes, source, sizes):
        fp = read_fingerprint(p, own)
        if fp == fingerprint:
            done += 1
            continue
        for folder in {p, q}:
            other = read_fingerprint(folder, own)
            if other not in (None, fingerprint) and not args.overwrite:
                raise CommandError(
                    f"{folder / f'detections_{own}.hdf5'} was made by another detector ({other}); use --overwrite or "
                    "another --name"
                )
        todo.append((p, q, size))
    # --frames: a table of DIR's that this detector already wrote (an interrupted run) is rescaled, not made again
    fresh = [q for _, q, _ in todo if frames_root is None or read_fingerprint(q, own) != fingerprint]
    loaded = [_load(q, args.mirror) for q in fresh]
    bar = tqdm(
        total=sum(s.num_states for s in loaded),
        desc=f"detect {own}",
        unit="state",
        disable=args.quiet,
        dynamic_ncols=True,
    )
    try:
        maker.write(loaded, name, own, bar, args.workers)
    finally:
        bar.close()
    if frames_root is not None:  # DATA's tables: the boxes in DATA's pixels
        for p, q, size in todo:
            write_rescaled(q, p, own, size)
    print(
        f"detections_{own}.hdf5: {len(todo)} scenes written, {done} already done "
        f"({sum(s.num_states for s in loaded)} states)"
    )

    if not args.no_eval:
        if fold is not None:  # the fold's scenes: held out from this detector's training
            where, tag, eval_paths = f"fold {fold}", "fold" + fold.replace("/", "of"), scenes
        else:
            where, tag, eval_paths = args.eval_split, args.eval_split, list_scenes(root, split=args.eval_split)
        eval_scenes = [_load(p, args.mirror) for p in eval_paths]
        eval_scenes = [s for s in eval_scenes if (s.path / f"detections_{own}.hdf5").exists()]
        if not eval_scenes:
            print(f"no {where} scene with detections_{own}.hdf5: nothing to evaluate")
            return 0
        report = evaluate_detections(eval_scenes, [load_detections(s.path, own) for s in eval_scenes])
        print(f"evaluation of {own} on {where} scenes:")
        print(report.format())
        out = root / "detectors" / f"{own}_eval_{tag}.json"
        atomic_write_text(
            out,
            json.dumps(
                {"detector": args.detector, "name": own, "fingerprint": fingerprint, **report.to_json()}, indent=1
            ),
        )
        print(f"saved {out}")
    return 0
