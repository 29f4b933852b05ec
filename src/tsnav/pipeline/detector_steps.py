"""The learned detector as a pipeline step of the experiments and the demo (issue 14 item 4; paper III-B: a real
detector's confidence drives the stage switch and its table feeds the agent's target memory).

:func:`ensure_detector` trains (or resumes, or finds finished) the grid detector of :mod:`tsnav.detect` in a
detector folder on the TRAIN rooms, with the sizes and step budget of a :class:`ScaleConfig`, and fits its
temperature on the VAL rooms. :func:`ensure_learned_detections` gives every scene of a dataset a learned table:

* every scene already holds one made by the same learned detector (e.g. tables the lead wrote with
  ``tsnav detect``): they are used as they are, nothing is trained;
* some scenes lack one: the detector of the folder is trained / calibrated and its tables are written into
  those scenes only;
* a table made by another detector (an oracle's, or a learned detector other than the folder's) is never
  retrained or overwritten: one-line error naming the file.

Training, calibration and detection run on one torch thread (restored afterwards): the detector, its tables and
so every agent trained on them are then the same whatever ``--threads`` the caller uses.

:func:`detection_quality` measures a table on the VAL rooms (presence and box AP, ECE, reach of ``C_target``, false
positives: :mod:`tsnav.detect.evaluate`, :mod:`tsnav.detect.quality`); experiments record it in
``OUT/detector_quality.json`` and print it under their table.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Callable

import torch
from tqdm import tqdm

from ..atomic import atomic_write_json
from ..distributed import set_threads
from ..constants import C_TARGET, DEFAULT_CLASS_SET
from ..data.detections import detections_path, load_detections, read_fingerprint, write_rescaled
from ..data.reader import list_scenes, load_scene
from ..detect.data import frame_twins
from ..detect.evaluate import evaluate_detections
from ..detect.learned import LearnedDetector, write_scene_tables
from ..detect.shipped import shipped_detector, shipped_for, shipped_meta
from ..detect.model import DetectorConfig
from ..detect.quality import switch_report
from ..detect.train import BenchmarkSplit, DetectorTrainConfig, calibrate, is_checkpoint, read_meta, train_detector
from ..errors import CommandError
from .config import ScaleConfig
from ..report.tables import quality_line

#: Prefix of every learned detector's fingerprint (:func:`tsnav.detect.train.weights_fingerprint`).
LEARNED_PREFIX = "learned-"
#: The experiment folder's record of its detection tables' quality.
QUALITY_FILE = "detector_quality.json"


class one_thread:
    """Context: torch on one CPU thread, the caller's count restored on exit."""

    def __enter__(self):
        self.before = torch.get_num_threads()
        set_threads(1)

    def __exit__(self, *exc):
        set_threads(self.before)
        return False


def detector_configs(
    scale: ScaleConfig, image_size: int, class_set: str = DEFAULT_CLASS_SET
) -> tuple[DetectorTrainConfig, DetectorConfig]:
    """Training settings and the architecture of a new detector at ``scale`` for ``image_size``-px frames of
    scenes of ``class_set``."""
    tc = replace(scale.detector, threads=1)
    mc = DetectorConfig.from_dict({**scale.detector_model, "image_size": image_size, "class_set": class_set})
    return tc, mc


