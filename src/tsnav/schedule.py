"""The learning-rate schedule of every trainer that has one (pretraining, the detector): linear warm-up, then
a half cosine (MAE's schedule; the agent trains at a constant rate as in the paper)."""

from __future__ import annotations

import math


def warmup_cosine(step: int, total: int, peak: float, warmup: int, floor: float = 0.0) -> float:
    """Learning rate of optimiser step ``step`` (0-based): linear warm-up to ``peak`` over ``warmup`` steps,
    then a half cosine from ``peak`` down to ``floor`` at step ``total`` (and ``floor`` after it)."""
    if step < warmup:
        return peak * (step + 1) / warmup
    t = min((step - warmup) / max(1, total - warmup), 1.0)
    return floor + (peak - floor) * 0.5 * (1.0 + math.cos(math.pi * t))
