"""``tsnav thor export-lineage``: write every file the lineage's trainer and evaluator read into a tsnav dataset.

The lineage's code (IOM's ``main.py`` trainer and ``full_eval.py`` evaluator, and the VTNet / DOA / DAT
code it derives from) reads, per scene folder, besides ``graph.json``, ``grid.json`` and
``visible_object_map_1.5.json`` (which tsnav scene folders already hold):

* ``resnet18_featuremap.hdf5``: one float32 ``(1, 512, 7, 7)`` dataset per state key, the last feature map
  of a ResNet18 on the 224 x 224 frame (:func:`tsnav.pretrain.features.write_resnet_features`, from a tsnav ResNet18 encoder:
  ``tsnav pretrain --method resnet18-sup`` run, ``resnet18:PATH`` torchvision-layout weights, or
  ``untrained:resnet18``; frames are resized to 224 as ``tsnav features`` does);
* ``detr_features_22cls.hdf5``: the 22 x 264 table (:func:`tsnav.data.lineage.table_to_22x264`) from a tsnav
  detection table ``detections_<name>.hdf5`` (tsnav's 64-d features zero-padded to 256, boxes in 300 px);
* ``optimal_action.json``: ``{state key: {target type: action id}}``, a first action of a shortest path to
  a success state of the target (Done, 5, where the state already succeeds), from the BFS distance fields
  (:func:`tsnav.sim.lineage.optimal_actions`);

and, beside the scene folders, the episode lists ``test_val_split/{room}_{test,val}_22.pkl``
(:mod:`tsnav.data.lineage_splits`, :func:`tsnav.sim.lineage.write_splits`), drawn by
:func:`tsnav.sim.episodes.make_episodes` from the dataset's test and val scenes.

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
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from ..atomic import atomic_write_text
from ..data import lineage as L
from ..data.detections import detections_path
from ..data.reader import SceneFormatError, list_scenes, load_scene
from ..data.thor_export import export_detections_22x264
from ..pretrain.features import write_resnet_features
from ..sim.lineage import LINEAGE_SUCCESS_DISTANCE, optimal_actions, write_splits


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


def export_lineage(
    root: str | Path,
    encoder,
    detections: str | None,
    success_distance: float = LINEAGE_SUCCESS_DISTANCE,
    per_room_type: int = 1000,
    seed: int = 0,
    batch_size: int = 16,
    overwrite: bool = False,
    splits: bool = True,
    progress: bool = True,
) -> LineageExportStats:
    """Write the lineage's files into every complete scene folder of ``root`` and its episode lists (module doc).

    ``encoder``: a ResNet18 :class:`tsnav.pretrain.features.Encoder` (None: no ``resnet18_featuremap.hdf5``);
    ``detections``: the name of a detection table present in every scene (None: no DETR table). Raises
    :class:`SceneFormatError` / ``ValueError`` with one line for a missing table, images or wrong encoder.
    """
    root = Path(root)
    dirs = list_scenes(root)
    if not dirs:
        raise SceneFormatError(f"{root}: no complete scene folder")
    if detections is not None:
        missing = [d.name for d in dirs if not detections_path(d, detections).exists()]
        if missing:
            raise SceneFormatError(
                f"{root}: scene {missing[0]} has no detections_{detections}.hdf5 "
                f"(run `tsnav detect --name {detections}` first)"
            )
    if encoder is not None:
        no_img = [d.name for d in dirs if not (d / L.IMAGES_FILE).exists()]
        if no_img:
            raise SceneFormatError(f"{root}: scene {no_img[0]} has no images.hdf5 (build the world with images)")
    stats = LineageExportStats(scenes=len(dirs))
    scenes = [load_scene(d) for d in dirs]
    stats.states = sum(s.num_states for s in scenes)
    stats.image_sizes = sorted({int(s.image_size) for s in scenes})
    bar = tqdm(
        total=stats.states if encoder is not None else 0,
        desc="resnet18 features",
        unit="img",
        disable=not progress or encoder is None,
        dynamic_ncols=True,
    )
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
            atomic_write_text(path, json.dumps(optimal_actions(scene, success_distance), separators=(",", ":")))
            stats.optimal_written += 1
    finally:
        bar.close()
    if splits:
        stats.split_files = write_splits(root, success_distance, per_room_type, seed)
    return stats