def ensure_detector(
    train_root: str | Path,
    calib_root: str | Path,
    detector_dir: str | Path,
    scale: ScaleConfig,
    progress: bool = True,
    say: Callable[[str], None] = print,
) -> LearnedDetector:
    """Train (resume; nothing when finished) the learned detector in ``detector_dir`` on the train rooms of
    ``train_root`` up to ``scale.detector.steps`` steps, fit its temperature on the val rooms of ``calib_root``
    (once per step count; not when they are the benchmark, :class:`~tsnav.detect.train.BenchmarkSplit`) and load
    it. A folder trained on other rooms is refused (one line)."""
    detector_dir = Path(detector_dir)
    train = list_scenes(train_root, split="train")
    if not train:
        raise CommandError(f"{train_root}: no complete train room to train the detector on")
    names = sorted(p.name for p in train)
    if detector_dir.exists() and not detector_dir.is_dir():
        raise CommandError(f"detector folder {detector_dir} is a file")
    if is_checkpoint(detector_dir):
        was = read_meta(detector_dir).get("train_scenes")
        if was is not None and sorted(was) != names:
            raise CommandError(
                f"{detector_dir} holds a detector trained on other rooms ({len(was)} rooms, "
                f"{was[0]} ...); use another --detector-dir"
            )
    elif detector_dir.is_dir() and any(detector_dir.iterdir()):
        raise CommandError(f"{detector_dir} is a folder that holds no detector checkpoint; use another --detector-dir")
    first = load_scene(train[0])
    tc, mc = detector_configs(scale, first.image_size, first.class_set.name)
    with one_thread():
        res = train_detector(train_root, detector_dir, tc, model_cfg=mc, progress=progress)
        if res.step > res.start_step:
            say(
                f"    detector trained {res.start_step} -> {res.step} steps in {res.seconds:.0f} s "
                f"(last loss {res.last.get('loss', float('nan')):.3f}) -> {detector_dir}"
            )
        try:
            t, how = calibrate(calib_root, detector_dir, split="val", progress=progress), "fitted on the val rooms"
        except BenchmarkSplit:
            t, how = float(read_meta(detector_dir)["temperature"]), "kept: the val rooms are the benchmark"
    say(f"    detector at step {res.step}, temperature {t:.3f} ({how})")
    return LearnedDetector.load(detector_dir)


def learned_tables(data: str | Path, name: str, split: str | None = None) -> tuple[dict[Path, str | None], list[str]]:
    """(fingerprint of every scene's ``detections_<name>.hdf5`` or None, the one learned detector's fingerprint
    as a list of at most one), over the scenes of ``data`` (of ``split`` only, when given). One-line error when a
    table was made by an oracle or the scenes' tables by two learned detectors."""
    paths = list_scenes(data, split=split)
    if not paths:
        raise CommandError(f"{data}: no complete scene")
    have = {p: read_fingerprint(p, name) for p in paths}
    for p, fp in have.items():
        if fp is not None and not fp.startswith(LEARNED_PREFIX):
            raise CommandError(
                f"{detections_path(p, name)} was made by another detector ({fp}), not a learned one; "
                f"remove it or use another --detections name"
            )
    kinds = sorted({fp for fp in have.values() if fp is not None})
    if len(kinds) > 1:
        odd = next(p for p, fp in have.items() if fp == kinds[1])
        raise CommandError(
            f"{detections_path(odd, name)} was made by another learned detector ({kinds[1]}) than other "
            f"scenes' ({kinds[0]}); remove the stale tables"
        )
    return have, kinds


def tables_complete(data: str | Path, name: str) -> str | None:
    """The learned detector's fingerprint when every scene of ``data`` already holds its table (they are then
    used as they are), else None (errors of :func:`learned_tables`)."""
    have, kinds = learned_tables(data, name)
    return kinds[0] if kinds and all(fp is not None for fp in have.values()) else None


def complete_tables(data: str | Path, name: str, source: str | None = None) -> str | None:
    """:func:`tables_complete` under the one rule on a complete set of tables from another source than the one
    asked for (``source``: ``shipped`` or ``train``, :data:`~tsnav.pipeline.config.DETECTOR_SOURCES`; None:
    any): the shipped detector's tables are not taken by a run that trains its detector, nor another learned
    detector's by a run that asks for the shipped one; one-line error, the tables are kept."""
    ready = tables_complete(data, name)
    # --detector shipped takes the tables of the shipped detector it would write them with (shipped_for); a run
    # that trains its detector refuses the default shipped detector's, as before tables were named after detectors
    shipped_fp = shipped_meta(shipped_for(name) if source == "shipped" else None)["fingerprint"]
    if ready and source is not None and (ready == shipped_fp) != (source == "shipped"):
        have = "the shipped detector's" if ready == shipped_fp else f"another learned detector's ({ready})"
        other = "train" if source == "shipped" else "shipped"
        raise CommandError(
            f"every room of {data} holds {have} detections_{name}.hdf5, not from --detector {source}: "
            f"use another --out or --data (tables are never overwritten), or --detector {other}"
        )
    return ready


