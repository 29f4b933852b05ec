"""Folds of a world's scenes for cross-fitting: a model trained on every fold but one writes that fold's outputs.

A fold holds whole apartments. RoboTHOR's five variants of an apartment share its walls and plan
(``FloorPlan_Train3_1`` ... ``FloorPlan_Train3_5`` are apartment ``FloorPlan_Train3``), so a detector that trained on
one variant has seen the others' rooms; an iTHOR room (``FloorPlan12``) is its own apartment. The apartments, sorted
by name, are dealt to the folds in turn: apartment ``i`` goes to fold ``i % k``.
"""

from __future__ import annotations

import re
from collections.abc import Iterable

_VARIANT = re.compile(r"^(FloorPlan_\w+?\d+)_\d+$")


def apartment_of(scene: str) -> str:
    """The apartment a scene is a variant of: ``FloorPlan_Train3_2`` -> ``FloorPlan_Train3``; any other name is its
    own apartment."""
    m = _VARIANT.match(scene)
    return m.group(1) if m else scene


def assign_folds(scenes: Iterable[str], k: int) -> dict[str, int]:
    """``{scene: fold}`` for ``k`` folds: the apartments sorted by name and dealt in turn (see the module)."""
    if k < 2:
        raise ValueError(f"cross-fitting needs at least 2 folds, got {k}")
    scenes = list(scenes)
    apartments = sorted({apartment_of(s) for s in scenes})
    if len(apartments) < k:
        raise ValueError(f"{len(apartments)} apartment(s) cannot fill {k} folds")
    fold = {a: i % k for i, a in enumerate(apartments)}
    return {s: fold[apartment_of(s)] for s in scenes}


def parse_fold(text: str) -> tuple[int, int]:
    """``"I/K"`` -> ``(I, K)``: fold ``I`` (0-based) of ``K``; a one-line ``ValueError`` for anything else."""
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", str(text))
    if not m:
        raise ValueError(f"fold {text!r}: give I/K, fold I (counted from 0) of K, e.g. 0/2")
    i, k = int(m.group(1)), int(m.group(2))
    if k < 2:
        raise ValueError(f"fold {text!r}: cross-fitting needs at least 2 folds")
    if i >= k:
        raise ValueError(f"fold {text!r}: the folds of {k} are 0 to {k - 1}")
    return i, k
