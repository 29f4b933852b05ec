"""The paper's evaluation metrics over episode records (paper IV-A, "Evaluation Metrics").

With ``K`` episodes, ``Suc_i`` success, ``Nav_i`` "entered the pathfinding stage", ``K_Nav = sum Nav_i``:

* SR    = 1/K     sum Suc_i
* SPL   = 1/K     sum Suc_i       L*_i / max(L_i, L*_i)                          (Anderson et al. 2018)
* SSR   = 1/K     sum Nav_i
* SSSPL = 1/K     sum Nav_i       L*Search_i / max(LSearch_i, L*Search_i)
* NSNPL = 1/K_Nav sum Suc_i Nav_i L*Nav_i / max(LNav_i, L*Nav_i)                  (0 when K_Nav = 0)

Lengths count movement actions (MoveAhead, RotateLeft/Right, LookDown/Up); Done is not counted, neither in
the agent's lengths nor in the optimal ones (see :mod:`tsnav.sim.paths`). A ratio whose both lengths are 0
(e.g. the target is already detected in the first frame) is 1. Values are fractions in [0, 1]; tables
print percentages. Every metric is reported for ALL episodes and for those with ``L* >= 5``. Under the
``lineage`` success protocol SPL and the ``L>=5`` subset count lengths as the lineage's evaluator does
(:mod:`tsnav.protocol`, :func:`long_episode`).

Records are exchanged as JSON Lines, one :class:`EpisodeRecord` per line.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from .atomic import atomic_write_text
from .errors import from_fields
from .protocol import DEFAULT_PROTOCOL, check_protocol, protocol_line, protocol_of, spec

#: Metric names, in the paper's table order.
METRICS = ("SR", "SPL", "SSR", "SSSPL", "NSNPL")


@dataclass
class EpisodeRecord:
    """The outcome of one evaluation episode. Lengths are movement-action counts (Done not counted)."""

    success: bool
    """Suc_i: Done was output in a success state of the target (paper III-A)."""
    path_length: int
    """L_i: movement actions output during the episode (failed ones included)."""
    optimal_length: int
    """L*_i: shortest movement-action count from the start to a success state."""
    entered_pathfinding: bool = False
    """Nav_i: some frame's target confidence exceeded C_target (paper III-B, "Dividing point")."""
    pathfinding_start_step: int | None = None
    """Number of actions taken when the pathfinding stage began (0 = the first frame); None if never."""
    search_path_length: int = 0
    """LSearch_i: movement actions taken in the searching stage (all of them when never switched)."""
    optimal_search_length: int = 0
    """L*Search_i: shortest movement-action count from the start to a state whose frame switches stages."""
    pathfinding_path_length: int | None = None
    """LNav_i: movement actions taken in the pathfinding stage; None if never entered."""
    optimal_pathfinding_length: int | None = None
    """L*Nav_i: shortest movement-action count to success from the state where pathfinding began."""
    room_type: str = "unknown"
    scene: str = ""
    target: str = ""
    start: str = ""
    """Start state key."""
    steps: int = 0
    """All actions output, Done included."""
    episode: int = -1
    """Index of the episode in its episode list."""

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict) -> "EpisodeRecord":
        return from_fields(cls, d, "episode record")


def ratio(opt: np.ndarray, actual: np.ndarray) -> np.ndarray:
    """L* / max(L, L*), elementwise; 1 where both are 0."""
    opt = np.asarray(opt, dtype=np.float64)
    den = np.maximum(np.asarray(actual, dtype=np.float64), opt)
    return np.where(den > 0, opt / np.where(den > 0, den, 1.0), 1.0)


def metric_values(success, entered, path_length, optimal_length, search_length, optimal_search_length,
                  nav_length, optimal_nav_length, protocol: str = DEFAULT_PROTOCOL) -> dict[str, float]:
    """The five metrics of paper IV-A over ``K`` episodes given as ``(K,)`` arrays (the one definition; the
    record-based functions below and the training statistics of :mod:`tsnav.rl.stats` use it). Lengths are
    movement-action counts; ``entered`` is Nav_i. Every metric is 0 when ``K = 0``; NSNPL is 0 when no
    episode entered the pathfinding stage.

    Under the ``lineage`` protocol SPL is the lineage's ``compute_spl``: both lengths count one more
    (states on the shortest path, start included, over actions output with Done), ``(L* + 1) / (L + 1)`` on
    success (:mod:`tsnav.protocol`); the other metrics are the paper's under both."""
    suc = np.asarray(success, dtype=np.float64)
    nav = np.asarray(entered, dtype=np.float64)
    if len(suc) == 0:
        return dict.fromkeys(METRICS, 0.0)
    k_nav = float(nav.sum())
    off = spec(protocol).length_offset
    return {"SR": float(np.mean(suc)),
            "SPL": float(np.mean(suc * ratio(np.asarray(optimal_length, dtype=np.float64) + off,
                                             np.asarray(path_length, dtype=np.float64) + off))),
            "SSR": float(np.mean(nav)),
            "SSSPL": float(np.mean(nav * ratio(optimal_search_length, search_length))),
            "NSNPL": float(np.sum(suc * nav * ratio(optimal_nav_length, nav_length)) / k_nav) if k_nav else 0.0}


def _col(records: Sequence[EpisodeRecord], name: str, default=0) -> np.ndarray:
    return np.array([default if getattr(r, name) is None else getattr(r, name) for r in records], dtype=np.float64)