def ensure_learned_detections(
    data: str | Path,
    name: str,
    detector_dir: str | Path,
    scale: ScaleConfig,
    progress: bool = True,
    say: Callable[[str], None] = print,
    train_root: str | Path | None = None,
    workers: int = 1,
) -> dict:
    """Give every scene of ``data`` a learned table ``detections_<name>.hdf5`` (module docstring; the detector
    trains on the train rooms of ``train_root``, default ``data``, and is calibrated on the val rooms of ``data``;
    ``workers`` processes write the tables); returns ``{"fingerprint", "written", "trained"}`` (``trained``: the
    detector folder was used)."""
    have, kinds = learned_tables(data, name)
    if not any(fp is None for fp in have.values()):
        return {"fingerprint": kinds[0], "written": 0, "trained": False}
    det = ensure_detector(train_root or data, data, detector_dir, scale, progress=progress, say=say)
    return {
        **write_learned_tables(data, name, det, progress=progress, say=say, source=str(detector_dir), workers=workers),
        "trained": True,
    }


def ensure_shipped_detections(
    data: str | Path, name: str, progress: bool = True, say: Callable[[str], None] = print, workers: int = 1
) -> dict:
    """Like :func:`ensure_learned_detections`, with the detector shipped in the package
    (:mod:`tsnav.detect.shipped`, :func:`~tsnav.detect.shipped.shipped_for` ``name``, loaded for the scenes' frame size) writing the
    missing tables: nothing is trained. Returns ``{"fingerprint", "written"}``."""
    have, kinds = learned_tables(data, name)
    if not any(fp is None for fp in have.values()):
        return {"fingerprint": kinds[0], "written": 0}
    which = shipped_for(name)
    det = shipped_detector(load_scene(next(iter(have))).image_size, name=which)
    return write_learned_tables(
        data, name, det, progress=progress, say=say, source=f"the shipped detector {which}", workers=workers
    )


def write_learned_tables(
    data: str | Path,
    name: str,
    det: LearnedDetector,
    progress: bool = True,
    say: Callable[[str], None] = print,
    source: str = "the given detector",
    workers: int = 1,
    split: str | None = None,
    frames: str | Path | None = None,
) -> dict:
    """Write the tables of detector ``det`` into the scenes of ``data`` (of ``split`` only, when given) that lack
    ``detections_<name>.hdf5``
    (one torch thread per scene; ``workers`` processes share the scenes, :func:`tsnav.scene_pool.map_scenes`: the
    same tables for every value); a table made by another detector is refused in one line and never overwritten
    (``source`` names ``det`` in that line). Returns ``{"fingerprint", "written"}``.

    ``frames``: for a detector that reads other frames than ``data``'s, a build of the same scenes at ``det``'s side
    with the same states (``tsnav world --size``). ``det`` then writes its tables into ``frames``' scenes (kept, in
    its own pixels; a table it wrote there before is not made again) and ``data``'s scenes get them with the boxes
    scaled to their frames (:func:`~tsnav.data.detections.rescale_detections`), as ``tsnav detect --frames`` writes
    them; one-line errors for a scene ``frames`` lacks or holds with other states or at another side."""
    have = _tables_of(data, name, split, det, source)
    todo = [p for p, fp in have.items() if fp is None]
    if frames is not None:
        return _write_through_frames(todo, Path(frames), name, det, progress, say, source, workers)
    _detect(det, [load_scene(p) for p in todo], name, progress, workers)
    say(f"    detections_{name}.hdf5 written into {len(todo)} scenes ({det.fingerprint})")
    return {"fingerprint": det.fingerprint, "written": len(todo)}


def _tables_of(data, name: str, split: str | None, det: LearnedDetector, source: str) -> dict[Path, str | None]:
    """:func:`learned_tables`'s fingerprints of ``data``'s scenes, refusing in one line tables of another detector
    than ``det`` (named ``source``): they are never overwritten."""
    have, kinds = learned_tables(data, name, split)
    if kinds and det.fingerprint != kinds[0]:
        odd = next(p for p, fp in have.items() if fp is not None)
        raise CommandError(
            f"{detections_path(odd, name)} was made by another learned detector ({kinds[0]}) than the one in "
            f"{source} ({det.fingerprint}); it is not overwritten: remove it, or write the "
            f"missing tables with its own detector (tsnav detect)"
        )
    return have


def _detect(det: LearnedDetector, scenes: list, name: str, progress: bool, workers: int) -> None:
    """``det``'s tables into ``scenes`` on one torch thread per scene (``workers`` processes), with a progress bar."""
    bar = tqdm(
        total=sum(s.num_states for s in scenes),
        desc=f"detect {name} ({det.image_size} px)",
        unit="state",
        disable=not progress,
        dynamic_ncols=True,
    )
    try:
        with one_thread():
            write_scene_tables(det, scenes, name, bar, workers)
    finally:
        bar.close()


