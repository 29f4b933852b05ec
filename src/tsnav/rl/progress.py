"""Progress of a training run: its counters and the tqdm bar over the unit of its budget (both trainers)."""

from __future__ import annotations

from tqdm import tqdm

from .config import TrainConfig


def new_progress() -> dict:
    """Counters of a run: updates, environment steps and finished episodes over all ranks, training seconds."""
    return {"update": 0, "env_steps": 0, "episodes": 0, "seconds": 0.0, "finished": False}


class ProgressBar:
    """tqdm bar over the unit of the run's budget (episodes, updates or seconds)."""

    def __init__(self, cfg: TrainConfig, progress: dict, enabled: bool):
        b = cfg.budget
        self.key, total, unit = (("episodes", b["episodes"], "ep") if "episodes" in b else
                                 ("update", b["updates"], "upd") if "updates" in b else
                                 ("seconds", int(60 * b["minutes"]), "s"))
        self.bar = tqdm(total=total, initial=int(progress[self.key]), unit=unit, disable=not enabled,
                        dynamic_ncols=True, desc=f"train {cfg.algo}")

    def update(self, progress: dict, postfix: dict | None = None) -> None:
        self.bar.update(max(0, int(progress[self.key]) - self.bar.n))
        if postfix:
            self.bar.set_postfix(postfix, refresh=False)

    def close(self) -> None:
        self.bar.close()
