"""``tsnav thor export-lineage``: write every file the lineage's trainer and evaluator read into a tsnav dataset.

The lineage's code (IOM's ``main.py`` trainer and ``full_eval.py`` evaluator, and the VTNet / DOA / DAT
code it derives from) reads, per scene folder, besides ``graph.json``, ``grid.json`` and
``visible_object_map_1.5.json`` (which tsnav scene folders already hold):

* ``resnet18_featuremap.hdf5``: one float32 ``(1, 512, 7, 7)`` dataset per state key, the last feature map
  of a ResNet18 on the 224 x 224 frame (:func:`write_resnet_features`, from a tsnav ResNet18 encoder:
  ``tsnav pretrain --method resnet18-sup`` run, ``resnet18:PATH`` torchvision-layout weights, or
  ``untrained:resnet18``; frames are resized to 224 as ``tsnav features`` does);
* ``detr_features_22cls.hdf5``: the 22 x 264 table (:func:`tsnav.data.lineage.table_to_22x264`) from a tsnav
  detection table ``detections_<name>.hdf5`` (tsnav's 64-d features zero-padded to 256, boxes in 300 px);
* ``optimal_action.json``: ``{state key: {target type: action id}}``, a first action of a shortest path to
  a success state of the target (Done, 5, where the state already succeeds), from the BFS distance fields
  (:func:`optimal_actions`);

and, beside the scene folders, the episode lists ``test_val_split/{room}_{test,val}_22.pkl``
(:mod:`tsnav.data.lineage_splits`), drawn by :func:`tsnav.sim.episodes.make_episodes` from the dataset's
test and val scenes.

Success radius: optimal actions and episode lists are made for ``success_distance`` (default 1.5 m, the
lineage's visibility-map rule, so that the lineage's evaluator and its optimal actions agree with the
lists); pass 1.0 for the paper's rule. The radius is written in ``test_val_split/tsnav_split_info.json``,
for the lists and the optimal actions alike.

Every file is written to a temporary name and renamed when complete. A rerun skips the ResNet features
already made by the same encoder (the slow part) unless ``overwrite``; the other files are quick and are
written again.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..constants import ACTION_ORDER, DONE, NUM_CATEGORIES, TARGET_CATEGORIES
from . import lineage as L
from . import lineage_splits as LS
from .reader import SceneFormatError

#: Success radius of the lineage's evaluator (its visibility map), the default of the export.
LINEAGE_SUCCESS_DISTANCE = 1.5


@dataclass
class LineageExportStats:
    """What :func:`export_lineage` wrote."""

    scenes: int = 0
    states: int = 0
    resnet_written: int = 0
    detections_written: int = 0
    optimal_written: int = 0
    image_sizes: list = field(default_factory=list)
    split_files: dict = field(default_factory=dict)
    """file name -> number of episodes."""


def _tmp(path: Path) -> Path:
    return path.with_name(f".{path.name}.partial-{os.getpid()}")


def _h5_attr(path: Path, name: str):
    import h5py

    try:
        with h5py.File(path, "r") as f:
            v = f.attrs.get(name)
    except OSError:
        return None
    return v.decode() if isinstance(v, bytes) else v


def write_resnet_features(scene_dir: str | Path, encoder, keys, batch_size: int = 16, bar=None,
                          overwrite: bool = False) -> bool:
    """Write ``resnet18_featuremap.hdf5``: float32 ``(1, 512, 7, 7)`` per state key (see the module doc).

    ``encoder``: a :class:`tsnav.pretrain.features.Encoder` of arch ``resnet18`` with input size 224.
    Returns False when the file exists and was made by the same encoder (fingerprint) and ``overwrite`` is
    off; raises ``ValueError`` for another encoder's file without ``overwrite``.
    """
    import h5py

    from ..pretrain.features import iter_scene_features

    if encoder.arch != "resnet18" or encoder.img_size != L.RESNET_INPUT_SIZE:
        raise ValueError(f"the lineage's {L.RESNET_FILE} holds ResNet18 maps of {L.RESNET_INPUT_SIZE}px frames; "
                         f"encoder {encoder.spec} is {encoder.arch} at {encoder.img_size}px")
    scene_dir = Path(scene_dir)
    out = scene_dir / L.RESNET_FILE
    if out.exists() and not overwrite:
        fp = _h5_attr(out, "fingerprint")
        if fp == encoder.fingerprint:
            return False
        raise ValueError(f"{out} exists and was made by another encoder ({fp}); pass --overwrite to replace it")
    tmp = _tmp(out)
    try:
        with h5py.File(tmp, "w") as f:
            for a, feats in iter_scene_features(encoder, scene_dir, keys, batch_size):
                if feats.shape[1:] != L.RESNET_SHAPE[1:]:
                    raise ValueError(f"encoder {encoder.spec} gives {feats.shape[1:]} maps, expected {L.RESNET_SHAPE[1:]}")
                for k, x in zip(keys[a:a + len(feats)], feats):
                    f.create_dataset(str(k), data=x[None].astype(np.float32), track_times=False)
                if bar is not None:
                    bar.update(len(feats))
            f.attrs["encoder"] = encoder.spec
            f.attrs["fingerprint"] = encoder.fingerprint
            f.attrs["input_size"] = L.RESNET_INPUT_SIZE
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            tmp.unlink()
    return True


def optimal_actions(scene, success_distance: float = LINEAGE_SUCCESS_DISTANCE) -> dict[str, dict[str, int]]:
    """``{state key: {target type: action id}}`` of ``optimal_action.json`` for every target category with a
    success state in ``scene``: :func:`tsnav.sim.paths.optimal_action_targets` on the BFS distance fields
    (the lowest action id among those one step closer; Done where the state succeeds). States that cannot
    reach a target's success states have no entry for it. Action ids in ``constants.ACTIONS`` order, which
    is the lineage's."""
    from ..sim.paths import UNREACHABLE, optimal_action_targets, scene_distance_fields

    dist = scene_distance_fields(scene, success_distance)
    S = scene.num_states
    out: dict[str, dict[str, int]] = {str(k): {} for k in scene.keys}
    for c in np.flatnonzero((dist == 0).any(axis=0)):
        states = np.flatnonzero(dist[:, c] < UNREACHABLE)
        act = optimal_action_targets(scene.next_state, dist, states, np.full(len(states), c), done_action=DONE)
        name = TARGET_CATEGORIES[int(c)]
        for s, a in zip(states.tolist(), act.tolist()):
            out[str(scene.keys[s])][name] = int(a)
    assert len(out) == S
    return out