def _write_through_frames(
    todo: list[Path], frames: Path, name: str, det: LearnedDetector, progress, say, source: str, workers: int
) -> dict:
    """:func:`write_learned_tables` with ``frames``: the scene folders ``todo`` get ``det``'s tables of their twins
    in ``frames``, rescaled."""
    if not todo:
        return {"fingerprint": det.fingerprint, "written": 0}
    pairs = frame_twins(todo, frames, str(frames))
    for _, q, _, side in pairs:
        if side != det.image_size:
            raise CommandError(f"{q}: its frames are {side} px, {source} reads {det.image_size}-px frames")
    made = {q: read_fingerprint(q, name) for _, q, _, _ in pairs}
    stale = [q for q, fp in made.items() if fp not in (None, det.fingerprint)]
    if stale:
        raise CommandError(
            f"{detections_path(stale[0], name)} was made by another detector ({made[stale[0]]}) "
            f"than {source} ({det.fingerprint}); it is not overwritten: remove it"
        )
    _detect(det, [load_scene(q) for q, fp in made.items() if fp is None], name, progress, workers)
    for p, q, size, _ in pairs:
        write_rescaled(q, p, name, size)
    say(
        f"    detections_{name}.hdf5 written into {len(pairs)} scenes ({det.fingerprint}, read on "
        f"{det.image_size}-px frames in {frames}, boxes scaled)"
    )
    return {"fingerprint": det.fingerprint, "written": len(pairs)}


def detection_quality(data: str | Path, name: str, split: str = "val", c_target: float = C_TARGET) -> dict:
    """The table ``detections_<name>.hdf5`` measured on the ``split`` rooms: mean presence AP, box AP@0.5, ECE
    (all (state, class) pairs), reach of ``c_target`` (share of (scene, target) pairs with some state above it)
    and false-positive states (a class not in view scoring above 0.5 / 0.7 / 0.9), with the detector's
    fingerprint."""
    paths = list_scenes(data, split=split)
    if not paths:
        raise CommandError(f"{data}: no {split} scene to measure detections_{name}.hdf5 on")
    scenes = [load_scene(p) for p in paths]
    dets = [load_detections(p, name) for p in paths]
    ev = evaluate_detections(scenes, dets)
    sw = switch_report(scenes, dets, c_target)
    fps = sorted({d.fingerprint for d in dets})
    return {
        "name": name,
        "fingerprint": fps[0] if len(fps) == 1 else fps,
        "split": split,
        "scenes": len(scenes),
        "states": ev.states,
        "presence_ap": ev.mean_presence_ap,
        "box_ap50": ev.mean_box_ap,
        "ece": ev.reliability.ece,
        "c_target": c_target,
        "reach": sw.reach,
        "pairs": sw.pairs,
        "reached": sw.reached,
        "reached_in_view": sw.reached_in_view,
        "episode_pairs": sw.episode_pairs,
        "episode_reached": sw.episode_reached,
        "episode_reach": sw.episode_reach,
        "fp_states": {f"{t:g}": v for t, v in sw.fp_state_any.items()},
        "fp_states_targets": {f"{t:g}": v for t, v in sw.fp_state_target.items()},
    }


def record_quality(out: str | Path, data: str | Path, names: list[str], say: Callable[[str], None] = print) -> dict:
    """Measure each table of ``names`` on the val rooms of ``data`` (reusing ``OUT/detector_quality.json``'s
    entry when its fingerprint is unchanged), write the file and print one line per table; returns it."""
    path = Path(out) / QUALITY_FILE
    try:
        old = json.loads(path.read_text()) if path.exists() else {}
    except ValueError:
        old = {}
    doc = {}
    for name in names:
        fps = sorted({read_fingerprint(p, name) for p in list_scenes(data, split="val")} - {None})
        q = old.get(name)
        if not q or q.get("fingerprint") != (fps[0] if len(fps) == 1 else fps):
            q = detection_quality(data, name)
        doc[name] = q
        say(f"    {quality_line(q)}")
    atomic_write_json(path, doc, indent=1)
    return doc
