"""The detector registry: the detectors that write per-state detection tables (``tsnav detect --detector NAME``).

A detector is named once, here: what it is, the table name it writes by default, whether it is a trained network
(the pipeline never overwrites a table of another detector, :mod:`tsnav.pipeline.steps`), and how ``tsnav detect``
opens it (``open(options, root, scenes, name)``: trains it first when it must, and returns a
:class:`TableMaker` whose ``fingerprint`` identifies it and whose ``write`` writes the tables of the given rooms).

=============  ==========  ========================================================================================
name           table       what
=============  ==========  ========================================================================================
``oracle``     oracle      ground truth from the renderer's instance ids, a hand-made confidence (:mod:`.oracle`)
``learned``    learned     the grid detector trained on the train rooms, calibrated on val (:mod:`.learned`)
``shipped``    learned     a learned detector that comes with tsnav, nothing trained (:mod:`.shipped`)
=============  ==========  ========================================================================================

Heavy modules (torch) load when a detector is opened, not with this registry.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..constants import check_same_class_set
from ..data.detections import write_detections
from ..data.reader import list_scenes, load_scene
from ..errors import CommandError


@dataclass
class TableMaker:
    """An opened detector: its ``fingerprint`` (recorded in every table it writes) and
    ``write(scenes, name, own, bar, workers)``: the tables of loaded rooms, ``detections_<own>.hdf5`` (``own`` is
    ``name`` plus the mirror suffix for mirrored rooms); ``bar``: a tqdm bar advanced by states, or None."""

    fingerprint: str
    write: Callable[[list, str, str, object, int], None]


@dataclass(frozen=True)
class DetectorKind:
    """One detector (see the module docstring)."""

    name: str
    doc: str
    table: str
    """Table name it writes when ``--name`` is not given."""
    trained: bool
    """A learned network (its tables are ``learned`` tables to the pipeline's rule on foreign tables)."""
    open: Callable[[argparse.Namespace, Path, list, str], TableMaker]
    """``open(options, root, scenes, name)``: ``options`` are the ``tsnav detect`` options (an argparse namespace)."""


#: Every detector by name.
DETECTORS: dict[str, DetectorKind] = {}


def register_detector(kind: DetectorKind) -> DetectorKind:
    """Add a detector to ``tsnav detect --detector`` (and to :data:`DETECTORS`)."""
    if kind.name in DETECTORS and DETECTORS[kind.name] != kind:
        raise ValueError(f"detector {kind.name!r} is already registered")
    DETECTORS[kind.name] = kind
    return kind


def detector_kind(name: str) -> DetectorKind:
    """The registered detector ``name``; ``ValueError`` naming the choices otherwise."""
    if name not in DETECTORS:
        raise ValueError(f"unknown detector {name!r} (choose from {', '.join(DETECTORS)})")
    return DETECTORS[name]


# -- oracle --------------------------------------------------------------------------------------------------
def _open_oracle(args, root: Path, scenes: list, name: str) -> TableMaker:
    from .oracle import OracleConfig, oracle_detections

    cfg = OracleConfig()

    def write(loaded, name, own, bar, workers):
        for s in loaded:
            det = oracle_detections(s, cfg)
            if bar is not None:
                bar.update(det.num_states)
            write_detections(s.path, own, det)

    return TableMaker(cfg.fingerprint(), write)


# -- learned and shipped -------------------------------------------------------------------------------------
def _network_maker(det) -> TableMaker:
    from .learned import write_scene_tables

    return TableMaker(
        det.fingerprint, lambda loaded, name, own, bar, workers: write_scene_tables(det, loaded, name, bar, workers)
    )


def _same_classes(det, what: str, root: Path, scenes: list):
    """``det`` when it detects the class set of the scenes; a one-line error naming both sets otherwise."""
    try:
        check_same_class_set(det.class_set, load_scene(scenes[0]).class_set, what, f"{root}")
    except ValueError as e:
        raise CommandError(str(e)) from None
    return det


def _open_shipped(args, root: Path, scenes: list, name: str) -> TableMaker:
    from .shipped import shipped_detector, shipped_for

    which = getattr(args, "shipped", None) or shipped_for(name)
    det = shipped_detector(load_scene(scenes[0]).image_size, name=which)
    return _network_maker(_same_classes(det, "the shipped detector", root, scenes))


def _open_learned(args, root: Path, scenes: list, name: str) -> TableMaker:
    return _network_maker(_same_classes(_learned(args, root), "the learned detector", root, scenes))


def _check_fold(args, ckpt: Path) -> None:
    """Cross-fitting: refuse a checkpoint that was ever trained on a scene of the fold whose tables it would write
    (every training segment it records, :func:`~tsnav.detect.train.seen_scenes`)."""
    from .train import read_meta, seen_scenes

    allowed = getattr(args, "train_scenes", None)
    if allowed is None:
        return
    seen = sorted(set(seen_scenes(read_meta(ckpt))) - set(allowed))
    if seen:
        raise CommandError(
            f"--checkpoint {ckpt} was trained on scenes of fold {args.fold} ({', '.join(seen[:3])}"
            f"{', ...' if len(seen) > 3 else ''}), whose tables it would write; give each fold its own checkpoint"
        )


def _learned(args, root: Path):
    """The learned detector of ``args.checkpoint`` (default ``ROOT/detectors/learned``), trained to
    ``--train-steps`` and calibrated on the val rooms first (not with ``--no-calibrate``, nor in a world without
    test scenes: there the val scenes are the benchmark)."""
    from .model import LossWeights
    from .train import (
        BenchmarkSplit,
        DetectorTrainConfig,
        calibrate,
        default_train_steps,
        is_checkpoint,
        read_meta,
        train_detector,
    )

    ckpt = Path(args.checkpoint) if args.checkpoint else root / "detectors" / "learned"
    if args.train_steps is not None and args.train_steps < 1:
        raise CommandError("--train-steps must be at least 1")
    if args.batch_size is not None and args.batch_size < 1:
        raise CommandError("--batch-size must be at least 1")
    if args.repeat_threshold is not None and not args.repeat_threshold >= 0:
        raise CommandError(f"--repeat-threshold must be >= 0, got {args.repeat_threshold}")
    if args.hard_negative_weight is not None and not (
        args.hard_negative_weight >= 0 and math.isfinite(args.hard_negative_weight)
    ):
        raise CommandError(f"--hard-negative-weight must be a finite number >= 0, got {args.hard_negative_weight}")
    if args.hard_negative_threshold is not None:
        if not args.hard_negative_weight:
            raise CommandError("--hard-negative-threshold needs --hard-negative-weight")
        if not 0 < args.hard_negative_threshold < 1:
            raise CommandError(f"--hard-negative-threshold must be in (0, 1), got {args.hard_negative_threshold}")
    if args.presence_pos_weight is not None and not (
        args.presence_pos_weight > 0 and math.isfinite(args.presence_pos_weight)
    ):
        raise CommandError(f"--presence-pos-weight must be a finite number > 0, got {args.presence_pos_weight}")
    if args.focal_alpha is not None and not 0 < args.focal_alpha < 1:
        raise CommandError(f"--focal-alpha must be in (0, 1), got {args.focal_alpha}")
    if ckpt.exists() and not ckpt.is_dir():
        raise CommandError(f"--checkpoint {ckpt} is a file; give a checkpoint folder")
    if ckpt.is_dir() and any(ckpt.iterdir()) and not is_checkpoint(ckpt):
        raise CommandError(f"--checkpoint {ckpt} is a folder that holds no detector checkpoint")
    existing = is_checkpoint(ckpt)
    # a new checkpoint takes its architecture from the train scenes; an existing one keeps its own, so a finished
    # checkpoint writes tables for a world without train scenes (a benchmark's val world)
    model_cfg = None if existing else _model_config(args, root)
    steps = args.train_steps
    if steps is None:  # an existing checkpoint: finish its own target (a no-op when it is finished)
        steps = (
            int(read_meta(ckpt).get("train", {}).get("steps", 0))
            if existing
            else default_train_steps(model_cfg.image_size)
        )
    if existing and not list_scenes(root, split="train"):
        at = int(read_meta(ckpt).get("step", 0))
        if steps > at:
            raise CommandError(
                f"{root}: no complete train scene to train the detector on (checkpoint {ckpt} is at step {at} of "
                f"{steps})"
            )
    tc = DetectorTrainConfig(
        steps=steps,
        threads=args.threads,
        max_states_per_scene=args.max_states_per_scene,
        repeat_threshold=args.repeat_threshold or 0.0,
        hard_negative_weight=args.hard_negative_weight or 0.0,
        hard_negative_threshold=args.hard_negative_threshold or 0.5,
    )
    if args.batch_size:
        tc.batch_size = args.batch_size
    if args.presence_pos_weight is not None or args.focal_alpha is not None:
        loss = LossWeights()
        if args.presence_pos_weight is not None:
            loss.presence_pos_weight = args.presence_pos_weight
        if args.focal_alpha is not None:
            loss.focal_alpha = args.focal_alpha
        tc.loss = loss
    if is_checkpoint(ckpt):
        _check_fold(args, ckpt)  # before training: refused without spending the steps
    retarget = bool(getattr(args, "retarget", False))
    if retarget and not existing:
        raise CommandError(f"--retarget goes on with an existing checkpoint at another frame size; {ckpt} holds none")
    res = train_detector(
        root,
        ckpt,
        tc,
        model_cfg=model_cfg,
        progress=not args.quiet,
        scenes=getattr(args, "train_scenes", None),
        retarget=retarget,
    )
    if res.step > res.start_step:
        print(
            f"trained the detector {res.start_step} -> {res.step} steps in {res.seconds:.0f}s "
            f"(last loss {res.last.get('loss', float('nan')):.3f}); checkpoint {ckpt}"
        )
    else:
        print(f"detector checkpoint {ckpt} at step {res.step}")
    _check_fold(args, ckpt)
    if getattr(args, "no_calibrate", False):
        print("no calibration (--no-calibrate); the checkpoint's temperature is kept")
    else:
        try:
            t = calibrate(root, ckpt, split="val", progress=not args.quiet)
            print(f"temperature {t:.3f} (fitted on val scenes)")
        except BenchmarkSplit as e:
            print(f"no calibration: {e}; the checkpoint's temperature is kept")
        except ValueError as e:
            print(f"no calibration ({e}); temperature 1")
    from .learned import LearnedDetector

    return LearnedDetector.load(ckpt)


def _model_config(args, root: Path):
    """Architecture of a new checkpoint: :func:`~tsnav.detect.model.default_config` of the train scenes' frame
    side, changed by ``--stem`` / ``--widths`` / ``--fine``."""

    from .model import default_config

    train = list_scenes(root, split="train")
    if not train:
        raise CommandError(f"{root}: no complete train scene to train the detector on")
    first = load_scene(train[0])
    size = first.image_size
    cfg = default_config(size, first.class_set.name)
    stem = cfg.stem = args.stem if args.stem is not None else cfg.stem
    if args.widths:
        try:
            widths = tuple(int(w) for w in args.widths.split(","))
        except ValueError:
            widths = ()
        if len(widths) != 3 or min(widths) < 1:
            raise CommandError(f"--widths {args.widths!r}: give three positive channel counts, e.g. 24,48,96")
        cfg.widths = widths
    if args.fine is not None:
        cfg.fine = bool(args.fine)
    if stem < 1 or size % (8 * stem) or size < 16 * stem:
        raise CommandError(f"--stem {stem} does not fit {size}px frames (the side must be a multiple of 8 x stem)")
    return cfg


register_detector(
    DetectorKind(
        "oracle",
        "ground truth from the renderer's instance ids (a hand-made confidence)",
        "oracle",
        trained=False,
        open=_open_oracle,
    )
)
register_detector(
    DetectorKind(
        "learned",
        "the grid detector, trained on the train rooms and calibrated on val",
        "learned",
        trained=True,
        open=_open_learned,
    )
)
register_detector(
    DetectorKind(
        "shipped",
        "a learned detector that comes with tsnav (128-px ithor-real rooms)",
        "learned",
        trained=True,
        open=_open_shipped,
    )
)