def optimal_actions_reference(scene, success_distance: float = LINEAGE_SUCCESS_DISTANCE) -> dict[str, dict[str, int]]:
    """Slow reference for :func:`optimal_actions`: per state and category, a Python loop over the actions
    comparing the successors' BFS distances (:func:`tsnav.sim.paths.bfs_reference`)."""
    from ..sim.paths import UNREACHABLE, bfs_reference

    success = scene.category_visible_within(success_distance)
    out: dict[str, dict[str, int]] = {str(k): {} for k in scene.keys}
    for c in range(NUM_CATEGORIES):
        if not success[:, c].any():
            continue
        d = bfs_reference(scene.next_state, success[:, c])
        for s in range(scene.num_states):
            if d[s] == UNREACHABLE:
                continue
            if d[s] == 0:
                a = DONE
            else:
                a = next(a for a in range(DONE) if d[scene.next_state[s, a]] == d[s] - 1)
            out[str(scene.keys[s])][TARGET_CATEGORIES[c]] = a
    return out


def _write_json_atomic(path: Path, obj) -> None:
    tmp = _tmp(path)
    try:
        with open(tmp, "w") as f:
            json.dump(obj, f, separators=(",", ":"))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_splits(root: str | Path, success_distance: float = LINEAGE_SUCCESS_DISTANCE, per_room_type: int = 1000,
                 seed: int = 0) -> dict[str, int]:
    """Write ``root/test_val_split/{room}_{split}_22.pkl`` for the test and val scenes of ``root`` and the info
    file naming ``success_distance``; returns file name -> episodes. Room types without a valid episode in
    a split get no file."""
    from ..sim.batch import SceneBank
    from ..sim.episodes import make_episodes
    from .reader import list_scenes, load_scene

    folder = Path(root) / L.SPLIT_DIR
    written: dict[str, int] = {}
    for split in LS.SPLIT_NAMES:
        dirs = list_scenes(root, split=split)
        if not dirs:
            continue
        bank = SceneBank([load_scene(d) for d in dirs], success_distance=success_distance)
        eps = make_episodes(bank, per_room_type, seed)
        for room in LS.SPLIT_ROOMS:
            mine = [e for e in eps if e.room_type == room]
            if not mine:
                continue
            name = LS.split_file_name(room, split)
            LS.write_split(folder / name, LS.split_records(bank, mine))
            written[name] = len(mine)
    if written:
        rule = ("the lineage's: the target in its visibility map (in view within 1.5 m)" if success_distance == 1.5
                else f"in view and within {success_distance} m of the agent on the floor plane (the paper's rule at 1.0 m)")
        LS.write_split_info(folder, {
            "format": "tsnav-lineage-splits", "success_distance": success_distance, "success_rule": rule,
            "per_room_type": per_room_type, "seed": seed, "action_order": ACTION_ORDER,
            "start_horizons": "0 or 30, each with probability 1/2 per (scene, target) pair", "files": written,
            "note": "optimal_action.json in every scene folder was made for the same success distance"})
    return written