def _values(records: Sequence[EpisodeRecord], protocol: str = DEFAULT_PROTOCOL) -> dict[str, float]:
    return metric_values(*(_col(records, n) for n in (
        "success", "entered_pathfinding", "path_length", "optimal_length", "search_path_length",
        "optimal_search_length", "pathfinding_path_length", "optimal_pathfinding_length")), protocol=protocol)


def sr(records: Sequence[EpisodeRecord]) -> float:
    """Success rate: share of successful episodes (paper IV-A)."""
    return _values(records)["SR"]


def spl(records: Sequence[EpisodeRecord]) -> float:
    """Success weighted by path length (Anderson et al.; paper IV-A)."""
    return _values(records)["SPL"]


def ssr(records: Sequence[EpisodeRecord]) -> float:
    """Searching success rate: share of episodes that entered the pathfinding stage (paper IV-A)."""
    return _values(records)["SSR"]


def ssspl(records: Sequence[EpisodeRecord]) -> float:
    """Searching success weighted by searching path length (the paper's new metric, IV-A)."""
    return _values(records)["SSSPL"]


def nsnpl(records: Sequence[EpisodeRecord]) -> float:
    """Navigation success weighted by navigation path length, averaged over the K_Nav episodes that entered
    the pathfinding stage (paper IV-A); 0 when none did."""
    return _values(records)["NSNPL"]


def metrics(records: Sequence[EpisodeRecord], protocol: str = DEFAULT_PROTOCOL) -> dict:
    """All five metrics plus the counts ``episodes`` (K) and ``K_nav``."""
    return {**_values(records, protocol), "episodes": len(records),
            "K_nav": int(sum(bool(r.entered_pathfinding) for r in records))}


def long_episode(optimal_length: int, min_optimal_length: int = 5, protocol: str = DEFAULT_PROTOCOL) -> bool:
    """Whether an episode belongs to the ``L>=5`` subset: ``L* >= min_optimal_length`` in movement actions
    (``paper``), or the lineage's ``best_path_len >= min_optimal_length`` with its path length counted in
    states, ``L* + 1`` (``lineage``; its ``GreaterThan/5`` bucket)."""
    return optimal_length + spec(protocol).length_offset >= min_optimal_length


def summarize(records: Sequence[EpisodeRecord], min_optimal_length: int = 5, by_room_type: bool = True,
              protocol: str = DEFAULT_PROTOCOL) -> dict:
    """Metrics for ``ALL`` episodes and for ``L>=5`` (:func:`long_episode`), optionally also per room type
    (``rooms: {room: {"ALL": .., "L>=5": ..}}``), counted under the success ``protocol`` (recorded as
    ``protocol``; it sets SPL's and the subset's length convention, :mod:`tsnav.protocol`)."""
    protocol = check_protocol(protocol)
    label = f"L>={min_optimal_length}"
    long_ = [r for r in records if long_episode(r.optimal_length, min_optimal_length, protocol)]
    out = {"ALL": metrics(records, protocol), label: metrics(long_, protocol),
           "min_optimal_length": min_optimal_length, "protocol": protocol}
    if by_room_type:
        rooms = sorted({r.room_type for r in records})
        out["rooms"] = {rt: {"ALL": metrics([r for r in records if r.room_type == rt], protocol),
                             label: metrics([r for r in long_ if r.room_type == rt], protocol)} for rt in rooms}
    return out


def format_table(summary: dict, trained: str | None = None) -> str:
    """A plain-text table of a :func:`summarize` result in percent, like the paper's Table II, headed by the
    protocol it was counted under (and the one the agent was trained under, ``trained``, when given)."""
    label = f"L>={summary.get('min_optimal_length', 5)}"
    rows = [("ALL", summary["ALL"]), (label, summary[label])]
    for rt, sub in summary.get("rooms", {}).items():
        rows += [(f"{rt} ALL", sub["ALL"]), (f"{rt} {label}", sub[label])]
    width = max(len(r[0]) for r in rows)
    head = f"{'subset':<{width}}  " + "  ".join(f"{m:>6}" for m in METRICS) + f"  {'K':>6}  {'K_nav':>6}"
    lines = [protocol_line(protocol_of(summary), trained), head, "-" * len(head)]
    for name, m in rows:
        lines.append(f"{name:<{width}}  " + "  ".join(f"{100 * m[k]:6.2f}" for k in METRICS)
                     + f"  {m['episodes']:>6d}  {m['K_nav']:>6d}")
    return "\n".join(lines)


def write_records(path: str | Path, records: Iterable[EpisodeRecord]) -> None:
    """Write records as JSON Lines, atomically (temporary file + ``os.replace``)."""
    atomic_write_text(Path(path), "".join(r.to_json() + "\n" for r in records))


def read_records(path: str | Path) -> list[EpisodeRecord]:
    """Read a JSON Lines file of records; ``ValueError`` naming the file and line when malformed."""
    out = []
    with open(path) as f:
        for i, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                out.append(EpisodeRecord.from_dict(json.loads(line)))
            except (json.JSONDecodeError, TypeError, ValueError) as e:
                raise ValueError(f"{path}:{i}: not an episode record ({e})") from None
    return out


def write_json(path: str | Path, obj) -> None:
    """Write ``obj`` as indented JSON, atomically."""
    atomic_write_text(Path(path), json.dumps(obj, indent=2, sort_keys=True) + "\n")
