"""Training logs: JSON Lines (``log.jsonl``) and TensorBoard (``tb/``), both resumable.

On resume, log lines written after the checkpoint being resumed (their ``update`` is larger) are dropped, and
TensorBoard purges the same steps, so a resumed run's logs read like an uninterrupted one's.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

from ..atomic import atomic_write_bytes
from ..metrics import METRICS
from .stats import concat, summarize


#: TensorBoard group of each key (cleanrl-style tags: charts/..., losses/..., reward/..., metrics/...); every
#: metric of :data:`tsnav.metrics.METRICS` goes to ``metrics/`` (:func:`tag_group`).
_GROUPS = {
    "loss": "losses",
    "policy_loss": "losses",
    "value_loss": "losses",
    "entropy": "losses",
    "grad_norm": "losses",
}


def tag_group(key: str) -> str:
    """TensorBoard group of a log key: ``reward``, ``losses``, ``metrics`` (a registered metric) or ``charts``."""
    if key.startswith("reward/") or key == "return":
        return "reward"
    return "metrics" if key in METRICS else _GROUPS.get(key, "charts")


class RunLogger:
    """Appends one record per log interval; ``enabled=False`` (non-zero ranks) makes it a no-op."""

    def __init__(self, run_dir: str | Path, resume_update: int = 0, enabled: bool = True, tensorboard: bool = True):
        self.enabled = enabled
        self.path = Path(run_dir) / "log.jsonl"
        self.tb = None
        if not enabled:
            return
        if self.path.exists():
            keep = []
            for line in self.path.read_text().splitlines():
                try:
                    if json.loads(line).get("update", 0) <= resume_update:
                        keep.append(line)
                except json.JSONDecodeError:
                    break  # a torn last line from a kill
            atomic_write_bytes(self.path, "".join(k + "\n" for k in keep).encode())
        if tensorboard:
            # lazy: torch.utils.tensorboard takes about 2.3 s to import (`python -X importtime`); only logging runs need it
            from torch.utils.tensorboard import SummaryWriter

            self.tb = SummaryWriter(str(Path(run_dir) / "tb"), purge_step=resume_update + 1 if resume_update else None)

    def log(self, record: dict) -> None:
        """Write ``record`` (must hold ``update`` and ``env_steps``); numbers go to TensorBoard under their group."""
        if not self.enabled:
            return
        clean = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in record.items()}
        with open(self.path, "a") as f:
            f.write(json.dumps(clean, sort_keys=True) + "\n")
        if self.tb is not None:
            step = int(record["env_steps"])
            for k, v in record.items():
                if isinstance(v, (int, float)) and not isinstance(v, bool) and k not in ("update", "env_steps"):
                    tag = f"{tag_group(k)}/{k.split('/', 1)[-1]}"
                    self.tb.add_scalar(tag, v, step)
            self.tb.flush()

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()
            self.tb = None


def read_log(run_dir: str | Path) -> list[dict]:
    """The records of a run's ``log.jsonl`` (a torn last line is skipped)."""
    p = Path(run_dir) / "log.jsonl"
    out = []
    if p.exists():
        for line in p.read_text().splitlines():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                break
    return out


class LogWindow:
    """Losses and finished episodes gathered between two log lines, turned into one record."""

    def __init__(self, env_steps: int, protocol: str = "paper"):
        self.protocol = protocol
        """Success protocol of the run: SPL and its lengths as :func:`tsnav.metrics.metric_values` counts them."""
        self.t = time.perf_counter()
        self.steps = env_steps
        self.parts: list[dict] = []
        self.episodes: list[dict] = []
        self.cpu_s = 0.0

    def add(self, parts: dict, episodes: dict, cpu_s: float = 0.0) -> None:
        """One update's loss parts, finished episodes and CPU seconds (summed over every process)."""
        self.parts.append(parts)
        self.episodes.append(episodes)
        self.cpu_s += cpu_s

    def __bool__(self) -> bool:
        return bool(self.parts)

    def record(self, progress: dict) -> dict:
        """Progress counters, mean loss parts, episode statistics (:func:`tsnav.rl.stats.summarize`) and
        environment steps per second (and per CPU-second, when given) over the window; starts a new window."""
        now = time.perf_counter()
        rec = {k: progress[k] for k in ("update", "env_steps", "episodes", "seconds")}
        for k in self.parts[0] if self.parts else ():
            rec[k] = sum(p[k] for p in self.parts) / len(self.parts)
        rec["steps_per_s"] = (progress["env_steps"] - self.steps) / max(now - self.t, 1e-9)
        if self.cpu_s > 0:  # steps per CPU-second of all processes: the throughput on an idle core each
            rec["steps_per_cpu_s"] = (progress["env_steps"] - self.steps) / self.cpu_s
        rec.update(summarize(concat(self.episodes), self.protocol))
        self.t, self.steps, self.parts, self.episodes, self.cpu_s = now, progress["env_steps"], [], [], 0.0
        return rec
