"""The detectors that ship inside the package: :class:`~tsnav.detect.learned.LearnedDetector` checkpoints trained
here on the 80 training rooms of the ``ithor-real`` world at 128x128 and calibrated on its 20 validation rooms, and
six trained on the 60 training apartments of the ``robothor-real`` world (``robothor1`` to
``robothor5`` at 128x128, ``robothor5hr`` at 256x256; the 12 classes of ``robothor12``).

The paper's stage switch reads a DETR that was trained before, and apart from, the navigation agent; the
shipped weights play that part for the 128-px real rooms, so that a short job (``tsnav demo``) can use a
detector that took two to three hours of one CPU core to train. Nothing is downloaded. Ten are kept (1.9 MB of
float32 each, 6.8 MB for the wider ``learned7``) with their checkpoint JSON (training configuration and rooms,
temperature, fingerprint, provenance):

* ``learned4`` (the default, ``weights/ithor-real-128``): presence AP 0.743 on the val rooms, 90.4 % of val
  (scene, target) pairs reach C_target = 0.7 (BENCHMARKS.md);
* ``learned6`` (``weights/ithor-real-128-learned6``): ``learned4`` fine-tuned 2,000 steps with the classes in view
  weighted 4x in the presence loss; it ranks like ``learned4`` at a lower threshold (more targets in view pass
  C_target, and ten times the false positives: 3 % of absent target cells above 0.7 on the test rooms against
  0.3 %); agents trained on its tables score higher under ``lineage`` (docs/RESULTS.md);
* ``learned7`` (``weights/ithor-real-128-learned7``): a backbone twice as wide (64, 128, 256 channels) trained from
  nothing for 18,000 steps with ``learned6``'s loss; val presence AP 0.820, every val (scene, target) pair reaches
  C_target; at equal false positives about 4 points more of the targets in view pass 0.7 than with ``learned6``
  (docs/RESULTS.md); four times the compute per frame;
* ``learned3`` (``weights/ithor-real-128-learned3``): AP 0.713, reach 87.2 %; the tables of the medium-scale
  experiments of docs/RESULTS.md are its tables (``tsnav detect --detector shipped --shipped learned3``
  writes them again);
* ``robothor1`` (``weights/robothor-real-128-robothor1``): the first RoboTHOR detector (the shipped RoboTHOR agent's
  until ``robothor2``), the 12 challenge target types (class set ``robothor12``), ``learned6``'s architecture and
  loss, trained from nothing on the 60 training apartments' frames at 128x128 (its ``provenance`` names the command
  and the steps); not calibrated (temperature 1): the val apartments are the benchmark, so nothing is fitted on them. Val presence AP
  0.414 (0.85 GarbageCan, 0.76 Television, under 0.2 for BasketBall, SprayBottle, Vase;
  docs/results/robothor1_val_eval_2026-12-06.json);
* ``robothor2`` (``weights/robothor-real-128-robothor2``): the detector of the shipped RoboTHOR agent:
  ``robothor1`` trained on to 15,000 steps with class-balanced sampling (repeat threshold 0.5, as ``learned7``) on
  the same train apartments' frames, not calibrated. Val presence AP 0.621 against ``robothor1``'s 0.414
  (AlarmClock 0.90, Bowl 0.75, Apple 0.62; under 0.35 for SprayBottle, BasketBall, Vase;
  docs/results/robothor2_val_eval_2026-12-06.json).
* ``robothor3`` (``weights/robothor-real-128-robothor3``): ``robothor2`` trained on to 20,000 steps on the train
  apartments rebuilt the val way (``tsnav world --infer-train-objects``: furniture from the plans, targets inferred
  from the challenge's train episodes, as the val apartments are built), same architecture, loss and sampling; not
  calibrated. Val presence AP 0.780 against ``robothor2``'s 0.639 in the same val apartments (rules v2; box AP@0.5
  0.557 against 0.374; docs/results/robothor3_val_eval_2026-12-06.json, robothor2_val_v2_eval_2026-12-06.json).
* ``robothor4`` (``weights/robothor-real-128-robothor4``): ``robothor3`` trained on to 25,000 steps in the same
  apartments, same settings; not calibrated. Val presence AP 0.802, box AP@0.5 0.586 (docs/results/
  robothor4_val_eval_2026-12-07.json): a gain within the val episodes' noise for the agent, docs/RESULTS.md.
* ``robothor5`` (``weights/robothor-real-128-robothor5``): ``robothor4``'s 5,000 steps from ``robothor3``, in the
  same apartments with their floor and wall materials redrawn per scene (``tsnav world --seed 1``); not calibrated.
  Val presence AP 0.849, box AP@0.5 0.630 (docs/results/robothor5_val_eval_2026-12-07.json), and a third of
  ``robothor4``'s boxes on targets out of view. The detector of ``tsrm-demae-robothor-paper-protocol`` until
  ``robothor5hr``'s agent replaced it, docs/RESULTS.md.
* ``robothor5hr`` (``weights/robothor-real-256-robothor5hr``): ``robothor5`` trained on to 30,000 steps on the
  256-px frames of the same apartments (``tsnav world --size 256``: the same states), its weights carried over
  (``tsnav detect --retarget``); not calibrated. It reads 256-px frames: a 128-px world's tables are written through
  a build of the same rooms at 256 px (``tsnav detect --detector shipped --shipped robothor5hr --frames DIR256``;
  ``tsnav release eval`` builds it), the boxes scaled to the world's frames. Val presence AP 0.928, box AP@0.5 0.770,
  SprayBottle's presence AP 0.644 against ``robothor5``'s 0.337 (docs/results/robothor5hr_val_eval_2026-12-07.json).
  The detector of ``tsrm-demae-robothor-paper-protocol``, in training (its tables of the redrawn train apartments)
  and evaluation, docs/RESULTS.md.

Their tables carry the same fingerprint as the ones written by ``tsnav detect --checkpoint`` with the same
weights, so tables written from a shipped copy and from the training folder are interchangeable.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import CommandError
from .learned import LearnedDetector
from .train import read_meta

_WEIGHTS = Path(__file__).parent / "weights"
#: Shipped checkpoint folders (``model.safetensors`` and ``state.json``) by name.
SHIPPED = {
    "learned4": _WEIGHTS / "ithor-real-128",
    "learned3": _WEIGHTS / "ithor-real-128-learned3",
    "learned6": _WEIGHTS / "ithor-real-128-learned6",
    "learned7": _WEIGHTS / "ithor-real-128-learned7",
    "robothor1": _WEIGHTS / "robothor-real-128-robothor1",
    "robothor2": _WEIGHTS / "robothor-real-128-robothor2",
    "robothor3": _WEIGHTS / "robothor-real-128-robothor3",
    "robothor4": _WEIGHTS / "robothor-real-128-robothor4",
    "robothor5": _WEIGHTS / "robothor-real-128-robothor5",
    "robothor5hr": _WEIGHTS / "robothor-real-256-robothor5hr",
}
#: The one used unless another is named.
DEFAULT_SHIPPED = "learned4"
#: The default's folder.
SHIPPED_DIR = SHIPPED[DEFAULT_SHIPPED]


def shipped_for(table: str) -> str:
    """The shipped detector whose tables are named ``table``: the shipped detector of that name when there is one
    (``detections_learned7.hdf5`` is ``learned7``'s), else :data:`DEFAULT_SHIPPED`. ``tsnav detect --detector
    shipped`` without ``--shipped`` and ``tsnav experiment --detector shipped`` write and accept tables by it."""
    return table if table in SHIPPED else DEFAULT_SHIPPED


def _folder(name: str | None) -> Path:
    name = name or DEFAULT_SHIPPED
    if name not in SHIPPED:
        raise CommandError(f"no shipped detector named {name!r} (choose from {', '.join(SHIPPED)})")
    return SHIPPED[name]


def shipped_meta(name: str | None = None) -> dict:
    """The JSON of the shipped checkpoint ``name`` (default :data:`DEFAULT_SHIPPED`): step, temperature, training
    rooms, provenance."""
    return read_meta(_folder(name), pinned=True)


def shipped_side(name: str | None = None) -> int:
    """The side of the frames the shipped detector ``name`` reads (its checkpoint's ``model.image_size``): the
    world's frames, or finer ones for a detector trained with ``tsnav detect --frames``."""
    return int(shipped_meta(name)["model"]["image_size"])


def shipped_detector(image_size: int | None = None, name: str | None = None) -> LearnedDetector:
    """Load the shipped detector ``name`` (default :data:`DEFAULT_SHIPPED`); its weights are checked against the
    fingerprint recorded beside them.

    ``image_size``: the frames of the world it will read; a world of another size gets a one-line
    :class:`CommandError` (the detector reads 128x128 frames only)."""
    folder = _folder(name)
    det = LearnedDetector.load(folder, pinned=True)  # the shipped files, never what was trained on from them
    want = det.meta.get("fingerprint")
    if det.fingerprint != want:
        raise CommandError(
            f"{folder}: the shipped detector's weights do not match their recorded fingerprint "
            f"({det.fingerprint} != {want}); reinstall tsnav"
        )
    if image_size is not None and image_size != det.image_size:
        raise CommandError(
            f"the shipped detector {name or DEFAULT_SHIPPED} reads {det.image_size}x{det.image_size} frames (those "
            f"of the world it was trained on), this world has {image_size}x{image_size}: "
            + (
                f"give it the same rooms built at {det.image_size} px (tsnav detect --frames DIR)"
                if det.image_size > image_size
                else "train a detector on it instead (--detector train in tsnav demo and tsnav experiment, "
                "--detector learned in tsnav detect)"
            )
        )
    return det
