"""The detector that ships inside the package: a :class:`~tsnav.detect.learned.LearnedDetector` trained here on the
80 training rooms of the ``ithor-real`` world at 128x128 and calibrated on its 20 validation rooms.

The paper's stage switch reads a DETR that was trained before, and apart from, the navigation agent; the
shipped weights play that part for the 128-px real rooms, so that a short job (``tsnav demo``) can use a
detector that took about two hours of one CPU core to train. They are the weights of the detector measured in
BENCHMARKS.md (``learned3``: presence AP 0.713 on the val rooms, 87 % of val (scene, target) pairs reach
C_target = 0.7), 1.9 MB of float32 in ``weights/ithor-real-128`` with their checkpoint JSON (training
configuration, training rooms, temperature, fingerprint). Nothing is downloaded.

Its tables carry the same fingerprint as the ones written by ``tsnav detect --checkpoint`` with the same
weights, so tables written from the shipped copy and from the training folder are interchangeable.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import CommandError
from .learned import LearnedDetector
from .train import read_meta

#: The shipped checkpoint folder (``model.safetensors`` and ``state.json``).
SHIPPED_DIR = Path(__file__).parent / "weights" / "ithor-real-128"


def shipped_meta() -> dict:
    """The shipped checkpoint's JSON (step, temperature, training rooms, provenance)."""
    return read_meta(SHIPPED_DIR)


def shipped_detector(image_size: int | None = None) -> LearnedDetector:
    """Load the shipped detector; its weights are checked against the fingerprint recorded beside them.

    ``image_size``: the frames of the world it will read; a world of another size gets a one-line
    :class:`CommandError` (the detector reads 128x128 frames only)."""
    det = LearnedDetector.load(SHIPPED_DIR)
    want = det.meta.get("fingerprint")
    if det.fingerprint != want:
        raise CommandError(f"{SHIPPED_DIR}: the shipped detector's weights do not match their recorded fingerprint "
                           f"({det.fingerprint} != {want}); reinstall tsnav")
    if image_size is not None and image_size != det.image_size:
        raise CommandError(f"the shipped detector reads {det.image_size}x{det.image_size} frames (the ithor-real "
                           f"rooms), this world has {image_size}x{image_size}: train a detector on it instead "
                           f"(--detector train in tsnav demo and tsnav experiment, --detector learned in tsnav "
                           f"detect)")
    return det
