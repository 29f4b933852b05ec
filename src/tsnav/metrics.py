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

The metrics are one registry (:data:`METRIC_REGISTRY`, names in :data:`METRICS`): each :class:`Metric` is a
function of the episodes' columns (:class:`EpisodeArrays`). Every table (``format_table``, the HTML report,
the release and demo tables), the training log's ``metrics/`` group (:mod:`tsnav.rl.logger`), the convergence
curves (``Metric.curve``) and the claims read it; :func:`register_metric` adds one
(``docs/howto/add-a-metric.md``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_write_text
from .errors import from_fields
from .protocol import DEFAULT_PROTOCOL, check_protocol, protocol_line, protocol_of, spec

#: The paper's five metrics, in its table order (the columns of its Tables II and III).
PAPER_METRICS = ("SR", "SPL", "SSR", "SSSPL", "NSNPL")


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


@dataclass(frozen=True)
class EpisodeArrays:
    """The columns every metric reads, ``(K,)`` float64 arrays over ``K`` episodes (lengths in movement actions,
    see :class:`EpisodeRecord`), and the success ``protocol`` they were counted under."""

    success: np.ndarray
    """Suc_i (1.0 / 0.0)."""
    entered: np.ndarray
    """Nav_i: the episode entered the pathfinding stage (1.0 / 0.0)."""
    path_length: np.ndarray
    """L_i."""
    optimal_length: np.ndarray
    """L*_i."""
    search_length: np.ndarray
    """LSearch_i."""
    optimal_search_length: np.ndarray
    """L*Search_i."""
    nav_length: np.ndarray
    """LNav_i (0 where never entered)."""
    optimal_nav_length: np.ndarray
    """L*Nav_i (0 where never entered)."""
    protocol: str = DEFAULT_PROTOCOL

    @property
    def k_nav(self) -> float:
        """K_Nav: episodes that entered the pathfinding stage."""
        return float(self.entered.sum())


@dataclass(frozen=True)
class Metric:
    """One evaluation metric: a name, what it means, and its value over a set of episodes (a fraction in [0, 1];
    tables print percentages). Registered metrics are computed by :func:`metric_values` for every evaluation,
    selection and training log."""

    name: str
    """Column name in every table and JSON file (``metrics.json``, ``log.jsonl``, ``results.json``)."""
    doc: str
    """One line: what it measures (and the paper's section, if it is the paper's)."""
    value: Callable[[EpisodeArrays], float]
    """The metric over ``K >= 1`` episodes (``K = 0`` gives 0 without calling it)."""
    curve: bool = True
    """Drawn on the convergence curves (``tsnav convergence``)."""


def _spl(e: EpisodeArrays) -> float:
    off = spec(e.protocol).length_offset
    return float(np.mean(e.success * ratio(e.optimal_length + off, e.path_length + off)))


def _nsnpl(e: EpisodeArrays) -> float:
    k_nav = e.k_nav
    return float(np.sum(e.success * e.entered * ratio(e.optimal_nav_length, e.nav_length)) / k_nav) if k_nav else 0.0


#: Every metric by name, in table order (the paper's five first).
METRIC_REGISTRY: dict[str, Metric] = {}


def register_metric(metric: Metric) -> Metric:
    """Add ``metric`` to every table, log and curve (after the ones registered before it)."""
    if not isinstance(metric, Metric):
        raise ValueError(f"{metric!r} is not a tsnav.metrics.Metric")
    if metric.name in METRIC_REGISTRY and METRIC_REGISTRY[metric.name] != metric:
        raise ValueError(f"metric {metric.name!r} is already registered")
    METRIC_REGISTRY[metric.name] = metric
    return metric


class _Names(Sequence):
    """The registry's names, a live read-only view (iterates, indexes and compares like a tuple)."""

    def __getitem__(self, i):
        return tuple(METRIC_REGISTRY)[i]

    def __len__(self) -> int:
        return len(METRIC_REGISTRY)

    def __contains__(self, name) -> bool:
        return name in METRIC_REGISTRY

    def __eq__(self, other) -> bool:
        return tuple(self) == tuple(other) if isinstance(other, (tuple, list, _Names)) else NotImplemented

    def __hash__(self):
        return hash(tuple(self))

    def __repr__(self) -> str:
        return repr(tuple(self))


#: Names of the registered metrics, in table order (a live view of :data:`METRIC_REGISTRY`).
METRICS = _Names()

for _m in (
    Metric("SR", "success rate: share of successful episodes (IV-A)", lambda e: float(np.mean(e.success))),
    Metric("SPL", "success weighted by path length (Anderson et al.; IV-A; the lineage's under `lineage`)", _spl),
    Metric(
        "SSR",
        "searching success rate: share of episodes that entered the pathfinding stage (IV-A)",
        lambda e: float(np.mean(e.entered)),
        curve=False,
    ),
    Metric(
        "SSSPL",
        "searching success weighted by searching path length (IV-A)",
        lambda e: float(np.mean(e.entered * ratio(e.optimal_search_length, e.search_length))),
    ),
    Metric(
        "NSNPL",
        "navigation success weighted by navigation path length, over the K_Nav episodes that "
        "entered the pathfinding stage (IV-A)",
        _nsnpl,
    ),
):
    register_metric(_m)


def curve_metrics() -> tuple[str, ...]:
    """Names of the registered metrics drawn on convergence curves (``Metric.curve``)."""
    return tuple(m.name for m in METRIC_REGISTRY.values() if m.curve)


def metric_values(
    success,
    entered,
    path_length,
    optimal_length,
    search_length,
    optimal_search_length,
    nav_length,
    optimal_nav_length,
    protocol: str = DEFAULT_PROTOCOL,
) -> dict[str, float]:
    """Every registered metric (the paper's five of IV-A, and any added) over ``K`` episodes given as ``(K,)``
    arrays (the one definition; the record-based functions below and the training statistics of
    :mod:`tsnav.rl.stats` use it). Lengths are movement-action counts; ``entered`` is Nav_i. Every metric is 0
    when ``K = 0``; NSNPL is 0 when no episode entered the pathfinding stage.

    Under the ``lineage`` protocol SPL is the lineage's ``compute_spl``: both lengths count one more
    (states on the shortest path, start included, over actions output with Done), ``(L* + 1) / (L + 1)`` on
    success (:mod:`tsnav.protocol`); the other metrics are the paper's under both."""
    cols = [
        np.asarray(c, dtype=np.float64)
        for c in (
            success,
            entered,
            path_length,
            optimal_length,
            search_length,
            optimal_search_length,
            nav_length,
            optimal_nav_length,
        )
    ]
    if len(cols[0]) == 0:
        return dict.fromkeys(METRICS, 0.0)
    episodes = EpisodeArrays(*cols, protocol=protocol)
    return {name: m.value(episodes) for name, m in METRIC_REGISTRY.items()}


#: The :class:`EpisodeRecord` fields :func:`metric_values` reads, in its argument order.
RECORD_COLUMNS = (
    "success",
    "entered_pathfinding",
    "path_length",
    "optimal_length",
    "search_path_length",
    "optimal_search_length",
    "pathfinding_path_length",
    "optimal_pathfinding_length",
)


def record_columns(records: Sequence[EpisodeRecord]) -> np.ndarray:
    """``(8, K)`` float64: the :data:`RECORD_COLUMNS` of ``records`` (None counted 0), the arguments of
    :func:`metric_values` in order."""
    return np.array(
        [[0.0 if getattr(r, c) is None else float(getattr(r, c)) for r in records] for c in RECORD_COLUMNS],
        dtype=np.float64,
    ).reshape(len(RECORD_COLUMNS), len(records))


def _values(records: Sequence[EpisodeRecord], protocol: str = DEFAULT_PROTOCOL) -> dict[str, float]:
    return metric_values(*record_columns(records), protocol=protocol)


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
    return {
        **_values(records, protocol),
        "episodes": len(records),
        "K_nav": int(sum(bool(r.entered_pathfinding) for r in records)),
    }


def long_episode(optimal_length: int, min_optimal_length: int = 5, protocol: str = DEFAULT_PROTOCOL) -> bool:
    """Whether an episode belongs to the ``L>=5`` subset: ``L* >= min_optimal_length`` in movement actions
    (``paper``), or the lineage's ``best_path_len >= min_optimal_length`` with its path length counted in
    states, ``L* + 1`` (``lineage``; its ``GreaterThan/5`` bucket)."""
    return optimal_length + spec(protocol).length_offset >= min_optimal_length


def summarize(
    records: Sequence[EpisodeRecord],
    min_optimal_length: int = 5,
    by_room_type: bool = True,
    protocol: str = DEFAULT_PROTOCOL,
) -> dict:
    """Metrics for ``ALL`` episodes and for ``L>=5`` (:func:`long_episode`), optionally also per room type
    (``rooms: {room: {"ALL": .., "L>=5": ..}}``), counted under the success ``protocol`` (recorded as
    ``protocol``; it sets SPL's and the subset's length convention, :mod:`tsnav.protocol`)."""
    protocol = check_protocol(protocol)
    label = f"L>={min_optimal_length}"
    long_ = [r for r in records if long_episode(r.optimal_length, min_optimal_length, protocol)]
    out = {
        "ALL": metrics(records, protocol),
        label: metrics(long_, protocol),
        "min_optimal_length": min_optimal_length,
        "protocol": protocol,
    }
    if by_room_type:
        rooms = sorted({r.room_type for r in records})
        out["rooms"] = {
            rt: {
                "ALL": metrics([r for r in records if r.room_type == rt], protocol),
                label: metrics([r for r in long_ if r.room_type == rt], protocol),
            }
            for rt in rooms
        }
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
        lines.append(
            f"{name:<{width}}  "
            + "  ".join(f"{100 * m[k]:6.2f}" for k in METRICS)
            + f"  {m['episodes']:>6d}  {m['K_nav']:>6d}"
        )
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
