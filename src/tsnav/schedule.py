"""The learning-rate schedules of the trainers that have one: linear warm-up, then a half cosine (pretraining and
the detector, MAE's schedule); a linear decay (the agent's ``TrainConfig.lr_schedule``, off by default: the agent
trains at a constant rate as in the paper)."""

from __future__ import annotations

import math


def warmup_cosine(step: int, total: int, peak: float, warmup: int, floor: float = 0.0) -> float:
    """Learning rate of optimiser step ``step`` (0-based): linear warm-up to ``peak`` over ``warmup`` steps,
    then a half cosine from ``peak`` down to ``floor`` at step ``total`` (and ``floor`` after it)."""
    if step < warmup:
        return peak * (step + 1) / warmup
    t = min((step - warmup) / max(1, total - warmup), 1.0)
    return floor + (peak - floor) * 0.5 * (1.0 + math.cos(math.pi * t))


def linear_decay(step: int, total: int, start: float, end: float) -> float:
    """Learning rate of optimiser step ``step`` (0-based): ``start`` at step 0, falling linearly to ``end`` at step
    ``total`` (and ``end`` after it)."""
    t = min(step / max(1, total), 1.0)
    return (1.0 - t) * start + t * end  # exactly start at step 0 and end from step total on