def export_lineage(root: str | Path, encoder, detections: str | None, success_distance: float = LINEAGE_SUCCESS_DISTANCE,
                   per_room_type: int = 1000, seed: int = 0, batch_size: int = 16, overwrite: bool = False,
                   splits: bool = True, progress: bool = True) -> LineageExportStats:
    """Write the lineage's files into every complete scene folder of ``root`` and its episode lists (module doc).

    ``encoder``: a ResNet18 :class:`tsnav.pretrain.features.Encoder` (None: no ``resnet18_featuremap.hdf5``);
    ``detections``: the name of a detection table present in every scene (None: no DETR table). Raises
    :class:`SceneFormatError` / ``ValueError`` with one line for a missing table, images or wrong encoder.
    """
    from tqdm import tqdm

    from ..detect.table import detections_path
    from .reader import list_scenes, load_scene
    from .thor_export import export_detections_22x264

    root = Path(root)
    dirs = list_scenes(root)
    if not dirs:
        raise SceneFormatError(f"{root}: no complete scene folder")
    if detections is not None:
        missing = [d.name for d in dirs if not detections_path(d, detections).exists()]
        if missing:
            raise SceneFormatError(f"{root}: scene {missing[0]} has no detections_{detections}.hdf5 "
                                   f"(run `tsnav detect --name {detections}` first)")
    if encoder is not None:
        no_img = [d.name for d in dirs if not (d / L.IMAGES_FILE).exists()]
        if no_img:
            raise SceneFormatError(f"{root}: scene {no_img[0]} has no images.hdf5 (build the world with images)")
    stats = LineageExportStats(scenes=len(dirs))
    scenes = [load_scene(d) for d in dirs]
    stats.states = sum(s.num_states for s in scenes)
    stats.image_sizes = sorted({int(s.image_size) for s in scenes})
    bar = tqdm(total=stats.states if encoder is not None else 0, desc="resnet18 features", unit="img",
               disable=not progress or encoder is None, dynamic_ncols=True)
    try:
        for d, scene in zip(dirs, scenes):
            if encoder is not None:
                if write_resnet_features(d, encoder, scene.keys, batch_size, bar, overwrite):
                    stats.resnet_written += 1
                else:
                    bar.update(scene.num_states)
            if detections is not None:
                export_detections_22x264(d, detections_path(d, detections), d / L.DETECTION_FILES[0])
                stats.detections_written += 1
            path = d / L.OPTIMAL_ACTION_FILE
            _write_json_atomic(path, optimal_actions(scene, success_distance))
            stats.optimal_written += 1
    finally:
        bar.close()
    if splits:
        stats.split_files = write_splits(root, success_distance, per_room_type, seed)
    return stats
