"""What both trainers share around their loop: the run's counters resumed from its newest checkpoint, the budget
check that writes the final checkpoint once, and the run's output (log lines, TensorBoard, the tqdm bar over the
unit of its budget)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import torch
from tqdm import tqdm

from .checkpoint import resume_checkpoint
from .config import TrainConfig
from .logger import LogWindow, RunLogger


def new_progress() -> dict:
    """Counters of a run: updates, environment steps and finished episodes over all ranks, training seconds."""
    return {"update": 0, "env_steps": 0, "episodes": 0, "seconds": 0.0, "finished": False}


def resume_progress(
    run_dir: str | Path, model: torch.nn.Module, optimizer: torch.optim.Optimizer, *, aside: bool = True, **counters
) -> tuple[dict, dict | None]:
    """``(progress, state)``: the counters of the newest readable checkpoint of ``run_dir``, whose weights and
    optimizer state are loaded into ``model`` and ``optimizer``, and its ``state.json`` content (with ``rng``);
    for a run without a checkpoint :func:`new_progress` plus ``counters`` and None. ``aside``: a broken newest
    checkpoint is set aside (rank 0 only)."""
    progress = {**new_progress(), **counters}
    found = resume_checkpoint(run_dir, model, optimizer, aside=aside)
    if found is None:
        return progress, None
    progress.update(found[1]["progress"])
    return progress, found[1]


def schedule_lr(cfg: TrainConfig, optimizer: torch.optim.Optimizer, update: int, parts: dict | None = None) -> None:
    """Set the learning rate of the update that follows ``update`` finished updates (:meth:`TrainConfig.lr_at`)
    in every parameter group of ``optimizer``, and record it as ``parts["lr"]`` (a log column). A ``constant``
    schedule leaves the optimizer as it is (the rate it was made with) and adds no column."""
    if cfg.lr_schedule == "constant":
        return
    lr = cfg.lr_at(update)
    for group in optimizer.param_groups:
        group["lr"] = lr
    if parts is not None:
        parts["lr"] = lr


def budget_used(cfg: TrainConfig, progress: dict, final_checkpoint: Callable[[], None]) -> bool:
    """Whether the run's budget is used up, so that there is nothing to train; a run that is not yet marked
    ``finished`` is then marked so and ``final_checkpoint()`` writes it (once: a finished run is not written
    again). Otherwise the run is marked unfinished."""
    if cfg.budget_reached(progress):
        if not progress.get("finished"):
            progress["finished"] = True
            final_checkpoint()
        return True
    progress["finished"] = False
    return False


class ProgressBar:
    """tqdm bar over the unit of the run's budget (episodes, updates or seconds)."""

    def __init__(self, cfg: TrainConfig, progress: dict, enabled: bool):
        b = cfg.budget
        self.key, total, unit = (
            ("episodes", b["episodes"], "ep")
            if "episodes" in b
            else ("update", b["updates"], "upd")
            if "updates" in b
            else ("seconds", int(60 * b["minutes"]), "s")
        )
        self.bar = tqdm(
            total=total,
            initial=int(progress[self.key]),
            unit=unit,
            disable=not enabled,
            dynamic_ncols=True,
            desc=f"train {cfg.algo}",
        )

    def update(self, progress: dict, postfix: dict | None = None) -> None:
        self.bar.update(max(0, int(progress[self.key]) - self.bar.n))
        if postfix:
            self.bar.set_postfix(postfix, refresh=False)

    def close(self) -> None:
        self.bar.close()


class RunOutput:
    """A run's output from ``progress`` on: the updates gathered since the last log line (``window``), the log
    (``log.jsonl`` and TensorBoard, lines after ``progress`` dropped) and the bar. ``main=False`` (ranks other
    than 0) writes nothing."""

    def __init__(
        self, run_dir: str | Path, cfg: TrainConfig, progress: dict, *, main: bool = True, progress_bar: bool = True
    ):
        self.logger = RunLogger(run_dir, progress["update"], enabled=main)
        self.bar = ProgressBar(cfg, progress, enabled=progress_bar and main)
        self.window = LogWindow(progress["env_steps"], cfg.protocol)

    def show(self, progress: dict, log: bool) -> None:
        """Move the bar to ``progress``; with ``log``, first write the window's record (and show its SR and
        return on the bar)."""
        if log:
            record = self.window.record(progress)
            self.logger.log(record)
            self.bar.update(progress, {k: f"{record[k]:.3g}" for k in ("SR", "return") if k in record})
        else:
            self.bar.update(progress)

    def close(self) -> None:
        self.bar.close()
        self.logger.close()
